"""DOF evaluation: AEE against Farneback / exact flow and the baselines, the multi-step error, the files
written, and the shipped weights."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.learn import dataset as D
from pixelmpc_jax.learn import evaluate as E
from pixelmpc_jax.learn import train as T

TINY = D.CollectConfig(laps=2, max_lap_time_s=1.0, num_samples=64, test_laps=(1,), render_batch=16)
HORIZON = 12
REQUIRED = ("num_parameters", "aee_px", "aee_exact_px", "baseline_zero_aee_px", "baseline_mean_aee_px")


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    # Through the no-dataset path: the held-out collection into a cache directory.
    return E.heldout_dataset(tmp_path_factory.mktemp("heldout"), TINY, progress=False)


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


def test_aee_figures_match_the_training_module(results, tiny_dir, shipped):
    """The evaluation's AEE and baselines are train.py's definitions on the test laps (baseline fitted on
    the train laps), so the numbers are comparable with the training history."""
    _, res = results
    test = D.load_dataset(tiny_dir, "test")
    train = D.load_dataset(tiny_dir, "train")
    assert res["aee_px"] == pytest.approx(T.evaluate_aee(shipped, test.q, test.u, test.flow), rel=1e-4)
    assert res["baseline_zero_aee_px"] == pytest.approx(T.zero_flow_aee(test.q, test.u, test.flow), rel=1e-6)
    baseline = T.fit_orientation_bin_baseline(train.q, train.u, train.flow)
    assert res["baseline_mean_aee_px"] == pytest.approx(
        T.orientation_bin_aee(baseline, test.q, test.u, test.flow), rel=1e-5)
    # The Farneback label is close to the exact flow; the DOF is judged against both.
    assert res["farneback_vs_exact_aee_px"] < res["baseline_zero_aee_exact_px"]


def test_multistep_with_a_still_pixel_model_equals_the_zero_motion_error(tiny_dir, shipped):
    """A DOF predicting no motion keeps the start pixel, so its error is the pixel's true displacement."""
    still = shipped.replace(output_mean=jnp.zeros(2), output_std=jnp.asarray([1e-20, 1.0]))
    world = E.episode_lib.make_world()
    laps = D.load_laps(tiny_dir, "test", with_flow=False)
    ms = E.multistep_error(still, laps, world.track, world.camera, horizon=HORIZON)
    counted = [k for k in range(HORIZON) if ms["count"][k]]
    assert counted
    np.testing.assert_allclose([ms["mean_px"][k] for k in counted],
                               [ms["zero_motion_mean_px"][k] for k in counted], rtol=1e-5, atol=1e-4)
    assert ms["zero_motion_mean_px"][counted[-1]] > ms["zero_motion_mean_px"][0]


def test_shipped_weights_load_and_predict_finite_flows(shipped):
    assert E.shipped_weights_path().stat().st_size < 200_000  # parameters + normalisation only
    assert dof.num_trainable_params(shipped) == 34_690
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


# --------------------------------------------------------------------------------------------------
# Rotation response and pixel-cost ranking.
# --------------------------------------------------------------------------------------------------


def test_exact_rotation_response_is_the_pinhole_cameras():
    camera = E.episode_lib.make_world().camera
    exact = E.exact_rotation_response(camera)
    dt = E.episode_lib.CONTROL_DT
    fx, fy = float(camera.fx), float(camera.fy)
    np.testing.assert_allclose(exact, [[0.0, 0.0, fx * dt], [0.0, -fy * dt, 0.0]], atol=1e-4)
    assert exact[0, 2] == pytest.approx(2.73, abs=0.01)  # px/frame per rad/s at 204 x 153 and 1/40 s


