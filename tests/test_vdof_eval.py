"""`pixelmpc evaluate` of a vdof checkpoint (learn/vdof_eval.py): its figures are the DOF evaluation's, computed the
same way for vdof and the DOF on the same windows, rows and states; on a lap flown by hand towards a gate."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import timing
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.dynamics import dof, quadrotor, vdof
from pixelmpc_jax.learn import control_response as R
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn import vdof_data, vdof_eval
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

HORIZON = 12
DT = timing.CONTROL_DT


@pytest.fixture(scope="module")
def world():
    return course_lib.load_course(), camera_lib.default_camera()


@pytest.fixture(scope="module")
def lap(world):
    """40 frames from the course start towards gate 0 at 8 m/s while weaving (the rates flown are the states')."""
    track, _ = world
    frames = 40
    t = np.arange(frames + 1) * DT
    position = np.asarray(track.start)[:3] + np.outer(t, [0.5, 8.0, 0.2])
    q = jax.vmap(quadrotor.quat_from_euler)(0.1 * np.sin(3 * t), -0.15 + 0.05 * np.cos(2 * t),
                                            np.pi / 2 + 0.2 * np.sin(4 * t))
    states = np.concatenate([position, np.asarray(q), np.gradient(position, DT, axis=0)], 1).astype(np.float32)
    w_flown = dataset_lib.flown_rates(states)
    u = np.c_[w_flown + 0.1, np.full(frames, 9.8)].astype(np.float32)  # the command differs from the rates flown
    return dataset_lib.Lap(None, states[:-1, 3:7], u, states, np.zeros(frames + 1, np.int32), None, None, {}, w_flown)


@pytest.fixture(scope="module")
def models():
    return vdof.load_packaged_vdof(), dof.load_packaged_dof("turned")


def _still(params: vdof.VDOFParams) -> vdof.VDOFParams:
    """The same network with zero weights: p_dot = 0 (the same shapes: nothing recompiles)."""
    return params.replace(weights=jax.tree_util.tree_map(jnp.zeros_like, params.weights))


def test_both_models_are_judged_as_the_dof_evaluation_judges_the_dof(world, lap, models):
    """The DOF's figures are control_response.multistep_error's, for its input; vdof's come from the same windows."""
    track, camera = world
    vdof_params, dof_params = models
    for dof_input in ("flown", "command"):
        figures = vdof_eval.multistep_figures(vdof_params, dof_params, [lap], track, camera, HORIZON, DT, "apparent",
                                              dof_input)
        expected = R.multistep_error(dof_params, [lap], track, camera, HORIZON, DT, input=dof_input)
        got = figures["dof"]["multistep"]
        assert {k: v for k, v in got.items() if k != "model"} == {k: v for k, v in expected.items() if k != "part"}
        assert figures["vdof"]["multistep"]["count"] == expected["count"] and expected["count"][-1] > 0
        assert figures["vdof"]["multistep"]["input"] == "flown"
    assert set(figures["vdof"]["multistep_at"]) == {"1", "10"}  # the steps of 1, 10, 20, 40, 80 the horizon reaches
    assert figures["vdof"]["multistep_at"]["10"]["mean_px"] == figures["vdof"]["multistep"]["mean_px"][9]
    assert figures["vdof"]["multistep"]["mean_px"][-1] < figures["vdof"]["multistep"]["zero_motion_mean_px"][-1]


def test_a_still_vdof_has_the_still_pixels_errors(world, lap, models):
    """A vdof that never moves its state: the pixel's error is the still pixel's, the box's is |s_0 - s_k| / s_k."""
    track, camera = world
    figures = vdof_eval.multistep_figures(_still(models[0]), models[1], [lap], track, camera, HORIZON, DT, "apparent",
                                          "flown")
    ms = figures["vdof"]["multistep"]
    np.testing.assert_allclose(ms["mean_px"], ms["zero_motion_mean_px"], rtol=1e-6)
    p, found, inside = (np.asarray(a) for a in vdof_data.lap_detections(track, camera, lap.states, lap.target))
    starts = np.nonzero(found[:-1] & inside[:-1] & found[1:] & inside[1:])[0]
    rel = np.abs(p[starts, 2] - p[starts + 1, 2]) / p[starts + 1, 2]
    assert figures["box_size_rel_err_at"]["1"]["count"] == starts.size
    assert figures["box_size_rel_err_at"]["1"]["mean"] == pytest.approx(rel.mean(), rel=1e-5)
    one_step = vdof_eval.target_one_step_errors(_still(models[0]), models[1], [lap], track, camera, DT)
    assert one_step["vdof_px"] == pytest.approx(one_step["still_px"], rel=1e-6) and one_step["still_px"] > 0.5


def test_multistep_windows_are_shared_by_both_models(world, lap):
    """Models that never move the pixel have the still pixel's error, vdof and the DOF on the same windows."""
    track, camera = world
    zero = lambda tree: jax.tree_util.tree_map(jnp.zeros_like, tree)  # noqa: E731
    still_vdof = vdof.init_vdof_params(jax.random.key(0), (16, 16))
    still_dof = dof.init_dof_params(jax.random.key(0))
    windows = vdof_eval.multistep_window_errors(still_vdof.replace(weights=zero(still_vdof.weights)),
                                                still_dof.replace(weights=zero(still_dof.weights)), [lap], track,
                                                camera, 5, DT)
    valid = windows["valid"]
    assert valid[:, 4].sum() > 0 and np.array_equal(windows["dof"]["valid"], valid)
    for name in ("vdof", "dof"):
        np.testing.assert_allclose(windows[name]["err"][valid], windows[name]["err_zero"][valid], rtol=1e-5,
                                   atol=1e-6)


def test_target_aee_is_the_error_on_vdofs_label_rows(world, lap, models):
    """On vdof_data.lap_rows' rows: |dt p_dot_predicted - dt p_dot_label| of the centre, in px at the camera's size."""
    track, camera = world
    vdof_params, dof_params = models
    rows = vdof_data.lap_rows(track, camera, lap.states, lap.w_flown, lap.target, DT)
    u = np.c_[rows.w, np.zeros(len(rows.w))].astype(np.float32)
    p_dot = np.asarray(jax.vmap(vdof.pixel_state_velocity, in_axes=(None, 0, 0, 0))(vdof_params, rows.x, rows.p, u))
    scale = np.asarray([camera.width, camera.height])
    expected = np.linalg.norm(DT * (p_dot[:, :2] - rows.p_dot[:, :2]) * scale, axis=1)
    one_step = vdof_eval.target_one_step_errors(vdof_params, dof_params, [lap], track, camera, DT)
    assert one_step["rows"] == len(rows.x) > 30
    assert one_step["vdof_px"] == pytest.approx(expected.mean(), rel=1e-4)
    uv_dot = jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0))(dof_params, rows.x[:, 3:7], rows.p[:, :2],
                                                                    np.c_[rows.w, lap.u[:len(rows.w), 3]])
    dof_expected = np.linalg.norm(DT * (np.asarray(uv_dot) - rows.p_dot[:, :2]) * scale, axis=1)
    assert one_step["dof_px"] == pytest.approx(dof_expected.mean(), rel=1e-4)


