"""The learning pipeline (learn/train.py) with the DOF (learn/dof_spec.py, Algorithm 1): targets, loss, a seeded run
that learns, determinism, checkpoints, resume, the `pixelmpc train` entry point, and the weights the pipeline gives
pinned to those of the trainers it replaced."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import json
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn import aee, dof_spec
from pixelmpc_jax.learn import train as train_mod
from pixelmpc_jax.learn.dataset import FlowData
from pixelmpc_jax.learn.dof_spec import Batch, DOFConfig
from pixelmpc_jax.learn.train import TrainConfig
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.world import camera as camera_lib

W, H, DT = 32, 24, 1.0 / 40.0
PINNED = Path(__file__).parent / "data" / "train_pinned.npz"


def rotational_flow_data(n_frames: int, seed: int) -> FlowData:
    """Frames of an analytic flow field driven by the body rates, the pixel and the roll angle.

    In normalised units per second: u_dot = -1.2 wz + 2 wx (v - 0.5) + 0.5 roll,
    v_dot = -1.2 wy - 2 wx (u - 0.5); stored as float16 pixels per frame, like the real data.
    """
    rng = np.random.default_rng(seed)
    eul = rng.uniform(-0.5, 0.5, (n_frames, 3))
    q = np.asarray(jax.vmap(quadrotor.quat_from_euler)(eul[:, 0], eul[:, 1], eul[:, 2]), np.float32)
    u = np.concatenate([rng.uniform(-2, 2, (n_frames, 3)), rng.uniform(5, 15, (n_frames, 1))], 1)
    jj, ii = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    x, y = (ii + 0.5) / W - 0.5, (jj + 0.5) / H - 0.5
    wx, wy, wz = (u[:, k, None, None] for k in range(3))
    u_dot = -1.2 * wz + 2.0 * wx * y + 0.5 * eul[:, 0, None, None]
    v_dot = -1.2 * wy - 2.0 * wx * x
    flow = np.stack([u_dot * W * DT, v_dot * H * DT], -1).astype(np.float16)
    return FlowData(q, u.astype(np.float32), flow)


@pytest.fixture(scope="module")
def train_data():
    return rotational_flow_data(64, seed=0)


@pytest.fixture(scope="module")
def test_data():
    return rotational_flow_data(16, seed=1)


def small_config(**overrides) -> TrainConfig:
    """The loop's and the DOF's settings of a small run, each override set where its field lives."""
    model = dict(steps=300, batch_size=512, learning_rate=3e-3, schedule="constant", width=W, height=H, dt=DT,
                 probe_size=2048, eval_chunk_pixels=4096)
    loop = dict(log_every=50, checkpoint_every=0, progress=False)
    for name, value in overrides.items():
        (loop if name in {f.name for f in dataclasses.fields(TrainConfig)} else model)[name] = value
    return TrainConfig(model=DOFConfig(**model), **loop)


@pytest.fixture(scope="module")
def trained(train_data, test_data):
    return train_mod.train(small_config(), train_data, test_data)


# --------------------------------------------------------------------------------------------------
# Equations.
# --------------------------------------------------------------------------------------------------


def test_flow_to_polar_hand_cases():
    # one image width per second to the right; two image heights per second upwards (v down).
    flow = jnp.asarray([[W * DT, 0.0], [0.0, -2 * H * DT]])
    l, theta = dof_spec.flow_to_polar(flow, W, H, DT)
    np.testing.assert_allclose(l, [1.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(theta, [0.0, -np.pi / 2], atol=1e-6)
    np.testing.assert_allclose(flow_lib.polar_to_flow(l, theta, W, H, DT), flow, atol=1e-5)


def test_training_uses_the_one_polar_conversion_the_tick_and_the_image_size():
    assert dof_spec.flow_to_polar is flow_lib.flow_to_polar
    config = DOFConfig()
    assert config.dt == timing.CONTROL_DT
    assert (config.width, config.height) == (camera_lib.PAPER_WIDTH, camera_lib.PAPER_HEIGHT)


def _batch_with_prediction(params, l_hat, theta_hat, l, theta):
    """A one-row batch and params whose network output is exactly (l_hat, theta_hat)."""
    zero = jax.tree_util.tree_map(jnp.zeros_like, params.weights)
    params = params.replace(weights=zero, output_mean=jnp.asarray([l_hat, theta_hat], jnp.float32))
    batch = Batch(jnp.zeros((1, 10)), jnp.asarray([l], jnp.float32), jnp.asarray([theta], jnp.float32))
    return params, batch


def test_loss_wraps_the_angle_and_ignores_direction_of_zero_flow():
    params = dof.init_dof_params(jax.random.key(0), output_std=[1.0, 1.0])
    # The loss scale is rms(l)^2 = output_mean[0]^2 + output_std[0]^2 = l_hat^2 + 1 here.
    s2 = 2.0
    # pi - 0.01 vs -pi + 0.01: 0.02 rad apart, not 2 pi - 0.02.
    p, b = _batch_with_prediction(params, 1.0, np.pi - 0.01, 1.0, -np.pi + 0.01)
    loss, parts = dof_spec.dof_loss(p.weights, p, b, None)
    np.testing.assert_allclose(loss, 2 * (1 - np.cos(0.02)) / s2, rtol=1e-3)
    assert float(loss) < 1e-3
    # The angle of a zero flow costs nothing; its magnitude still does.
    p, b = _batch_with_prediction(params, 0.5, 2.0, 0.0, 0.0)
    loss, parts = dof_spec.dof_loss(p.weights, p, b, None)
    assert float(parts["loss_theta"]) == 0.0
    np.testing.assert_allclose(parts["loss_l"], 0.25 / 1.25, rtol=1e-6)
    # Small errors: the loss is the squared endpoint error / rms(l)^2.
    p, b = _batch_with_prediction(params, 1.0, 0.01, 1.0, 0.0)
    loss, _ = dof_spec.dof_loss(p.weights, p, b, None)
    np.testing.assert_allclose(loss, (2 * np.sin(0.005)) ** 2 / s2, rtol=1e-3)


def test_endpoint_loss_is_the_flow_vector_error_and_its_minimiser_is_the_mean_vector():
    params = dof.init_dof_params(jax.random.key(0), output_std=[1.0, 1.0])
    # (l_hat, theta_hat) = (1, 0) against (1, pi/2): the vectors are (1, 0) and (0, 1), |error|^2 = 2.
    p, b = _batch_with_prediction(params, 1.0, 0.0, 1.0, np.pi / 2)
    loss, _ = dof_spec.dof_loss(p.weights, p, b, None, "endpoint")
    np.testing.assert_allclose(loss, 2.0 / 2.0, rtol=1e-5)  # / rms(l)^2 = 1 + 1
    # Two equally likely flows for the same input, (2, 1) and (-2, 1) (a translation of unknown sign plus a
    # common shift): the endpoint loss is lowest at their mean (0, 1), the polar loss is not.
    targets_l = jnp.asarray([np.hypot(2, 1)] * 2, jnp.float32)
    targets_theta = jnp.asarray([np.arctan2(1, 2), np.arctan2(1, -2)], jnp.float32)

    zero = jax.tree_util.tree_map(jnp.zeros_like, params.weights)
    batch = Batch(jnp.zeros((2, 10)), targets_l, targets_theta)

    def loss_at(kind, l_hat, theta_hat):  # the output through the last bias, so the loss scale stays rms 1
        weights = {**zero, "Dense_3": {**zero["Dense_3"], "bias": jnp.stack([l_hat, theta_hat])}}
        return dof_spec.dof_loss(weights, params, batch, None, kind)[0]

    lh, th = np.meshgrid(np.linspace(0.0, 3.0, 61), np.linspace(-np.pi, np.pi, 73), indexing="ij")
    lh, th = jnp.asarray(lh.ravel(), jnp.float32), jnp.asarray(th.ravel(), jnp.float32)
    best = {}
    for kind in ("endpoint", "polar"):
        i = int(jnp.argmin(jax.jit(jax.vmap(functools.partial(loss_at, kind)))(lh, th)))
        best[kind] = (float(lh[i]), float(th[i]))
    np.testing.assert_allclose(dof.polar_to_euler(*best["endpoint"]), [0.0, 1.0], atol=0.06)
    assert best["polar"][0] > 2.0  # the polar minimiser keeps the mean LENGTH (sqrt 5), overshooting (0, 1)
    with pytest.raises(ValueError, match="loss"):
        small_config(loss="vector")


def test_normalisation_constants(train_data):
    c = dof_spec.normalisation_constants(train_data, W, H, DT, chunk_frames=5)
    np.testing.assert_allclose(c["input_mean"][:4], train_data.q.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(c["input_mean"][4:6], [0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(c["input_std"][4], np.sqrt((W**2 - 1) / 12) / W, rtol=1e-5)
    l, _ = dof_spec.flow_to_polar(jnp.asarray(train_data.flow), W, H, DT)
    np.testing.assert_allclose(c["output_mean"][0], np.mean(l), rtol=1e-4)
    np.testing.assert_allclose(c["output_std"][0], np.std(l), rtol=1e-3)


def test_bad_data_and_config_raise(train_data):
    with pytest.raises(ValueError, match=r"flow must have shape \(F, H, W, 2\) = \(64, 153, 204, 2\)"):
        train_mod.train(TrainConfig(DOFConfig(steps=1), progress=False), train_data)  # 32 x 24, paper size expected
    params = dof.init_dof_params(jax.random.key(0))
    with pytest.raises(AssertionError, match="shape"):  # (B, 1) targets would broadcast against (B,) outputs
        dof_spec.dof_loss(params.weights, params, Batch(jnp.zeros((3, 10)), jnp.ones((3, 1)), jnp.ones((3, 1))), None)
    with pytest.raises(ValueError, match="schedule"):
        small_config(schedule="linear")
    bad_flow = train_data.flow.copy()
    bad_flow[3, 2, 1, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        train_mod.train(small_config(steps=1), (train_data.q, train_data.u, bad_flow))


# --------------------------------------------------------------------------------------------------
# Behaviour.
# --------------------------------------------------------------------------------------------------


def test_training_learns_and_beats_zero_flow(trained, test_data):
    params, history = trained
    assert history["probe_loss"][-1] < 0.5 * history["probe_loss"][0]
    assert history["probe_loss"][-1] < 0.1
    assert history["step"] == [50, 100, 150, 200, 250, 300] and history["stage"] == ["flow"] * 6
    assert history["probe_step"] == [0, 50, 100, 150, 200, 250, 300]
    assert not history["interrupted"]
    zero = aee.zero_flow_aee(*test_data)
    results = history["results"]
    assert results["test_zero_flow_aee_px"] == pytest.approx(zero)
    assert results["test_aee_px"] < 0.6 * zero
    np.testing.assert_allclose(aee.evaluate_aee(params, *test_data, W, H, DT), results["test_aee_px"], rtol=1e-5)
    assert dof_spec.summary(results) == (f"held-out AEE {results['test_aee_px']:.2f} px/frame (zero flow "
                                         f"{zero:.2f})") and dof_spec.summary(None) == "no held-out AEE"


def test_same_seed_same_params(train_data):
    config = small_config(steps=20, log_every=10)
    a, _ = train_mod.train(config, train_data)
    b, _ = train_mod.train(config, train_data)
    c, _ = train_mod.train(dataclasses.replace(config, seed=1), train_data)
    chex.assert_trees_all_equal(a, b)
    with pytest.raises(AssertionError):
        chex.assert_trees_all_equal(a, c)


def test_resume_continues_from_saved_step(train_data, tmp_path):
    """20 steps, checkpoint, resume to 40 == 40 uninterrupted steps, bit for bit."""
    path = tmp_path / "run.msgpack"
    full, _ = train_mod.train(small_config(steps=40, log_every=10), train_data)
    train_mod.train(small_config(steps=20, log_every=10, checkpoint_path=str(path)), train_data)
    _, config = dof.load_checkpoint(path)
    assert config["step"] == 20 and config["train_config"]["model"]["steps"] == 20 and "command" in config
    resumed, history = train_mod.train(small_config(steps=40, log_every=10), train_data, resume_from=path)
    assert history["step"] == [10, 20, 30, 40]
    chex.assert_trees_all_equal(full, resumed)


def test_keyboard_interrupt_saves_and_returns(train_data, tmp_path, monkeypatch):
    config = small_config(steps=40, log_every=10, checkpoint_path=str(tmp_path / "run.msgpack"))
    real = train_mod.train_chunk
    calls = []

    def interrupted_after_three(*args, **kwargs):  # Ctrl-C during the fourth chunk of 10 steps
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(train_mod, "train_chunk", interrupted_after_three)
    params, history = train_mod.train(config, train_data)
    assert history["interrupted"] and "results" not in history
    saved, record = dof.load_checkpoint(config.checkpoint_path)
    assert record["step"] == 30 and history["step"] == [10, 20, 30]
    chex.assert_trees_all_equal(params, saved)
    monkeypatch.undo()
    _, history = train_mod.train(config, train_data, resume_from=config.checkpoint_path)
    assert history["step"] == [10, 20, 30, 40] and not history["interrupted"]


def test_weights_only_checkpoint_cannot_resume(train_data, tmp_path):
    path = tmp_path / "weights.msgpack"
    dof.save_checkpoint(path, dof.init_dof_params(jax.random.key(0)), {})
    with pytest.raises(ValueError, match="no optimizer state"):
        train_mod.train(small_config(steps=5), train_data, resume_from=path)


def test_input_variant_is_validated_and_recorded_in_the_checkpoint(train_data, tmp_path):
    with pytest.raises(ValueError, match="input"):
        small_config(input="gyro")
    assert DOFConfig().input == "command"  # the paper's by default
    path = tmp_path / "flown.msgpack"
    train_mod.train(small_config(steps=2, log_every=1, checkpoint_path=str(path), input="flown",
                                 loss="endpoint"), train_data)
    _, record = dof.load_checkpoint(path)
    assert record["model"] == "dof" and record["train_config"]["model"]["input"] == "flown"
    assert {k: record["variant"][k] for k in ("input", "loss", "layer_sizes")} == \
        {"input": "flown", "loss": "endpoint", "layer_sizes": [10, 128, 128, 128, 2]}
    assert dof.checkpoint_variant(record) == {"input": "flown", "loss": "endpoint"}


def test_run_train_writes_the_weights_their_record_and_the_history(tmp_path):
    from test_dataset import write_dataset  # a small dataset as collect writes it

    write_dataset(tmp_path / "data", frames=(6, 4))
    out = tmp_path / "out"
    config = TrainConfig(DOFConfig(steps=3, batch_size=64, loss="endpoint", input="flown"), progress=False)
    record = train_mod.run_train(tmp_path / "data", out, config)
    assert record["model"] == "dof" and record["steps_done"] == 3 and not record["interrupted"]
    assert record["variant"]["input"] == "flown" and record["variant"]["loss"] == "endpoint"
    assert np.isfinite(record["results"]["test_aee_px"])
    _, saved = dof.load_checkpoint(out / "dof_weights.msgpack")
    assert saved == json.loads((out / "dof_weights.json").read_text()) == json.loads(json.dumps(record))
    assert json.loads((out / "history.json").read_text())["step"][-1] == 3
    assert (out / "learning_curve.png").stat().st_size > 0  # the curve drawn beside the checkpoints
    assert dof.read_checkpoint(out / "checkpoint.msgpack").extra["train"]  # resumable
    for call in record["calls"]:  # the calls it records name functions that exist
        module, name = call.split("(")[0].rsplit(".", 1)
        assert callable(getattr(importlib.import_module(module), name)), call
    # the recorded run_train call carries the whole config: every setting but those set from the data and out_dir
    call = record["calls"][-1]
    repeated = eval(call[call.index("TrainConfig("):-1], {"TrainConfig": TrainConfig, "DOFConfig": DOFConfig})
    repeated = dataclasses.replace(repeated, model=repeated.model.with_data(json.loads(
        (tmp_path / "data" / "manifest.json").read_text())), checkpoint_path=None, progress=False)
    assert json.loads(json.dumps(dataclasses.asdict(repeated))) == record["train_config"]
    assert repeated.model.steps == 3 and repeated.model.loss == "endpoint" and repeated.model.input == "flown"


def test_run_train_takes_the_image_size_and_dt_from_the_data(tmp_path):
    from test_dataset import write_dataset

    write_dataset(tmp_path / "data", frames=(3,))  # train lap only
    config = TrainConfig(DOFConfig(steps=3, batch_size=64, loss="endpoint", width=7, height=5, dt=1.0),
                         progress=False)
    record = train_mod.run_train(tmp_path / "data", tmp_path / "out", config)
    manifest = json.loads((tmp_path / "data" / "manifest.json").read_text())
    model = record["train_config"]["model"]
    assert [model["width"], model["height"]] == manifest["image_size_wh"] and model["dt"] == manifest["frame_dt_s"]
    assert record["train_config"]["checkpoint_path"] is None and record["results"] == {}



def test_rotation_augment_is_validated():
    with pytest.raises(ValueError, match="input='flown'"):
        DOFConfig(rotation_augment=1.0, input="command")
    with pytest.raises(ValueError, match="rotation_augment"):
        DOFConfig(rotation_augment=-1.0, input="flown")
    with pytest.raises(ValueError, match="rotation_augment"):
        DOFConfig(rotation_augment=1.0, rotation_augment_fraction=1.5, input="flown")


def test_turned_rows_carry_the_flow_of_their_rate():
    """Frames of a still camera (zero flow, zero rate): every turned row's label must be exactly the
    rotational flow of the rate written in its features, and the rates must have the configured spread."""
    W, H = camera_lib.PAPER_WIDTH, camera_lib.PAPER_HEIGHT
    frames = 4
    q = np.tile(np.asarray([[1.0, 0.0, 0.0, 0.0]], np.float32), (frames, 1))
    u = np.tile(np.asarray([[0.0, 0.0, 0.0, 9.8]], np.float32), (frames, 1))
    data = FlowData(jnp.asarray(q), jnp.asarray(u), jnp.zeros((frames, H, W, 2), jnp.float16))
    config = DOFConfig(input="flown", rotation_augment=1.5, rotation_augment_fraction=1.0)
    batch = dof_spec.sample_batch(data, jax.random.key(0), 2048, config)
    uv, w = batch.features[:, 4:6], batch.features[:, 6:9]
    np.testing.assert_allclose(np.std(np.asarray(w), axis=0), 1.5, rtol=0.1)
    np.testing.assert_allclose(batch.features[:, 9], 9.8)
    camera = camera_lib.default_camera()
    pixel_px = uv * jnp.asarray([W, H])
    from pixelmpc_jax.learn import rotation_augment

    _, expected = jax.vmap(rotation_augment.augment_row, in_axes=(None, 0, None, 0, None, None))(
        jnp.zeros(3), pixel_px, jnp.zeros(2), w, camera, config.dt)
    label = flow_lib.polar_to_flow(batch.l, batch.theta, W, H, config.dt)
    np.testing.assert_allclose(label, expected, atol=2e-3)
    assert float(jnp.mean(jnp.abs(label))) > 1.0  # the rows were turned: a still camera has zero flow


def test_training_with_turned_rows_runs_and_records_it(train_data, tmp_path):
    config = small_config(steps=3, batch_size=64, log_every=1, probe_size=64, input="flown", rotation_augment=1.0,
                          rotation_augment_fraction=0.5, checkpoint_path=str(tmp_path / "ckpt.msgpack"))
    params, history = train_mod.train(config, train_data)
    assert history["step"][-1] == 3 and np.all(np.isfinite(history["loss"]))
    _, record = dof.load_checkpoint(tmp_path / "ckpt.msgpack")
    assert record["train_config"]["model"]["rotation_augment"] == 1.0


# --------------------------------------------------------------------------------------------------
# The weights the pipeline gives, pinned.
# --------------------------------------------------------------------------------------------------


def fingerprint(weights) -> dict[str, np.ndarray]:
    """Per leaf (its path): the sum, the root sum of squares and the projections on 4 seeded random directions
    (float64): any change of what training computes moves them far beyond float rounding."""
    prints = {}
    for path, leaf in traverse_util.flatten_dict(weights).items():
        x = np.asarray(leaf, np.float64).ravel()
        directions = np.random.default_rng(x.size).standard_normal((4, x.size))
        prints["/".join(path)] = np.concatenate([[x.sum(), np.sqrt(x @ x)], directions @ x])
    return prints


def assert_pinned(weights, name: str) -> None:
    """``weights`` match the fingerprints ``name`` in :data:`PINNED`, to float tolerance (relative 1e-4 of each
    leaf's norm: rounding differs across CPUs, XLA versions and compilations; a changed computation moves them by
    order 1). On a 2-core AMD EPYC (family 25 model 17), jax 0.10.2, the two DOF fingerprints came within 0.4 % and
    0.3 % of that tolerance as a user's run compiles, and 0.4 % and 6.6 % at the test run's cheapest compilation
    (tests/conftest.py)."""
    pinned = np.load(PINNED)
    prints = fingerprint(weights)
    assert sorted(prints) == sorted(k.split("/", 1)[1] for k in pinned.files if k.split("/", 1)[0] == name)
    for path, value in prints.items():
        expected = pinned[f"{name}/{path}"]
        np.testing.assert_allclose(value, expected, rtol=1e-4, atol=1e-4 * expected[1], err_msg=f"{name}/{path}")


@pytest.mark.parametrize("name, variant", [
    ("dof", {}),
    ("dof_turned", dict(loss="endpoint", input="flown", rotation_augment=1.0, rotation_augment_fraction=0.5)),
])
def test_the_pipeline_trains_the_dof_as_the_trainer_it_replaced(name, variant):
    """30 seeded steps on fixed frames give the weights today's pipeline replaced (learn/train.py of commit
    bf10cee: ``TrainConfig(steps=30, batch_size=256, learning_rate=3e-3, log_every=10, checkpoint_every=0, width=32,
    height=24, dt=1/40, probe_size=256, eval_chunk_pixels=4096, **variant)`` on ``rotational_flow_data(24, seed=3)``)
    recorded (bit for bit equal there on this CPU; the file holds their fingerprints)."""
    model = DOFConfig(steps=30, batch_size=256, learning_rate=3e-3, width=W, height=H, dt=DT, probe_size=256,
                      eval_chunk_pixels=4096, **variant)
    params, _ = train_mod.train(TrainConfig(model, log_every=10, checkpoint_every=0, progress=False),
                                rotational_flow_data(24, seed=3))
    assert_pinned(params.weights, name)


# --------------------------------------------------------------------------------------------------
# `pixelmpc train --model dof|vdof`.
# --------------------------------------------------------------------------------------------------


def _train_cli(argv, tmp_path, capsys, monkeypatch) -> tuple[int, str, list]:
    """(exit code, stderr, the run_train calls) of ``pixelmpc train --data DIR argv`` with run_train faked."""
    from pixelmpc_jax import cli

    data = tmp_path / "data"
    data.mkdir(exist_ok=True)
    (data / "manifest.json").write_text("{}")
    calls = []
    monkeypatch.setattr(train_mod, "run_train", lambda *a, **k: calls.append((a, k)) or {"interrupted": False})
    try:
        code = cli.main(["train", "--data", str(data), *argv])
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err, calls


@pytest.mark.parametrize("argv, message", [
    (["--box-cue", "per_gate_size"], "argument --box-cue: applies to --model vdof only"),
    (["--model", "vdof", "--loss", "endpoint"], "argument --loss: applies to --model dof only"),
    (["--model", "vdof", "--rotation-augment", "1"], "argument --rotation-augment: applies to --model dof only"),
    (["--model", "vdof", "--hidden-sizes", "32,0"], "argument --hidden-sizes: expected comma-separated widths"),
    (["--model", "vdof", "--rollout-steps", "-1"], "argument --rollout-steps: must be an integer in [0, 1000]"),
    (["--rotation-augment", "1"], "argument --rotation-augment: needs --input flown"),
    (["--model", "cnn"], "argument --model: invalid choice: 'cnn'"),
])
def test_train_refuses_bad_input_in_one_line_before_anything_runs(argv, message, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    code, err, calls = _train_cli([*argv, "--out", str(out)], tmp_path, capsys, monkeypatch)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not calls and not out.exists()


def test_train_flags_make_the_model_config(tmp_path, capsys, monkeypatch):
    """--model dof (the default) keeps today's defaults and output folder; --model vdof takes every option of the
    old vdof trainer as a flag; the loop's seed and progress bar are the same flags for both."""
    from pixelmpc_jax.learn.vdof_spec import VDOFConfig

    code, _, calls = _train_cli([], tmp_path, capsys, monkeypatch)
    (data_dir,), kwargs = calls[0]
    assert code == 0 and kwargs["config"] == TrainConfig(DOFConfig()) and str(kwargs["out_dir"]) == "runs/dof_train"
    argv = ["--steps", "5", "--batch-size", "64", "--learning-rate", "0.01", "--seed", "3", "--no-progress",
            "--input", "flown", "--loss", "endpoint", "--rotation-augment", "1", "--rotation-augment-fraction", "0.5"]
    code, _, calls = _train_cli(argv, tmp_path, capsys, monkeypatch)
    assert calls[0][1]["config"] == TrainConfig(DOFConfig(steps=5, batch_size=64, learning_rate=0.01, input="flown",
                                                          loss="endpoint", rotation_augment=1.0,
                                                          rotation_augment_fraction=0.5), seed=3, progress=False)
    argv = ["--model", "vdof", "--steps", "7", "--hidden-sizes", "16,8", "--box-loss", "absolute", "--box-cue",
            "per_gate_size", "--rollout-steps", "0", "--rollout-train-steps", "9", "--rollout-learning-rate", "0.002",
            "--rollout-batch-size", "8", "--comparison-dof", "flown", "--resume", "--ship", "--out", str(tmp_path)]
    code, _, calls = _train_cli(argv, tmp_path, capsys, monkeypatch)
    assert code == 0 and calls[0][1]["config"] == TrainConfig(VDOFConfig(
        steps=7, hidden_sizes=(16, 8), box_loss="absolute", box_cue="per_gate_size", rollout_steps=0,
        rollout_train_steps=9, rollout_learning_rate=0.002, rollout_batch_size=8, comparison_dof="flown"))
    assert calls[0][1]["resume"] and calls[0][1]["ship"] and calls[0][1]["out_dir"] == tmp_path
    code, _, calls = _train_cli(["--model", "vdof"], tmp_path, capsys, monkeypatch)
    assert calls[0][1]["config"].model == VDOFConfig() and str(calls[0][1]["out_dir"]) == "runs/vdof_train"


def test_a_record_keeps_the_command_as_a_user_types_it_not_the_path_it_ran_from():
    from pixelmpc_jax.platform_info import invocation

    assert invocation(["/opt/venv/bin/pixelmpc", "train", "--data", "my data"]) == "pixelmpc train --data 'my data'"
    assert invocation(["/opt/src/pixelmpc_jax/cli.py", "collect"]) == "python -m pixelmpc_jax.cli collect"
