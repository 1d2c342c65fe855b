"""The DOF's response to the controls: the rotation response against the pinhole camera, the pixel-cost
ranking of sampled control sequences, and the multi-step pixel error (Fig. 7), on stubs and networks with a
known response and on a lap flown by hand past a gate."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import timing
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn import control_response as R
from pixelmpc_jax.learn.dataset import Lap
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course

HORIZON = 12


@pytest.fixture(scope="module")
def camera():
    return camera_lib.default_camera()


@pytest.fixture(scope="module")
def straight():
    return course.straight_course(num_gates=2)  # the first gate 20 m ahead of the start, at its height


@pytest.fixture(scope="module")
def laps():
    """One lap flown by hand: 40 frames level at 10 m/s along +x, 2 m beside the gates' line, towards gate 1
    (seen all the way, its centre moving out from the image centre as the drone closes in)."""
    frames = 40
    states = np.tile(np.asarray(quadrotor.hover_state((0.0, 2.0, 3.0), yaw=0.0)), (frames + 1, 1))
    states[:, 0] = 10.0 * timing.CONTROL_DT * np.arange(frames + 1)
    states[:, 7] = 10.0
    states = states.astype(np.float32)
    u = np.tile(np.asarray([0.0, 0.0, 0.0, 9.81], np.float32), (frames, 1))
    return [Lap(flow=None, q=states[:frames, 3:7], u=u, states=states, target=np.zeros(frames + 1, np.int32),
                exact_flow=None, exact_valid=None, info={}, w_flown=np.zeros((frames, 3), np.float32))]


def test_multistep_with_a_still_pixel_model_equals_the_zero_motion_error(laps, straight, camera):
    """A DOF predicting no motion keeps the start pixel, so its error is the pixel's true displacement."""
    still = dof.load_packaged_dof().replace(output_mean=jnp.zeros(2), output_std=jnp.asarray([1e-20, 1.0]))
    ms = R.multistep_error(still, laps, straight, camera, horizon=HORIZON)
    counted = [k for k in range(HORIZON) if ms["count"][k]]
    assert counted
    np.testing.assert_allclose([ms["mean_px"][k] for k in counted],
                               [ms["zero_motion_mean_px"][k] for k in counted], rtol=1e-5, atol=1e-4)
    assert ms["zero_motion_mean_px"][counted[-1]] > ms["zero_motion_mean_px"][0]
    assert ms["starts"] == 40 and ms["count"][0] == 40  # every frame starts one; the gate stays in view


def test_multistep_parts_on_a_lap_that_only_turns(straight, camera):
    """Hovering in place while yawing at 0.3 rad/s: the exact rotational flow predicts the gate centre to a
    hundredth of a pixel, with or without a still DOF's zero-rate flow added; a still DOF's response to the
    rates is no motion, so its error is the zero-motion error, which grows to several pixels."""
    frames, rate = 40, 0.3
    yaw = rate * timing.CONTROL_DT * np.arange(frames + 1)
    states = np.stack([np.asarray(quadrotor.hover_state((0.0, 0.5, 3.0), yaw=float(a))) for a in yaw])
    states = states.astype(np.float32)
    u = np.tile(np.asarray([0.0, 0.0, rate, 9.81], np.float32), (frames, 1))
    lap = Lap(flow=None, q=states[:frames, 3:7], u=u, states=states, target=np.ones(frames + 1, np.int32),
              exact_flow=None, exact_valid=None, info={}, w_flown=u[:, :3].copy())
    still = dof.load_packaged_dof().replace(output_mean=jnp.zeros(2), output_std=jnp.asarray([1e-20, 1.0]))
    parts = {part: R.multistep_error(still, [lap], straight, camera, horizon=HORIZON, input="flown", part=part)
             for part in R.PIXEL_MODEL_PARTS}
    for part in ("exact_rotation", "exact_rotation_dof_rest"):
        assert max(parts[part]["mean_px"]) < 0.01, part
    zero = parts["dof_rate_response"]["zero_motion_mean_px"]
    np.testing.assert_allclose(parts["dof_rate_response"]["mean_px"], zero, atol=1e-4)
    assert zero[-1] > 3.0
    with pytest.raises(ValueError, match="part"):
        R.multistep_error(still, [lap], straight, camera, horizon=HORIZON, part="nothing")


