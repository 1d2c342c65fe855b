"""The velocity-and-depth DOF (dynamics/vdof.py), its data (learn/vdof_data.py) and its training through the one
pipeline (learn/vdof_spec.py, learn/train.py): the box size, the model's structure and transformations, checkpoints,
the rows from the detector, a few training steps in both stages, resume across them, and the weights pinned to
those of the trainer the pipeline replaced."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization
from test_train import assert_pinned

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import dof, quadrotor, vdof
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn import train as train_mod
from pixelmpc_jax.learn import vdof_data
from pixelmpc_jax.learn.train import TrainConfig
from pixelmpc_jax.learn.vdof_spec import VDOFConfig, VDOFData
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

SMALL = (16, 16)
batched_velocity = jax.jit(jax.vmap(vdof.pixel_state_velocity, in_axes=(None, 0, 0, 0)))  # one compilation per shape


@pytest.fixture(scope="module")
def params():
    """Random weights with non-trivial normalisation constants (so they are exercised)."""
    return vdof.init_vdof_params(jax.random.key(1), SMALL, uv_mean=[0.45, 0.3], uv_std=[0.2, 0.15],
                                 velocity_scale=[8.0, 2.0, 1.5], rate_scale=[0.7, 0.5, 0.5], box_scale=0.3,
                                 box_max=2.5, p_dot_scale=[0.4, 0.5, 2.0])


def _samples(n: int, seed: int = 0):
    """n random (x (n, 10), p (n, 3), u (n, 4))."""
    rng = np.random.default_rng(seed)
    eul = rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
    q = np.asarray(jax.vmap(quadrotor.quat_from_euler)(eul[:, 0], eul[:, 1], eul[:, 2]))
    x = np.concatenate([rng.uniform(-5, 5, (n, 3)), q, rng.uniform(-10, 10, (n, 3))], 1).astype(np.float32)
    p = np.concatenate([rng.uniform(0, 1, (n, 2)), rng.uniform(0.02, 1.5, (n, 1))], 1).astype(np.float32)
    u = np.concatenate([rng.uniform(-2, 2, (n, 3)), rng.uniform(5, 15, (n, 1))], 1).astype(np.float32)
    return jnp.asarray(x), jnp.asarray(p), jnp.asarray(u)


# --------------------------------------------------------------------------------------------------
# The equations.
# --------------------------------------------------------------------------------------------------


def test_box_size_of_known_quadrilaterals():
    box_size = jax.jit(vdof.box_size)
    square = jnp.asarray([[0.4, 0.4], [0.6, 0.4], [0.6, 0.6], [0.4, 0.6]])  # TL, TR, BR, BL, side 0.2
    np.testing.assert_allclose(box_size(square), 0.2, rtol=1e-6)
    np.testing.assert_allclose(box_size(square[::-1]), 0.2, rtol=1e-6)  # orientation does not matter
    c, s = np.cos(0.3), np.sin(0.3)
    turned = (square - 0.5) @ jnp.asarray([[c, -s], [s, c]]) + 0.5
    np.testing.assert_allclose(box_size(turned), 0.2, rtol=1e-5)
    np.testing.assert_allclose(box_size(jnp.asarray([[0.0, 0.0], [0.3, 0.0], [0.3, 0.1], [0.0, 0.1]])),
                               np.sqrt(0.03), rtol=1e-6)
    flat = jnp.zeros((4, 2))
    assert float(box_size(flat)) == 0.0
    assert np.all(np.isfinite(jax.grad(vdof.box_size)(flat)))
    batched = jax.vmap(vdof.box_size)(jnp.stack([square, turned]))
    np.testing.assert_allclose(batched, [0.2, 0.2], rtol=1e-5)
    np.testing.assert_allclose(vdof.initial_pixel_state(jnp.asarray([0.5, 0.45]), square, 2.0), [0.5, 0.45, 0.1],
                               rtol=1e-6)


def test_output_shape_and_dtype(params):
    x, p, u = _samples(1)
    p_dot = vdof.pixel_state_velocity(params, x[0], p[0], u[0])
    assert p_dot.shape == (3,) and p_dot.dtype == jnp.float32
    assert np.all(np.isfinite(p_dot))
    with pytest.raises(ValueError, match=r"p must have shape \(3,\)"):
        vdof.pixel_state_velocity(params, x[0], p[0, :2], u[0])
    with pytest.raises(ValueError, match=r"x must have shape \(10,\)"):
        vdof.pixel_state_velocity(params, x, p[0], u[0])


def test_zero_velocity_and_zero_rate_give_zero_p_dot(params):
    x, p, u = _samples(4, seed=2)
    still = x.at[:, 7:].set(0.0)
    no_turn = u.at[:, :3].set(0.0)
    p_dot = batched_velocity(params, still, p, no_turn)
    np.testing.assert_array_equal(p_dot, 0.0)


def test_structure_is_linear_in_rates_and_scaled_velocity(params):
    """uv_dot = s A v_b + B w: linear in w at rest, and the translational part scales with s (below box_max);
    s_dot vanishes with s."""
    x, p, u = _samples(4, seed=3)
    f = batched_velocity
    at_rest = x.at[:, 7:].set(0.0)
    np.testing.assert_allclose(f(params, at_rest, p, 2 * u), 2 * f(params, at_rest, p, u), rtol=1e-5, atol=1e-6)
    no_turn = u.at[:, :3].set(0.0)
    half = p.at[:, 2].multiply(0.5)
    np.testing.assert_allclose(f(params, x, half, no_turn)[:, :2], 0.5 * f(params, x, p, no_turn)[:, :2],
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(f(params, x, p.at[:, 2].set(0.0), u)[:, 2], 0.0, atol=1e-7)
    # the thrust is no input of the model
    np.testing.assert_array_equal(f(params, x, p, u.at[:, 3].set(0.0)), f(params, x, p, u))


def test_body_velocity_undoes_the_attitude():
    q = quadrotor.quat_from_euler(0.1, -0.2, 0.7)
    v_b = jnp.asarray([3.0, -1.0, 0.5])
    x = jnp.concatenate([jnp.zeros(3), q, quadrotor.quat_rotate(q, v_b)])
    np.testing.assert_allclose(vdof.body_velocity(x), v_b, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------------------------------
# The transformations.
# --------------------------------------------------------------------------------------------------


def test_jit_equals_nojit_and_vmap_equals_loop(params):
    x, p, u = _samples(4, seed=4)
    looped = np.stack([vdof.pixel_state_velocity(params, x[k], p[k], u[k]) for k in range(4)])
    batched = batched_velocity(params, x, p, u)
    np.testing.assert_allclose(batched, looped, rtol=1e-5, atol=1e-6)
    jitted = jax.jit(vdof.pixel_state_velocity)(params, x[0], p[0], u[0])
    np.testing.assert_allclose(jitted, looped[0], rtol=1e-5, atol=1e-6)
    with jax.numpy_rank_promotion("raise"):
        jax.jit(vdof.pixel_state_velocity)(params, x[1], p[1], u[1]).block_until_ready()


def test_large_box_stays_finite_in_a_rollout(params):
    """The box size saturates at box_max before it multiplies: a long Euler rollout stays finite."""
    x, p, u = _samples(1, seed=5)

    def step(pk, _):
        pk = pk + timing.CONTROL_DT * vdof.pixel_state_velocity(params, x[0], pk, u[0])
        return pk, pk

    _, traj = jax.lax.scan(step, p[0].at[2].set(2.0), None, length=400)
    assert np.all(np.isfinite(traj))


# --------------------------------------------------------------------------------------------------
# Checkpoints.
# --------------------------------------------------------------------------------------------------


def test_checkpoint_round_trip_is_bit_exact(params, tmp_path):
    path = tmp_path / "vdof.msgpack"
    vdof.save_vdof(path, params, {"steps": 3, "note": "test"})
    loaded, config = vdof.load_vdof(path)
    assert config == {"steps": 3, "note": "test"}
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(loaded), strict=True):
        assert np.asarray(a).dtype == np.asarray(b).dtype
        np.testing.assert_array_equal(a, b)
    x, p, u = _samples(3, seed=6)
    np.testing.assert_array_equal(vdof.pixel_state_velocity(loaded, x[0], p[0], u[0]),
                                  vdof.pixel_state_velocity(params, x[0], p[0], u[0]))
    assert vdof.hidden_sizes_of(loaded.weights) == SMALL
    assert vdof.box_cue_of(config) == "apparent"
    assert vdof.box_cue_of({"train_config": {"box_cue": "per_gate_size"}}) == "per_gate_size"


def test_bad_files_give_a_one_line_value_error(params, tmp_path):
    path = tmp_path / "vdof.msgpack"
    vdof.save_vdof(path, params, {})
    data = path.read_bytes()
    corrupted = tmp_path / "corrupted.msgpack"
    corrupted.write_bytes(data[: len(data) // 2])
    foreign = tmp_path / "foreign.msgpack"
    dof.save_checkpoint(foreign, dof.init_dof_params(jax.random.key(0)), {})
    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\xc1\x00not msgpack")
    expected = {corrupted: "corrupted or truncated", garbage: "corrupted or truncated",
                foreign: "format expected 'pixelmpc_jax.vdof', found 'pixelmpc_jax.dof'"}
    for bad, message in expected.items():
        with pytest.raises(ValueError, match=message) as err:
            vdof.load_vdof(bad)
        assert "\n" not in str(err.value)
    payload = serialization.msgpack_restore(data)
    payload["architecture"] = payload["architecture"].replace('"tanh"', '"relu"')
    mismatched = tmp_path / "mismatched.msgpack"
    mismatched.write_bytes(serialization.msgpack_serialize(payload))
    with pytest.raises(ValueError, match="activation: expected 'tanh', found 'relu'"):
        vdof.load_vdof(mismatched)


# --------------------------------------------------------------------------------------------------
# Rows from the detector, and training.
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def world():
    return course_lib.load_course(), camera_lib.default_camera()


def _hand_made_lap(track, frames: int = 40):
    """States flying from the course start towards gate 0 while weaving; the target turns to gate 1 at the end."""
    t = np.arange(frames + 1) * timing.CONTROL_DT
    start = np.asarray(track.start)
    position = start[:3] + np.outer(t, [0.5, 8.0, 0.2])
    q = jax.vmap(quadrotor.quat_from_euler)(0.1 * np.sin(3 * t), -0.15 + 0.05 * np.cos(2 * t),
                                            np.pi / 2 + 0.2 * np.sin(4 * t))
    velocity = np.gradient(position, timing.CONTROL_DT, axis=0)
    states = np.concatenate([position, np.asarray(q), velocity], 1).astype(np.float32)
    target = np.zeros(frames + 1, np.int32)
    target[-4:] = 1
    return states, dataset_lib.flown_rates(states), target


def test_rows_are_finite_differences_of_the_detector(world):
    track, camera = world
    states, w_flown, target = _hand_made_lap(track)
    rows = vdof_data.lap_rows(track, camera, states, w_flown, target)
    p, found, box_size, detect = [], [], jax.jit(vdof.box_size), jax.jit(detector_lib.detect_from_geometry)
    for x, gate_id in zip(states, target, strict=True):
        det = detect(track.gate(int(gate_id)), jnp.asarray(x), camera)
        p.append(np.r_[np.asarray(det.centre), float(box_size(det.corners))])
        found.append(bool(det.found))
    p, found = np.asarray(p), np.asarray(found)
    keep = [k for k in range(len(w_flown)) if found[k] and found[k + 1] and target[k] == target[k + 1]]
    assert 30 <= len(keep) < len(w_flown)  # the frame where the target changes is left out
    np.testing.assert_allclose(rows.p, p[keep], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rows.p_dot, (p[np.add(keep, 1)] - p[keep]) / timing.CONTROL_DT, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(rows.x, states[keep])
    np.testing.assert_array_equal(rows.w, w_flown[keep])


def test_rows_from_the_detections_a_lap_file_stores_equal_those_from_its_states(world):
    """collect stores the detector's per-frame output; training reads it (older files: from the states)."""
    from pixelmpc_jax.learn import collect
    from pixelmpc_jax.sim import env as env_lib

    track, camera = world
    states, w_flown, target = _hand_made_lap(track)
    stored = collect.lap_detections(env_lib.make_world(track, camera=camera), states, target)
    assert stored["gate_corners"].shape == (len(states), 4, 2) and stored["gate_found"].dtype == bool
    from_file = vdof_data.lap_rows(track, camera, states, w_flown, target, detections=stored)
    from_states = vdof_data.lap_rows(track, camera, states, w_flown, target)
    np.testing.assert_array_equal(from_file.x, from_states.x)
    # two compilations of the same detector: the box size's shoelace area cancels, so a few float32 ulps of the
    # corners show in s at 1e-4 relative, and in its finite difference over 0.025 s
    np.testing.assert_allclose(from_file.p, from_states.p, rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(from_file.p_dot, from_states.p_dot, rtol=1e-2, atol=1e-3)


def _as_lap(states, w_flown, target) -> dataset_lib.Lap:
    return dataset_lib.Lap(None, states[:-1, 3:7], np.c_[w_flown, np.full(len(w_flown), 9.8)], states, target,
                           None, None, {}, w_flown)


def test_rollout_windows_follow_the_detector(world):
    track, camera = world
    states, w_flown, target = _hand_made_lap(track)
    windows = vdof_data.load_windows([_as_lap(states, w_flown, target)], track, camera, steps=5)
    windows = jax.tree_util.tree_map(np.asarray, windows)
    p, found, _ = (np.asarray(a) for a in vdof_data.lap_detections(track, camera, states, target))
    assert windows.x.shape[1:] == (5, 10) and windows.p.shape[1:] == (6, 3)
    starts = np.nonzero(found[:-1] & found[1:] & (target[:-1] == target[1:]))[0]
    assert windows.p.shape[0] == starts.size
    k = np.arange(6)
    for m, s in enumerate(starts):
        expected = (s + k <= len(w_flown)) & (target[np.minimum(s + k, len(w_flown))] == target[s])
        np.testing.assert_array_equal(windows.mask[m], np.cumprod(expected).astype(bool))
        valid = windows.mask[m]
        np.testing.assert_allclose(windows.p[m][valid], p[s + k[valid]], rtol=1e-6, atol=1e-6)
        used = valid[1:]  # x[j] moves p_j to p_{j+1}
        np.testing.assert_array_equal(windows.x[m][used], states[s + k[:-1][used]])
    assert not np.all(windows.mask)  # windows reaching the target change end there


@pytest.fixture(scope="module")
def hand_made_data(world) -> VDOFData:
    """The hand-made lap's rows and 5-step windows, as the pipeline trains on them."""
    track, camera = world
    states, w_flown, target = _hand_made_lap(track)
    lap = _as_lap(states, w_flown, target)
    rows = vdof_data.lap_rows(track, camera, states, w_flown, target)
    return VDOFData(rows, vdof_data.load_windows([lap], track, camera, steps=5), [lap])


def _small(steps: int = 100, rollout_train_steps: int = 100, log_every: int = 50, **loop) -> TrainConfig:
    model = VDOFConfig(hidden_sizes=SMALL, steps=steps, batch_size=32, rollout_steps=5,
                       rollout_train_steps=rollout_train_steps, rollout_batch_size=16)
    return TrainConfig(model, log_every=log_every, checkpoint_every=0, progress=False, **loop)


def test_a_few_training_steps_lower_the_loss_in_both_stages(hand_made_data):
    params, history = train_mod.train(_small(), hand_made_data)
    assert history["stage"] == ["one_step"] * 2 + ["rollout"] * 2 and history["step"] == [50, 100, 150, 200]
    assert history["probe_stage"] == ["one_step"] * 3 + ["rollout"] * 3
    assert history["probe_step"] == [0, 50, 100, 100, 150, 200]
    probe = history["probe_loss"]
    assert probe[2] < 0.5 * probe[0]  # the one-step MSE over every row
    assert probe[-1] < probe[3]  # the rollout loss over every window
    assert history["test_probe_loss"] == [None] * 6 and "results" not in history
    assert vdof.hidden_sizes_of(params.weights) == SMALL
    # held-out rows without held-out windows: the one-step stage's probe has them, the rollout stage's not
    held_out = hand_made_data._replace(windows=None)
    one_step, rollout = _small().model.spec().stage_data(hand_made_data, held_out, 0)
    assert one_step.test_probe is not None and rollout.test_probe is None


@pytest.mark.parametrize("chunks", [3, 4], ids=["at the stage boundary", "inside the rollout stage"])
def test_resume_across_the_stages_equals_an_uninterrupted_run(hand_made_data, tmp_path, monkeypatch, chunks):
    """Interrupted after ``chunks`` chunks of 20 steps (60 one-step + 40 rollout steps in all), saved, resumed: the
    weights of the uninterrupted run, bit for bit (the rollout stage's own Adam state starts fresh at step 60)."""
    full, _ = train_mod.train(_small(60, 40, 20), hand_made_data)
    path = tmp_path / "vdof_checkpoint.msgpack"
    config = _small(60, 40, 20, checkpoint_path=str(path))
    real, calls = train_mod.train_chunk, []

    def interrupted(*args, **kwargs):
        if len(calls) == chunks:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(train_mod, "train_chunk", interrupted)
    _, history = train_mod.train(config, hand_made_data)
    assert history["interrupted"] and vdof.read_vdof_checkpoint(path).config["step"] == 20 * chunks
    monkeypatch.undo()
    resumed, history = train_mod.train(config, hand_made_data, resume_from=path)
    assert history["step"] == [20, 40, 60, 80, 100] and not history["interrupted"]
    chex.assert_trees_all_equal(full, resumed)


# at the test run's cheapest compilation its fingerprints came to 54 % of their tolerance (112 % with the LLVM
# modules split), its training data rounded otherwise: it runs as a user's run compiles (tests/conftest.py)
# ~35 s (compiled as shipped, a process of its own): test_a_few_training_steps_lower_the_loss_in_both_stages and
# test_resume_across_the_stages_equals_an_uninterrupted_run cover the pipeline; this pins its weights bit for bit
@pytest.mark.slow
@pytest.mark.compiled_as_shipped
def test_the_pipeline_trains_vdof_as_the_trainer_it_replaced(hand_made_data):
    """60 one-step and 40 rollout steps on the hand-made lap give the weights the trainer the pipeline replaced
    (learn/vdof_train.py of commit bf10cee: ``VDOFTrainConfig(hidden_sizes=(16, 16), steps=60, batch_size=32,
    log_every=20, rollout_steps=5, rollout_train_steps=40, rollout_batch_size=16)``, ``train(config, rows, None,
    windows, None)``) recorded (bit for bit equal there on this CPU; tests/data/train_pinned.npz holds their
    fingerprints, test_train.assert_pinned)."""
    params, _ = train_mod.train(_small(60, 40, 20), hand_made_data)
    assert_pinned(params.weights, "vdof")