def _frames(n=37, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    u = np.concatenate([rng.normal(0.0, 1.5, (n, 3)), rng.uniform(5, 15, (n, 1))], axis=1).astype(np.float32)
    return q, u


def test_rotation_response_measures_a_stub_with_a_known_response():
    """A pixel velocity linear in the rates (px/frame per rad/s given) is measured as exactly that, with the
    image-size and frame-time scaling, signs and the ratio to the exact response."""
    camera = E.episode_lib.make_world().camera
    dt = E.episode_lib.CONTROL_DT
    A = np.array([[0.3, -0.2, 2.0], [0.1, -2.5, 0.4]])  # px/frame per rad/s; rows du, dv; columns wx, wy, wz
    to_normalised = np.array([camera.width * dt, camera.height * dt])[:, None]

    def stub(params, q, uv, u):  # normalised units per second; an attitude- and thrust-dependent offset
        return jnp.asarray(A / to_normalised, jnp.float32) @ u[:3] + params * q[:2] + 0.01 * u[3]

    q, u = _frames()
    rot = E.rotation_response(jnp.asarray(0.7), q, u, camera, dt, velocity_fn=stub, chunk=16)
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


def test_rotation_response_measures_a_network_with_a_known_response():
    """Through the real network and its normalisation: l = k wz (theta 0) moves u by k per rad/s of yaw."""
    camera = E.episode_lib.make_world().camera
    dt = E.episode_lib.CONTROL_DT
    k = 1.3 / (camera.width * dt)  # 1.3 px/frame per rad/s
    q, u = _frames()
    rot = E.rotation_response(_linear_network(k), q, u, camera, dt)
    assert rot["yaw_to_u"]["dof"] == pytest.approx(1.3, rel=1e-4)
    assert rot["yaw_to_u"]["ratio"] == pytest.approx(1.3 / (float(camera.fx) * dt), rel=1e-4)
    assert rot["pitch_to_v"]["dof"] == pytest.approx(0.0, abs=1e-6)
    # theta = pi/2: the flow points down the image (v), l = k wy
    k = -2.0 / (camera.height * dt)
    rot = E.rotation_response(_linear_network(0.0, k, theta=float(np.pi / 2)), q, u, camera, dt)
    assert rot["pitch_to_v"]["dof"] == pytest.approx(-2.0, rel=1e-4)
    assert rot["pitch_to_v"]["ratio"] == pytest.approx(2.0 / (float(camera.fy) * dt), rel=1e-4)
    assert rot["yaw_to_u"]["dof"] == pytest.approx(0.0, abs=1e-5)


def test_rankdata_and_spearman():
    np.testing.assert_array_equal(E.rankdata(np.array([3.0, 1.0, 4.0, 1.0, 5.0])), [3.0, 1.5, 4.0, 1.5, 5.0])
    np.testing.assert_array_equal(E.rankdata(np.array([2.0, 2.0, 2.0])), [2.0, 2.0, 2.0])
    x = np.random.default_rng(0).normal(size=200)
    assert E.spearman(x, np.exp(3 * x)) == pytest.approx(1.0)
    assert E.spearman(x, -x**3) == pytest.approx(-1.0)
    assert E.spearman(x, np.ones_like(x)) is None
    # against the textbook formula without ties: 1 - 6 sum d^2 / (n (n^2 - 1))
    y = x + np.random.default_rng(1).normal(size=200)
    d = E.rankdata(x) - E.rankdata(y)
    assert E.spearman(x, y) == pytest.approx(1 - 6 * np.sum(d**2) / (200 * (200**2 - 1)), rel=1e-9)


def test_pixel_cost_ranking_is_one_for_a_model_ranking_as_the_projection(tiny_dir, monkeypatch):
    """Sequences sampled around the logged commands: the DOF's pixel cost is ranked against the exact
    projection's. A pixel model equal to the projection's ranks the samples identically (correlation 1);
    one that holds the pixel still gives constant costs and is skipped."""
    world = E.episode_lib.make_world()
    laps = D.load_laps(tiny_dir, "test", with_flow=False)
    still = lambda params, q, uv, u: jnp.zeros(2, uv.dtype)  # noqa: E731
    res = E.pixel_cost_rank_correlation(None, laps, world.track, world.camera, num_samples=64, stride=10,
                                        velocity_fn=still)
    assert res["states"] == 0 and res["skipped_constant"] > 0 and res["median"] is None
    pair = E._pixel_cost_pair_fn  # the projection's cost in both places: identical rankings

    def projection_twice(config, velocity_fn=None):
        fn = pair(config, velocity_fn)

        def both(*args):
            _, exact = fn(*args)
            return exact * 2.0 + 1.0, exact
        return both

    monkeypatch.setattr(E, "_pixel_cost_pair_fn", projection_twice)
    res = E.pixel_cost_rank_correlation(None, laps, world.track, world.camera, num_samples=64, stride=10,
                                        velocity_fn=still)
    assert res["states"] > 0 and res["median"] == pytest.approx(1.0) and res["q25"] == pytest.approx(1.0)


def test_sampled_sequences_follow_the_mppi_sampler():
    config = E.pixelmpc_lib.paper_mppi_config(num_samples=4096, horizon=40)
    plan = jnp.tile(jnp.asarray([0.5, -0.2, 0.1, 10.0]), (40, 1))
    controls = E.sample_control_sequences(jax.random.key(0), plan, config)
    assert controls.shape == (4096, 40, 4)
    np.testing.assert_array_equal(controls[0], plan)  # the nominal sample
    np.testing.assert_allclose(np.std(np.asarray(controls[1:, :, :3] - plan[:, :3]), axis=(0, 1)),
                               config.noise_sigma[:3], rtol=0.05)
    assert np.all(np.asarray(controls) >= np.asarray(config.u_min) - 1e-6)
    assert np.all(np.asarray(controls) <= np.asarray(config.u_max) + 1e-6)


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