def test_multistep_error_refuses_a_lap_whose_arrays_disagree(laps, straight, camera):
    """A lap with one state fewer than its controls would be read past its end (JAX clamps the index)."""
    shipped = dof.load_packaged_dof()
    with pytest.raises(AssertionError, match="shape"):
        R.multistep_error(shipped, [laps[0]._replace(states=laps[0].states[:-1])], straight, camera, horizon=HORIZON)


def test_exact_rotation_response_is_the_pinhole_cameras(camera):
    exact = R.exact_rotation_response(camera)
    dt = timing.CONTROL_DT
    fx, fy = float(camera.fx), float(camera.fy)
    np.testing.assert_allclose(exact, [[0.0, 0.0, fx * dt], [0.0, -fy * dt, 0.0]], atol=1e-4)
    assert exact[0, 2] == pytest.approx(2.73, abs=0.01)  # px/frame per rad/s at 204 x 153 and 1/40 s


def _frames(n=37, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    u = np.concatenate([rng.normal(0.0, 1.5, (n, 3)), rng.uniform(5, 15, (n, 1))], axis=1).astype(np.float32)
    return q, u


def test_rotation_response_measures_a_stub_with_a_known_response(camera):
    """A pixel velocity linear in the rates (px/frame per rad/s given) is measured as exactly that, with the
    image-size and frame-time scaling, signs and the ratio to the exact response."""
    dt = timing.CONTROL_DT
    A = np.array([[0.3, -0.2, 2.0], [0.1, -2.5, 0.4]])  # px/frame per rad/s; rows du, dv; columns wx, wy, wz
    to_normalised = np.array([camera.width * dt, camera.height * dt])[:, None]

    def stub(params, q, uv, u):  # normalised units per second; an attitude- and thrust-dependent offset
        return jnp.asarray(A / to_normalised, jnp.float32) @ u[:3] + params * q[:2] + 0.01 * u[3]

    q, u = _frames()
    rot = R.rotation_response(jnp.asarray(0.7), q, u, camera, dt, velocity_fn=stub, chunk=16)
    np.testing.assert_allclose(rot["jacobian_dof"], A, atol=1e-5)
    np.testing.assert_allclose(rot["jacobian_dof_std"], 0.0, atol=1e-5)
    assert rot["yaw_to_u"]["dof"] == pytest.approx(2.0, abs=1e-5)
    assert rot["yaw_to_u"]["ratio"] == pytest.approx(2.0 / (float(camera.fx) * dt), rel=1e-5)
    assert rot["pitch_to_v"]["dof"] == pytest.approx(-2.5, abs=1e-5)
    assert rot["pitch_to_v"]["ratio"] == pytest.approx(2.5 / (float(camera.fy) * dt), rel=1e-5)
    assert rot["frames"] == 37


def _linear_network(k_yaw: float, k_pitch: float = 0.0, theta: float = 0.0) -> dof.DOFParams:
    """DOF parameters built so that l = k_yaw wz + k_pitch wy (ReLU units kept positive by a bias) and
    theta is the constant ``theta``: the pixel velocity is l (cos theta, sin theta), linear in the rates."""
    params = dof.init_dof_params(jax.random.key(0))
    w = jax.tree_util.tree_map(jnp.zeros_like, params.weights)
    big = 100.0
    w["Dense_0"]["kernel"] = w["Dense_0"]["kernel"].at[8, 0].set(1.0).at[7, 1].set(1.0)  # wz, wy
    w["Dense_0"]["bias"] = w["Dense_0"]["bias"].at[:2].set(big)
    for name in ("Dense_1", "Dense_2"):
        w[name]["kernel"] = w[name]["kernel"].at[0, 0].set(1.0).at[1, 1].set(1.0)
    w["Dense_3"]["kernel"] = w["Dense_3"]["kernel"].at[0, 0].set(k_yaw).at[1, 0].set(k_pitch)
    w["Dense_3"]["bias"] = w["Dense_3"]["bias"].at[0].set(-big * (k_yaw + k_pitch)).at[1].set(theta)
    return params.replace(weights=w)


def test_rotation_response_measures_a_network_with_a_known_response(camera):
    """Through the real network and its normalisation: l = k wz (theta 0) moves u by k per rad/s of yaw."""
    dt = timing.CONTROL_DT
    k = 1.3 / (camera.width * dt)  # 1.3 px/frame per rad/s
    q, u = _frames()
    rot = R.rotation_response(_linear_network(k), q, u, camera, dt)
    assert rot["yaw_to_u"]["dof"] == pytest.approx(1.3, rel=1e-4)
    assert rot["yaw_to_u"]["ratio"] == pytest.approx(1.3 / (float(camera.fx) * dt), rel=1e-4)
    assert rot["pitch_to_v"]["dof"] == pytest.approx(0.0, abs=1e-6)
    # theta = pi/2: the flow points down the image (v), l = k wy
    k = -2.0 / (camera.height * dt)
    rot = R.rotation_response(_linear_network(0.0, k, theta=float(np.pi / 2)), q, u, camera, dt)
    assert rot["pitch_to_v"]["dof"] == pytest.approx(-2.0, rel=1e-4)
    assert rot["pitch_to_v"]["ratio"] == pytest.approx(2.0 / (float(camera.fy) * dt), rel=1e-4)
    assert rot["yaw_to_u"]["dof"] == pytest.approx(0.0, abs=1e-5)


def test_rankdata_and_spearman():
    np.testing.assert_array_equal(R.rankdata(np.array([3.0, 1.0, 4.0, 1.0, 5.0])), [3.0, 1.5, 4.0, 1.5, 5.0])
    np.testing.assert_array_equal(R.rankdata(np.array([2.0, 2.0, 2.0])), [2.0, 2.0, 2.0])
    x = np.random.default_rng(0).normal(size=200)
    assert R.spearman(x, np.exp(3 * x)) == pytest.approx(1.0)
    assert R.spearman(x, -x**3) == pytest.approx(-1.0)
    assert R.spearman(x, np.ones_like(x)) is None
    # against the textbook formula without ties: 1 - 6 sum d^2 / (n (n^2 - 1))
    y = x + np.random.default_rng(1).normal(size=200)
    d = R.rankdata(x) - R.rankdata(y)
    assert R.spearman(x, y) == pytest.approx(1 - 6 * np.sum(d**2) / (200 * (200**2 - 1)), rel=1e-9)


def test_pixel_cost_ranking_is_one_for_a_model_ranking_as_the_projection(laps, straight, camera, monkeypatch):
    """Sequences sampled around the logged commands: the DOF's pixel cost is ranked against the exact
    projection's. A pixel model equal to the projection's ranks the samples identically (correlation 1);
    one that holds the pixel still gives constant costs and is skipped."""
    still = lambda params, q, uv, u: jnp.zeros(2, uv.dtype)  # noqa: E731
    res = R.pixel_cost_rank_correlation(None, laps, straight, camera, num_samples=64, stride=10,
                                        velocity_fn=still)
    assert res["states"] == 0 and res["skipped_constant"] > 0 and res["median"] is None
    pair = R._pixel_cost_pair_fn  # the projection's cost in both places: identical rankings

    def projection_twice(config, velocity_fn=None, pixel_model="dof"):
        fn = pair(config, velocity_fn, pixel_model)

        def both(*args):
            _, exact = fn(*args)
            return exact * 2.0 + 1.0, exact
        return both

    monkeypatch.setattr(R, "_pixel_cost_pair_fn", projection_twice)
    res = R.pixel_cost_rank_correlation(None, laps, straight, camera, num_samples=64, stride=10,
                                        velocity_fn=still)
    assert res["states"] > 0 and res["median"] == pytest.approx(1.0) and res["q25"] == pytest.approx(1.0)


def test_sampled_sequences_follow_the_mppi_sampler():
    config = pixelmpc_lib.paper_mppi_config(num_samples=4096, horizon=40)
    plan = jnp.tile(jnp.asarray([0.5, -0.2, 0.1, 10.0]), (40, 1))
    controls = R.sample_control_sequences(jax.random.key(0), plan, config)
    assert controls.shape == (4096, 40, 4)
    np.testing.assert_array_equal(controls[0], plan)  # the nominal sample
    np.testing.assert_allclose(np.std(np.asarray(controls[1:, :, :3] - plan[:, :3]), axis=(0, 1)),
                               config.noise_sigma[:3], rtol=0.05)
    assert np.all(np.asarray(controls) >= np.asarray(config.u_min) - 1e-6)
    assert np.all(np.asarray(controls) <= np.asarray(config.u_max) + 1e-6)
