"""The perception levers of issue 15: the border pixel cost, the behind-camera pixel, the heading weight, coloured
sampling noise, controller options through the race API, and the per-tick causes of low visibility."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.control import costs, sampling
from pixelmpc_jax.control import mppi as mppi_lib
from pixelmpc_jax.control import pixelmpc as PM
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config
from pixelmpc_jax.devices import compile_controller
from pixelmpc_jax.dynamics import quadrotor as Q
from pixelmpc_jax.sim import controllers
from pixelmpc_jax.sim import metrics as M
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import course as course_lib

SMALL = PM.paper_mppi_config(num_samples=32, horizon=12)


def _cost(config, uv):
    return float(PM.pixel_cost(jnp.asarray(uv, jnp.float32), config))


def test_border_cost_is_zero_inside_the_margin_and_one_per_axis_at_the_border():
    config = PM.ControllerConfig(pixel_cost="border", border_margin=0.2, c_pixel=1.0, pixel_cost_scale=1.0)
    assert _cost(config, (0.5, 0.5)) == 0.0
    assert _cost(config, (0.69, 0.31)) == 0.0  # 0.19 from the centre: inside the 0.3 free zone
    assert _cost(config, (1.0, 0.5)) == pytest.approx(1.0)  # at the right border
    assert _cost(config, (0.0, 0.0)) == pytest.approx(2.0)  # a corner: both axes at the border
    assert _cost(config, (0.5, -0.2)) == pytest.approx(((0.7 - 0.3) / 0.2) ** 2)  # past the top border
    # the paper's L1 charges the centred-but-off pixel the border cost leaves free
    l1 = dataclasses.replace(config, pixel_cost="l1")
    assert _cost(l1, (0.69, 0.31)) == pytest.approx(0.38)


@pytest.mark.parametrize("form", ["l1", "border"])
def test_target_behind_the_camera_costs_at_least_the_worst_pixel_in_front(form):
    """The projection model places a target behind the camera at the behind-camera pixel: that must cost at least
    as much as any pixel in front, however far off the image (the clip bounds those)."""
    config = PM.ControllerConfig(pixel_cost=form, pixel_model="projection", c_pixel=1.0, pixel_cost_scale=1.0)
    behind = float(PM.pixel_cost(PM.behind_camera_pixel(), config))
    grid_uv = np.stack(np.meshgrid(np.linspace(-3, 4, 57), np.linspace(-3, 4, 57)), -1).reshape(-1, 2)
    in_front = np.asarray(jax.vmap(lambda uv: PM.pixel_cost(uv, config))(jnp.asarray(grid_uv, jnp.float32)))
    assert behind >= in_front.max() - 1e-5
    assert behind > _cost(config, (0.0, 0.0))  # the old placement (the image corner) cost less than this


def test_projection_model_gives_the_behind_camera_pixel_when_the_gate_is_behind():
    """Flying away from the target gate, the projection model's predicted pixel is the behind-camera pixel."""
    track = course_lib.load_course()
    config = PM.ControllerConfig(mppi=SMALL, pixel_model="projection", t_f=0.1, pixel_cost="border")
    ctrl = compile_controller(PM.make_pixelmpc(config))
    gate = track.gate(0)
    yaw_away = float(np.arctan2(-gate.normal[1], -gate.normal[0]))
    x = Q.hover_state(gate.centre - 5.0 * gate.normal, yaw_away)
    racing = costs.racing_params(track, jnp.zeros((SMALL.horizon,)), 8.0, config.racing)
    params = PM.PixelMPCParams(racing=racing, dof=None, target_active=jnp.asarray(True), target_centre=gate.centre,
                               target_normal=gate.normal, camera=C.default_camera())
    _, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(0), Q.hover_control(Q.QuadParams())),
                           jnp.concatenate([x, jnp.full((2,), 0.5)]), params)
    predicted_uv = np.asarray(info.nominal_trajectory[1:config.pixel_steps + 1, Q.STATE_DIM:])
    np.testing.assert_allclose(predicted_uv, np.broadcast_to(np.asarray(PM.behind_camera_pixel()), predicted_uv.shape))


def test_bad_pixel_cost_options_are_rejected():
    with pytest.raises(ValueError, match="pixel_cost"):
        PM.ControllerConfig(pixel_cost="l2")
    with pytest.raises(ValueError, match="border_margin"):
        PM.ControllerConfig(border_margin=0.0)
    with pytest.raises(ValueError, match="heading_weight"):
        costs.RacingCostConfig(heading_weight=1.5)
    with pytest.raises(ValueError, match="noise_exponent"):
        mppi_lib.MPPIConfig(noise_sigma=(1.0,), noise_exponent=-1.0)


