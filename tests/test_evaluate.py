"""DOF evaluation: AEE against Farneback / exact flow and the baselines, the control gain, the files written,
the shipped weights, and the `pixelmpc evaluate` entry point (the response measures: test_control_response.py)."""

from __future__ import annotations

import json
import math
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import made_once_per_run
from flax import serialization
from test_collect import TINY, collect_tiny  # the dataset tests/test_collect.py collects

from pixelmpc_jax.dynamics import dof, network_weights, vdof
from pixelmpc_jax.learn import aee
from pixelmpc_jax.learn import dataset as D
from pixelmpc_jax.learn import evaluate as E

HORIZON = 12
REQUIRED = ("num_parameters", "aee_px", "aee_exact_px", "baseline_zero_aee_px", "baseline_mean_aee_px")


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    # Through the no-dataset path: the held-out collection into a cache directory, there already (tests/test_collect.py
    # collects the same dataset once per run), so the collection finds its laps and keeps them.
    root = tmp_path_factory.mktemp("heldout") / "cache"
    shutil.copytree(made_once_per_run("tiny_collection", collect_tiny), root)
    return E.heldout_dataset(root, TINY, progress=False)


@pytest.fixture(scope="module")
def shipped():
    return E.load_shipped_dof()


@pytest.fixture(scope="module")
def results(tiny_dir, shipped, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    return out, E.evaluate(shipped, tiny_dir, out, horizon=HORIZON, progress=False)


def test_evaluate_writes_the_required_finite_figures(results):
    out, res = results
    on_disk = json.loads((out / "dof_eval.json").read_text())
    assert on_disk == res
    for key in REQUIRED:
        assert isinstance(res[key], (int, float)) and math.isfinite(res[key]), key
    assert res["num_parameters"] == 34_690
    assert res["frames"] == 40
    ms = res["multistep"]
    for key in ("steps", "mean_px", "std_px", "count", "zero_motion_mean_px"):
        assert len(ms[key]) == HORIZON, key
    assert ms["steps"] == list(range(1, HORIZON + 1))
    assert ms["count"][0] > 0 and all(a >= b for a, b in zip(ms["count"], ms["count"][1:]))
    assert all(math.isfinite(v) and v >= 0 for v, c in zip(ms["mean_px"], ms["count"]) if c)
    for name in ("dof_flow_fields.png", "dof_multistep.png"):
        assert (out / name).stat().st_size > 10_000
    gain = res["control_gain"]
    assert np.shape(gain["data"]) == (2, 3) and np.shape(gain["dof"]) == (2, 3)
    assert np.all(np.isfinite(gain["dof"]))
    assert res["dof_input"] == "command" and gain["input"] == "command" and ms["input"] == "command"
    rot = res["rotation_response"]
    for key in ("yaw_to_u", "pitch_to_v"):
        assert set(rot[key]) == {"dof", "exact", "ratio"} and all(math.isfinite(v) for v in rot[key].values())
    assert rot["frames"] == 40
    rank = res["pixel_cost_rank_correlation"]
    assert set(rank) >= {"median", "q25", "q75"} and rank["samples"] == 512 and rank["steps"] == 40
    assert rank["states"] > 0 and -1.0 <= rank["q25"] <= rank["median"] <= rank["q75"] <= 1.0
    parts = res["multistep_parts"]["mean_px"]
    assert set(parts) == {"dof_rate_response", "exact_rotation", "exact_rotation_dof_rest"}
    for part, values in parts.items():
        assert len(values) == HORIZON and values[0] is not None and math.isfinite(values[0]), part
    assert parts["exact_rotation"] != ms["mean_px"]  # another pixel model, not the DOF again


def test_aee_figures_are_the_aee_modules(results, tiny_dir, shipped):
    """The evaluation's AEE and baselines are aee.py's, which training reports too, on the test laps (baseline
    fitted on the train laps), so the numbers are comparable with the training history."""
    _, res = results
    test = D.load_dataset(tiny_dir, "test")
    train = D.load_dataset(tiny_dir, "train")
    assert res["aee_px"] == pytest.approx(aee.evaluate_aee(shipped, test.q, test.u, test.flow), rel=1e-4)
    assert res["baseline_zero_aee_px"] == pytest.approx(aee.zero_flow_aee(test.q, test.u, test.flow), rel=1e-6)
    baseline = aee.fit_orientation_bin_baseline(train.q, train.u, train.flow)
    assert res["baseline_mean_aee_px"] == pytest.approx(
        aee.orientation_bin_aee(baseline, test.q, test.u, test.flow), rel=1e-5)
    # The Farneback label is close to the exact flow; the DOF is judged against both.
    assert res["farneback_vs_exact_aee_px"] < res["baseline_zero_aee_exact_px"]


def test_shipped_weights_load_and_predict_finite_flows(shipped):
    assert E.shipped_weights_path().stat().st_size < 200_000  # parameters + normalisation only
    assert network_weights.num_trainable_params(shipped) == 34_690
    key_q, key_uv, key_u = jax.random.split(jax.random.key(0), 3)
    q = jax.random.normal(key_q, (64, 4))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    uv = jax.random.uniform(key_uv, (64, 2))
    u = jnp.concatenate([jax.random.normal(key_u, (64, 3)), jnp.full((64, 1), 9.0)], axis=-1)
    uv_dot = jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0))(shipped, q, uv, u)
    assert uv_dot.shape == (64, 2) and bool(jnp.all(jnp.isfinite(uv_dot)))
    assert float(jnp.std(uv_dot)) > 0  # depends on its inputs
    record = E.shipped_dof_record()
    assert record["train_config"]["steps"] >= 1000 and record["calls"]
    assert record["results"]["test_aee_px"] < record["results"]["test_zero_flow_aee_px"]


