"""The learning curve (learn/curves.py): which curves a training history gives, per stage, and the PNG."""

from __future__ import annotations

import numpy as np
import pytest

from pixelmpc_jax.learn import curves


def _history(with_test: bool = False) -> dict:
    steps = [100, 200, 300, 400]
    history = {"step": steps, "loss": [1.0, 0.6, 0.5, 0.45], "loss_window": [1.2, 0.7, 0.55, 0.47],
               "probe_step": [0, *steps], "probe_loss": [2.0, 0.9, 0.6, 0.5, 0.44], "interrupted": False,
               "results": {"test_aee_px": 2.31, "test_zero_flow_aee_px": 4.8}}
    if with_test:
        history["test_probe_loss"] = [2.1, 1.0, 0.8, None, 0.7]  # a missing value is left out
    return history


def test_curves_follow_the_history():
    found = curves.learning_curves(_history())
    assert list(found) == ["training loss (mean over the log window)", "training probe (no dropout)"]
    steps, values, _ = found["training probe (no dropout)"]
    np.testing.assert_array_equal(steps, [0, 100, 200, 300, 400])
    np.testing.assert_array_equal(values, [2.0, 0.9, 0.6, 0.5, 0.44])
    held_out = curves.learning_curves(_history(with_test=True))["held-out probe (no dropout)"]
    np.testing.assert_array_equal(held_out[0], [0, 100, 200, 400])
    np.testing.assert_array_equal(held_out[1], [2.1, 1.0, 0.8, 0.7])
    assert curves.stage_starts(_history()) == []


def _two_stage_history() -> dict:
    """vdof's: a one-step stage to step 200, then a rollout stage to 300 (both probes logged at 200)."""
    return {"step": [100, 200, 250, 300], "stage": ["one_step"] * 2 + ["rollout"] * 2,
            "loss_window": [1.0, 0.5, 2.0, 1.5], "probe_step": [0, 100, 200, 200, 250, 300],
            "probe_stage": ["one_step"] * 3 + ["rollout"] * 3, "probe_loss": [3.0, 1.0, 0.4, 2.5, 1.8, 1.2],
            "test_probe_loss": [3.1, 1.2, 0.6, 2.8, None, 1.6], "interrupted": False}


def test_a_history_of_several_stages_gives_one_curve_per_stage():
    found = curves.learning_curves(_two_stage_history())
    assert list(found) == [f"{label}, {stage}" for label in ("training loss (mean over the log window)",
                                                             "training probe (no dropout)",
                                                             "held-out probe (no dropout)")
                           for stage in ("one_step", "rollout")]
    steps, values, _ = found["training probe (no dropout), rollout"]
    np.testing.assert_array_equal(steps, [200, 250, 300])
    np.testing.assert_array_equal(values, [2.5, 1.8, 1.2])
    np.testing.assert_array_equal(found["held-out probe (no dropout), rollout"][0], [200, 300])
    assert curves.stage_starts(_two_stage_history()) == [(200.0, "rollout")]


def test_curves_skip_what_is_missing_or_mismatched():
    assert curves.learning_curves({}) == {}
    assert curves.learning_curves({"step": [1, 2], "loss_window": [1.0]}) == {}  # lengths disagree
    assert curves.learning_curves({"step": [1], "loss_window": [0.0]}) == {}  # not on a log axis


@pytest.mark.parametrize("history", [_history(), _history(with_test=True), _two_stage_history(), {"interrupted": True}],
                         ids=["train", "train+held-out", "two stages", "empty"])
def test_plot_writes_a_png(tmp_path, history):
    path = tmp_path / "learning_curve.png"
    curves.plot_learning_curve(history, path, title="vdof learning curve", note="held-out figures; in two lines")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
