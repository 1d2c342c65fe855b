"""The DOF's learning curve (learn/curves.py): which curves a training history gives, and the PNG."""

from __future__ import annotations

import numpy as np
import pytest

from pixelmpc_jax.learn import curves


def _history(with_test: bool = False) -> dict:
    steps = [100, 200, 300, 400]
    history = {"step": steps, "loss": [1.0, 0.6, 0.5, 0.45], "loss_window": [1.2, 0.7, 0.55, 0.47],
               "probe_step": [0, *steps], "probe_loss": [2.0, 0.9, 0.6, 0.5, 0.44], "interrupted": False,
               "test_aee_px": 2.31, "test_zero_flow_aee_px": 4.8}
    if with_test:
        history["test_probe_loss"] = [2.1, 1.0, 0.8, None, 0.7]  # a missing value is left out
    return history


def test_curves_follow_the_history():
    found = curves.learning_curves(_history())
    assert list(found) == ["training loss (mean over the log window)", "training probe batch (no dropout)"]
    steps, values, _ = found["training probe batch (no dropout)"]
    np.testing.assert_array_equal(steps, [0, 100, 200, 300, 400])
    np.testing.assert_array_equal(values, [2.0, 0.9, 0.6, 0.5, 0.44])
    held_out = curves.learning_curves(_history(with_test=True))["held-out probe batch (no dropout)"]
    np.testing.assert_array_equal(held_out[0], [0, 100, 200, 400])
    np.testing.assert_array_equal(held_out[1], [2.1, 1.0, 0.8, 0.7])


def test_curves_skip_what_is_missing_or_mismatched():
    assert curves.learning_curves({}) == {}
    assert curves.learning_curves({"step": [1, 2], "loss_window": [1.0]}) == {}  # lengths disagree
    assert curves.learning_curves({"step": [1], "loss_window": [0.0]}) == {}  # not on a log axis


@pytest.mark.parametrize("history", [_history(), _history(with_test=True), {"interrupted": True}],
                         ids=["train", "train+held-out", "empty"])
def test_plot_writes_a_png(tmp_path, history):
    path = tmp_path / "learning_curve.png"
    curves.plot_learning_curve(history, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
    assert "2.31 px/frame (zero flow 4.80)" in curves._aee_note(_history())
    assert curves._aee_note({"interrupted": True}) == "no held-out AEE (interrupted)"