def test_control_gain_recovers_known_slopes():
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.normal(0.0, 0.3, (500, 3)), rng.normal(12.0, 2.0, (500, 1))], axis=1)
    slopes = np.array([[0.1, -0.2, 1.5], [0.3, -2.5, 0.0]])  # rows du, dv; columns wx, wy, wz
    data = u[:, :3] @ slopes.T + 0.05 * u[:, 3:] + 0.7 + rng.normal(0.0, 0.2, (500, 2))
    gain = E.control_gain(u, data, 0.5 * (data - 0.7))  # a "network" with half the gain everywhere
    np.testing.assert_allclose(gain["data"], slopes, atol=0.05)
    np.testing.assert_allclose(gain["dof"], 0.5 * slopes, atol=0.03)
    assert gain["yaw_to_u"]["ratio"] == pytest.approx(0.5, abs=0.02)
    assert gain["pitch_to_v"]["data"] == pytest.approx(-2.5, abs=0.05)
    assert all(0.8 < r < 1.0 for r in gain["r2_data"])


def test_run_evaluate_gives_the_network_the_input_its_weights_were_trained_on(tmp_path, monkeypatch, shipped):
    path = tmp_path / "flown.msgpack"
    dof.save_checkpoint(path, shipped, {"variant": {"input": "flown", "loss": "polar"}})
    seen = {}
    monkeypatch.setattr(E, "evaluate", lambda params, data, out, **kw: seen.update(kw) or {})
    monkeypatch.setattr(E, "summarise", lambda results: "")
    E.run_evaluate(path, tmp_path, tmp_path)
    assert seen["input"] == "flown"
    E.run_evaluate(None, tmp_path, tmp_path)
    assert seen["input"] == "command"  # the shipped weights: the paper's variant


def test_read_weights_dispatches_on_the_files_format(tmp_path, shipped):
    kind, params, record = E.read_weights(vdof.PACKAGED_VDOF)
    assert kind == "vdof" and isinstance(params, vdof.VDOFParams) and vdof.box_cue_of(record) == "apparent"
    kind, params, record = E.read_weights(E.shipped_weights_path())
    assert kind == "dof"
    assert network_weights.num_trainable_params(params) == network_weights.num_trainable_params(shipped)
    assert dof.checkpoint_variant(record)["input"] == "command"
    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\x00not msgpack at all")
    with pytest.raises(ValueError, match="DOF checkpoint"):  # neither: the DOF reader's one-line error
        E.read_weights(garbage)
    foreign = tmp_path / "foreign.msgpack"
    foreign.write_bytes(serialization.msgpack_serialize({"format": "something.else"}))
    with pytest.raises(ValueError, match="something.else"):
        E.read_weights(foreign)


def test_run_evaluate_of_a_vdof_file_writes_the_dof_evaluations_figures(tiny_dir, tmp_path, results):
    """A vdof file: the DOF evaluation's figures for vdof, and the turned DOF's on the same frames beside them."""
    res = E.run_evaluate(vdof.PACKAGED_VDOF, tiny_dir, tmp_path, horizon=HORIZON, progress=False)
    assert json.loads((tmp_path / "dof_eval.json").read_text()) == res
    assert (tmp_path / "vdof_multistep.png").stat().st_size > 10_000
    _, dof_res = results  # the shipped DOF's evaluation of the same laps
    assert res["model"] == "vdof"
    assert res["num_parameters"] == network_weights.num_trainable_params(vdof.load_packaged_vdof())
    turned = res["comparison_dof"]
    assert turned["variant"] == "turned" and turned["dof_input"] == "flown"
    for figures, name in ((res, "vdof"), (turned, "dof")):
        assert set(figures["multistep"]) == set(dof_res["multistep"]) - {"part"} | {"model"}
        assert figures["multistep"]["count"] == dof_res["multistep"]["count"]  # the same windows
        assert set(figures["multistep_at"]) == set(dof_res["multistep_at"])
        assert set(figures["rotation_response"]["yaw_to_u"]) == {name, "exact", "ratio"}
        assert figures["rotation_response"]["frames"] == dof_res["rotation_response"]["frames"] == 40
        rank = figures["pixel_cost_rank_correlation"]
        assert set(rank) == set(dof_res["pixel_cost_rank_correlation"])
        dof_rank = dof_res["pixel_cost_rank_correlation"]  # the same states
        assert rank["states"] + rank["skipped_constant"] == dof_rank["states"] + dof_rank["skipped_constant"] > 0
        assert rank["samples"] == 512 and rank["steps"] == 40
        assert math.isfinite(figures["target_aee_px"])
    assert res["target_one_step"]["rows"] > 0 and set(res["box_size_rel_err_at"]) == {"1", "10"}
    assert res["data"] == dof_res["data"]