def test_heading_weight_frees_the_heading_but_keeps_the_tilt():
    """With heading_weight 0 a level vehicle yawed off the path pays no attitude cost, a tilted one still does;
    with the paper's weight (1) the yaw offset is charged."""
    track = course_lib.load_course()
    racing_cfg = costs.RacingCostConfig(heading_weight=0.0)
    params = costs.racing_params(track, jnp.zeros((1,)), 0.0, racing_cfg)
    p0 = track.path_points[0]
    path_yaw = float(np.arctan2(track.path_tangents[0, 1], track.path_tangents[0, 0]))

    def cost(config, roll, yaw):
        q = Q.quat_from_euler(roll, 0.0, yaw)
        x = jnp.concatenate([p0, q, jnp.zeros(3)])
        return float(costs.racing_costs(x[None, None], jnp.asarray([0]), params, config)[0, 0])

    free, paper = racing_cfg, costs.RacingCostConfig()
    assert cost(free, 0.0, path_yaw + 0.8) == pytest.approx(cost(free, 0.0, path_yaw), abs=1e-3)
    assert cost(paper, 0.0, path_yaw + 0.8) > cost(paper, 0.0, path_yaw) + 10.0
    # the tilt is charged as the paper charges it at the path's heading: 250 * (2 - 2 cos(0.2)) for 0.4 rad
    assert cost(free, 0.4, path_yaw + 0.8) == pytest.approx(cost(paper, 0.4, path_yaw), rel=1e-3)
    assert cost(free, 0.4, path_yaw + 0.8) == pytest.approx(250.0 * (2.0 - 2.0 * np.cos(0.2)), rel=1e-3)


def test_coloured_noise_filter_keeps_unit_variance_and_correlates_neighbours():
    white = sampling.coloured_noise_filter(40, 0.0)
    np.testing.assert_array_equal(white, np.eye(40, dtype=np.float32))
    correlations = []
    for beta in (1.0, 2.0):
        L = sampling.coloured_noise_filter(40, beta).astype(np.float64)
        cov = L @ L.T
        np.testing.assert_allclose(np.diag(cov), 1.0, atol=1e-5)
        correlations.append(cov[10, 11])
    assert 0.3 < correlations[0] < correlations[1] < 1.0  # redder noise: smoother sequences


def test_coloured_noise_samples_have_sigma_and_are_smoother():
    """A step with coloured noise samples sequences with the configured per-step std and smaller step-to-step
    changes than white noise (seen through the costs of a cost that measures them)."""

    def dynamics(x, u, p):
        return x

    def cost(x, u, t, p):
        return 0.0 * jnp.sum(x) + jnp.sum(u**2)

    stds = {}
    for beta in (0.0, 2.0):
        config = mppi_lib.MPPIConfig(num_samples=4000, horizon=32, noise_sigma=(0.5,), temperature=1.0,
                                     noise_exponent=beta, nominal_sample=False)
        ctrl = compile_controller(mppi_lib.make_mppi(config, dynamics, cost))
        _, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(1), jnp.zeros((1,))), jnp.zeros((1,)), None)
        stds[beta] = float(jnp.sqrt(jnp.mean(info.costs) / config.horizon))
    assert stds[0.0] == pytest.approx(0.5, rel=0.03) and stds[2.0] == pytest.approx(0.5, rel=0.05)


def test_the_named_controllers_fly_their_configuration():
    """make_policy builds the controller from the configuration whole: nominal MPPI from its MPPI and racing
    settings, PixelMPC from all of it."""
    config = ControllerConfig(pixel_cost="border", mppi=paper_mppi_config(num_samples=64, horizon=12))
    assert controllers.make_policy("mppi", config).name == "mppi"
    assert controllers.make_policy("pixelmpc", config).name == "pixelmpc-dof"
    with pytest.raises(ValueError, match="unknown controller 'lqr'"):
        controllers.make_policy("lqr", config)