def test_vdof_rotation_response_is_its_rate_jacobian_at_any_velocity_and_box(world, lap, models):
    _, camera = world
    vdof_params = models[0]
    rot = R.rotation_response(vdof_params, lap.q, dataset_lib.lap_input(lap, "flown"), camera, DT,
                              velocity_fn=vdof_eval._vdof_image_velocity, name="vdof")
    x, centre = jnp.asarray(lap.states[5]), jnp.asarray([0.5, 0.5, 0.3])  # flying at 8 m/s, a box of 0.3
    jac = jax.jacfwd(lambda w: vdof.pixel_state_velocity(vdof_params, x, centre, jnp.r_[w, 9.8])[:2])(jnp.zeros(3))
    expected = np.asarray(jac) * np.asarray([[camera.width * DT], [camera.height * DT]])
    np.testing.assert_allclose(rot["jacobian_vdof"], expected, rtol=1e-4, atol=1e-5)
    assert set(rot["yaw_to_u"]) == {"vdof", "exact", "ratio"}
    assert rot["yaw_to_u"]["ratio"] == pytest.approx(rot["yaw_to_u"]["vdof"] / (float(camera.fx) * DT), rel=1e-5)


def test_vdof_ranking_starts_from_the_detected_box_state_and_costs_its_pixel(world, lap, models, monkeypatch):
    """A "vdof" that moves its pixel where the target projects ranks the samples as the projection (correlation 1);
    its start state is the detection's [centre, box size] (3,), the projection's its centre."""
    track, camera = world
    gate = track.gate(0)

    def projecting(params, x, p, u):  # vdof's signature; the pixel goes where the gate centre projects next
        x_next = quadrotor.step(x, u, DT, quadrotor.QuadParams())
        uv, _, in_front = camera_lib.project(gate.centre, x_next, camera)
        uv = jnp.where(in_front, uv, pixelmpc_lib.behind_camera_pixel(uv.dtype))
        return jnp.concatenate([(uv - p[:2]) / DT, jnp.zeros(1, p.dtype)])

    res = R.pixel_cost_rank_correlation(None, [lap], track, camera, num_samples=64, stride=10,
                                        velocity_fn=projecting, pixel_model="vdof")
    assert res["states"] == 4 and res["q25"] == pytest.approx(1.0, abs=1e-3)
    starts = R._ranking_starts([lap], track, camera, 10, R.pixel_state_model("vdof").initial)
    p, _, _ = vdof_data.lap_detections(track, camera, lap.states, lap.target)
    np.testing.assert_allclose(np.stack([p0 for _, _, p0 in starts]), np.asarray(p)[[0, 10, 20, 30]], atol=1e-6)
    with pytest.raises(ValueError, match="pixel_model"):
        R.pixel_cost_rank_correlation(None, [lap], track, camera, num_samples=8, pixel_model="projection")