def test_loss_causes_split_the_low_visibility_ticks_by_where_the_gate_projects():
    """Looking at a gate from 10 m with the camera pitched down, yawed left, yawed right, pitched up, and turned
    away: the causes are above, right (the gate lies to the right of a camera yawed left), left, below, behind."""
    track = course_lib.straight_course()
    camera = C.default_camera()
    gate = track.gate(0)
    position = np.asarray(gate.centre - 10.0 * gate.normal)
    yaw = float(np.arctan2(gate.normal[1], gate.normal[0]))
    attitudes = [(0.0, 0.9, yaw), (0.0, 0.0, yaw + 1.2), (0.0, 0.0, yaw - 1.2), (0.0, -0.9, yaw),
                 (0.0, 0.0, yaw + np.pi), (0.0, 0.0, yaw)]
    states = np.stack([np.concatenate([position, np.asarray(Q.quat_from_euler(*a)), np.zeros(3)])
                       for a in attitudes]).astype(np.float32)
    below_50 = np.array([True] * 5 + [False])
    target = np.zeros(6, np.int32)
    causes = M.loss_causes(states, below_50, np.zeros(6, bool), target, track.gates, camera)
    names = [M.LOSS_CAUSES[c] if c >= 0 else None for c in causes]
    assert names == ["above", "right", "left", "below", "behind", None]
    excused = np.array([True] + [False] * 5)
    assert M.LOSS_CAUSES[M.loss_causes(states, below_50, excused, target, track.gates, camera)[0]] == "excused"


def test_lap_metrics_causes_add_up_to_the_low_visibility_time():
    track = course_lib.straight_course()
    camera = C.default_camera()
    gate = track.gate(0)
    n = 40
    distances = np.linspace(12.0, 2.0, n + 1)
    positions = np.asarray(gate.centre)[None] - distances[:, None] * np.asarray(gate.normal)[None]
    yaw = float(np.arctan2(gate.normal[1], gate.normal[0]))
    pitch = np.where(np.arange(n + 1) % 3 == 0, 0.0, 0.9)  # every third tick looks at the gate
    quats = np.stack([np.asarray(Q.quat_from_euler(0.0, p, yaw)) for p in pitch])
    states = np.concatenate([positions, quats, np.zeros((n + 1, 3))], axis=1).astype(np.float32)
    visibility = np.asarray(jax.vmap(lambda x: C.gate_visibility(gate, x, camera))(jnp.asarray(states)))
    from pixelmpc_jax.sim.episode import EpisodeLog

    log = EpisodeLog(states=states, controls=np.zeros((n, 4)), body_rates=np.zeros((n + 1, 3)),
                     visibility=visibility, target=np.zeros(n + 1, np.int32), detected=np.zeros(n, bool),
                     detection_uv=np.zeros((n, 2)), predicted_uv=np.zeros((n, 1, 2)), estimates=states[:n],
                     position_cov_trace=np.zeros(n), num_ticks=np.asarray(n), gates_passed=np.asarray(0),
                     end_cause=np.asarray(0), finished=np.asarray(False))
    lap = M.lap_metrics(log, track=track, camera=camera, target_speed=8.0)
    parts = [lap[f"time_vis_below_50_{c}_s"] for c in M.LOSS_CAUSES]
    assert lap["time_vis_below_50_above_s"] > 0.5
    assert sum(parts) == pytest.approx(lap["time_vis_below_50_s"])
    table = M.format_table([lap], M.aggregate([lap]))
    assert f"above {lap['time_vis_below_50_above_s']:.2f}" in table.splitlines()[-1]


def test_the_map_aided_prior_projects_an_undetected_target_from_the_map_and_the_estimate():
    """In front of the camera the prior is the gate's projected centre and corners (what an ideal detector would
    report); behind it, the pixel the cost charges the most."""
    from pixelmpc_jax.perception.detector import detect_from_geometry

    track = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=10.0)
    camera = C.default_camera()
    gate = track.gate(0)
    ahead = Q.hover_state((0.0, 1.0, 3.0), yaw=0.3)
    centre, corners = PM.map_pixel_state(gate, ahead, camera)
    ideal = detect_from_geometry(gate, ahead, camera)
    np.testing.assert_allclose(centre, ideal.centre, atol=1e-6)
    np.testing.assert_allclose(corners, ideal.corners, atol=1e-6)
    assert 0.5 < float(centre[0]) < 1.0  # yawed 0.4 rad left of the gate: it lies in the image's right half
    behind, _ = PM.map_pixel_state(gate, Q.hover_state((0.0, 0.0, 3.0), yaw=np.pi), camera)
    np.testing.assert_array_equal(behind, PM.behind_camera_pixel())
    config = ControllerConfig(pixel_cost="border")
    assert float(PM.pixel_cost(behind, config)) >= float(PM.pixel_cost(jnp.asarray([1.2, 0.5]), config))
    with pytest.raises(ValueError, match="target_prior must be one of"):
        ControllerConfig(target_prior="guess")
