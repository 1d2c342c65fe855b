"""The environment alone (reset, observe, step from hand-made states) and the policies' init/act pair."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.sim import policies
from pixelmpc_jax.world import course as course_lib

CONFIG = env_lib.EnvConfig(max_time_s=10.0)
HOVER = quadrotor.hover_control(quadrotor.QuadParams())  # [0, 0, 0, m g]


@pytest.fixture(scope="module")
def world():
    # gates at x = 12, 27, 42 m, facing +x, centres 3 m up; the hall spans y in [-9.2, 9.2], z in [0, 15]
    course = course_lib.straight_course(num_gates=3, spacing=15.0, first_gate_x=12.0)
    return env_lib.make_world(course, target_speed=8.0)


@pytest.fixture(scope="module")
def env():
    e = env_lib.make_env(CONFIG)
    return env_lib.Env(reset=jax.jit(e.reset), observe=jax.jit(e.observe), step=jax.jit(e.step), config=CONFIG)


def placed(env, world, position, velocity=(0.0, 0.0, 0.0), target=0, progress_s=0.0, tick=0):
    """The reset state with the vehicle level at ``position`` moving at ``velocity``, the given target gate,
    path progress and tick."""
    x = jnp.concatenate([jnp.asarray(position, jnp.float32), jnp.asarray([1.0, 0.0, 0.0, 0.0]),
                         jnp.asarray(velocity, jnp.float32)])
    s = jnp.asarray(progress_s, jnp.float32)
    return env.reset(world, jax.random.PRNGKey(0))._replace(
        plant=plant_lib.init_plant(x, world.plant_params), target=jnp.asarray(target, jnp.int32),
        progress_s=s, progress_est_s=s, tick=jnp.asarray(tick, jnp.int32))


def fly(env, world, state, u, ticks):
    for i in range(ticks):
        state = env.step(world, state, jnp.asarray(u, jnp.float32), jax.random.PRNGKey(i))
    return state


def test_reset_puts_the_vehicle_at_rest_at_the_start(env, world):
    state = env.reset(world, jax.random.PRNGKey(0))
    np.testing.assert_allclose(state.plant.x, world.track.start, atol=1e-6)
    assert int(state.tick) == 0 and int(state.target) == 0 and not bool(state.done)
    assert int(state.end_cause) == 0 and float(state.progress_s) == 0.0


def test_a_hover_command_keeps_the_vehicle_near_the_start_and_no_thrust_drops_it(env, world):
    start = env.reset(world, jax.random.PRNGKey(0))
    hovering = fly(env, world, start, HOVER, 40)  # 1 s
    assert int(hovering.tick) == 40 and not bool(hovering.done) and int(hovering.end_cause) == 0
    assert np.linalg.norm(np.asarray(hovering.plant.x[:3] - world.track.start[:3])) < 0.1
    falling = fly(env, world, start, jnp.zeros(4), 20)  # 0.5 s: about g t^2 / 2 = 1.2 m down
    assert float(world.track.start[2] - falling.plant.x[2]) > 0.6
    assert abs(float(falling.plant.x[0])) < 0.05 and int(falling.target) == 0


def test_flying_through_the_gate_opening_advances_the_target(env, world):
    # 0.1 m before gate 0's plane at 10 m/s: one tick (0.25 m) crosses it
    before = placed(env, world, (11.9, 0.0, 3.0), (10.0, 0.0, 0.0), progress_s=11.9)
    after = env.step(world, before, HOVER, jax.random.PRNGKey(1))
    assert int(after.target) == 1 and not bool(after.done) and int(after.end_cause) == 0
    assert float(after.plant.x[0]) > 12.0 and float(after.progress_s) == pytest.approx(float(after.plant.x[0]),
                                                                                        abs=0.05)
    # the same crossing 4 m to the side of the opening passes nothing (and hits nothing)
    beside = env.step(world, placed(env, world, (11.9, 4.0, 3.0), (10.0, 0.0, 0.0), progress_s=11.9), HOVER,
                      jax.random.PRNGKey(1))
    assert int(beside.target) == 0 and not bool(beside.done)


def test_passing_the_last_gate_finishes_the_lap(env, world):
    last = world.track.num_gates - 1
    before = placed(env, world, (41.9, 0.0, 3.0), (10.0, 0.0, 0.0), target=last, progress_s=41.9)
    after = env.step(world, before, HOVER, jax.random.PRNGKey(1))
    assert int(after.target) == world.track.num_gates and bool(after.done) and int(after.end_cause) == 0
    assert bool(env_lib.lap_finished(world, after)) and float(env_lib.target_visibility(world, after)) == 1.0
    assert not bool(env_lib.lap_finished(world, before))


@pytest.mark.parametrize("position, velocity, cause", [
    ((0.0, 9.1, 3.0), (0.0, 10.0, 0.0), "wall"),  # 0.1 m from the hall's side wall, flying into it
    ((0.0, 0.0, 0.15), (0.0, 0.0, -10.0), "ground"),
    ((11.9, 0.0, 3.0 + 0.5 * 1.85 + 0.15), (10.0, 0.0, 0.0), "gate"),  # into gate 0's top bar
])
def test_flying_into_an_obstacle_ends_the_episode_with_its_cause(env, world, position, velocity, cause):
    before = placed(env, world, position, velocity, progress_s=float(position[0]))
    assert not bool(before.done)
    after = env.step(world, before, HOVER, jax.random.PRNGKey(1))
    assert bool(after.done) and env_lib.END_NAMES[int(after.end_cause)] == cause
    assert int(after.target) == 0 and not bool(env_lib.lap_finished(world, after))


def test_leaving_the_target_gate_behind_ends_the_episode_as_a_missed_gate(env, world):
    # gate 0 at s = 12 m, not passed; the margin is 6 m
    inside = env.step(world, placed(env, world, (17.5, 0.0, 3.0), progress_s=17.5), HOVER, jax.random.PRNGKey(1))
    assert not bool(inside.done)
    past = env.step(world, placed(env, world, (18.5, 0.0, 3.0), progress_s=18.5), HOVER, jax.random.PRNGKey(1))
    assert bool(past.done) and int(past.end_cause) == env_lib.CRASH_MISSED_GATE


def test_the_time_limit_ends_the_episode_as_a_timeout(env, world):
    last_tick = CONFIG.max_ticks - 1
    assert CONFIG.max_ticks == 400
    before = placed(env, world, (0.0, 0.0, 3.0), tick=last_tick - 1)
    assert not bool(env.step(world, before, HOVER, jax.random.PRNGKey(1)).done)
    ended = env.step(world, placed(env, world, (0.0, 0.0, 3.0), tick=last_tick), HOVER, jax.random.PRNGKey(1))
    assert bool(ended.done) and int(ended.tick) == 400 and int(ended.end_cause) == env_lib.CRASH_TIMEOUT


def test_an_estimate_lagging_the_truth_by_half_a_metre_switches_later_by_the_time_the_lag_takes(env, world):
    """The vehicle flies through gate 0 from 10 m/s (the plant, hover thrust, drag slowing it); the world's switch is
    the tick its true position crosses the gate. An estimate 0.5 m behind the truth along the flight crosses the map's
    gate 0.5 m / v later: the estimated switch comes that many ticks later (to the tick)."""
    state = placed(env, world, (9.0, 0.0, 3.0), (10.0, 0.0, 0.0), progress_s=9.0)
    positions, world_switch = [np.asarray(state.plant.x[:3])], None
    for i in range(30):
        state = env.step(world, state, HOVER, jax.random.PRNGKey(i))
        positions.append(np.asarray(state.plant.x[:3]))
        if world_switch is None and int(state.target) == 1:
            world_switch = i + 1
    positions = np.asarray(positions)
    speed = float(np.linalg.norm(positions[world_switch] - positions[world_switch - 1])) / env_lib.CONTROL_DT
    gate = world.track.gate(0)
    switches = {}
    for lag in (0.0, 0.5):
        estimate = jnp.asarray(positions - np.asarray([lag, 0.0, 0.0]), jnp.float32)
        crossed = [bool(env_lib.estimated_switch(gate, estimate[k - 1], estimate[k])) for k in range(1, 31)]
        switches[lag] = crossed.index(True) + 1
    assert switches[0.0] == world_switch  # an exact estimate switches with the world
    lag_ticks = 0.5 / speed / env_lib.CONTROL_DT  # 2.7 ticks: drag slows the vehicle to 7.3 m/s there
    assert 2.0 < lag_ticks < 3.5
    assert np.floor(lag_ticks) <= switches[0.5] - world_switch <= np.ceil(lag_ticks)


def test_a_controller_steering_for_a_gate_already_passed_ends_the_lap_as_a_target_mismatch(world):
    """The vehicle passes gate 0 while the Kalman filter's estimate stays near the start: with the estimated switch the
    controller keeps steering for gate 0 (the world's next is gate 1), and after ``target_mismatch_s`` the lap ends as
    ``target_mismatch``; with the world's switch the controller's target follows the world's."""
    ends = {}
    for switch in ("estimate", "truth"):
        config = env_lib.EnvConfig(max_time_s=10.0, estimator="eskf", gate_switch=switch)
        raw = env_lib.make_env(config)
        env = env_lib.Env(reset=jax.jit(raw.reset), observe=jax.jit(raw.observe), step=jax.jit(raw.step),
                          config=config)
        state = placed(env, world, (11.5, 0.0, 3.0), (8.0, 0.0, 0.0), progress_s=11.5)
        targets = []
        for i in range(40):
            state, obs = env.observe(world, state, jax.random.PRNGKey(i))
            targets.append((int(obs.target_gate), int(state.target)))
            state = env.step(world, state, HOVER, jax.random.PRNGKey(i))
            if bool(state.done):
                break
        ends[switch] = (int(state.tick), int(state.end_cause), targets)
    tick, cause, targets = ends["estimate"]
    limit = round(0.5 / env_lib.CONTROL_DT)
    assert env_lib.END_NAMES[cause] == "target_mismatch"
    passed = targets.index((0, 1))  # the first tick the world is past gate 0 and the controller is not
    assert all(target == (0, 1) for target in targets[passed:]) and tick == passed + limit
    tick, cause, targets = ends["truth"]
    assert cause == 0 and tick == 40 and targets[-1] == (1, 1)


def test_the_world_flies_its_course_while_the_controller_and_the_filter_read_the_map(world):
    """A world whose gate 0 stands 3 m to the side of where the map puts it: passage and the detector follow the
    course; the map (``World.track``, all the controller and the filter read) stays as it was."""
    course = world.track.replace(gates=world.track.gates.replace(
        centre=world.track.gates.centre.at[0, 1].add(3.0)))
    moved = world.replace(course=course)
    env = env_lib.make_env(CONFIG)
    step, observe = jax.jit(env.step), jax.jit(env.observe)
    through_map = step(moved, placed_in(env, moved, (11.9, 0.0, 3.0)), HOVER, jax.random.PRNGKey(1))
    through_course = step(moved, placed_in(env, moved, (11.9, 3.0, 3.0)), HOVER, jax.random.PRNGKey(1))
    assert int(through_map.target) == 0 and int(through_course.target) == 1
    ahead = placed_in(env, moved, (4.0, 0.0, 3.0), velocity=(0.0, 0.0, 0.0))
    _, seen = observe(moved, ahead, jax.random.PRNGKey(1))
    _, on_map = observe(world, ahead, jax.random.PRNGKey(1))
    assert float(seen.detection.centre[0]) < float(on_map.detection.centre[0]) - 0.1  # the gate seen to the left
    np.testing.assert_array_equal(moved.track.gates.centre, world.track.gates.centre)
    with pytest.raises(ValueError, match="same gates"):
        env_lib.make_world(world.track, course=course_lib.straight_course(num_gates=2))


def placed_in(env, world, position, velocity=(10.0, 0.0, 0.0)):
    return placed(env, world, position, velocity, progress_s=float(position[0]))


def test_observe_sees_the_target_gate_and_the_truth_or_the_filter(world):
    noisy = world.replace(detector_noise_px=jnp.asarray(3.0, jnp.float32))
    truth = env_lib.make_env(CONFIG)
    state = truth.reset(noisy, jax.random.PRNGKey(0))
    observe = jax.jit(truth.observe)
    same, obs = observe(noisy, state, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(obs.x_est, state.plant.x)
    assert int(obs.target_gate) == 0 and float(obs.position_cov_trace) == 0.0
    assert bool(obs.detection.found) and 0.0 < float(env_lib.target_visibility(noisy, same)) <= 1.0
    # gate 0 straight ahead: its centre is near the image centre, moved by the detector's noise (per key)
    np.testing.assert_allclose(obs.detection.centre, [0.5, 0.5], atol=0.05)
    _, again = observe(noisy, state, jax.random.PRNGKey(1))
    _, other = observe(noisy, state, jax.random.PRNGKey(2))
    np.testing.assert_array_equal(again.detection.centre, obs.detection.centre)
    assert not np.allclose(other.detection.centre, obs.detection.centre)

    from pixelmpc_jax.perception.particle_filter import PFConfig

    filtered = env_lib.make_env(env_lib.EnvConfig(estimator="pf", pf=PFConfig(num_particles=256)))
    state = filtered.reset(world, jax.random.PRNGKey(0))
    updated, obs = jax.jit(filtered.observe)(world, state, jax.random.PRNGKey(1))
    error = np.linalg.norm(np.asarray(obs.x_est[:3] - state.plant.x[:3]))
    assert 0.0 < error < 0.5 and float(obs.position_cov_trace) > 0.0
    assert not np.array_equal(updated.filter.key, state.filter.key)  # the filter stepped


def test_the_kalman_filter_estimates_near_the_truth_and_passes_on_no_detection_it_rejects(world):
    from pixelmpc_jax.sim.faults import Faults

    filtered = env_lib.make_env(env_lib.EnvConfig(estimator="eskf"))
    state = filtered.reset(world, jax.random.PRNGKey(0))
    observe = jax.jit(filtered.observe)
    updated, obs = observe(world, state, jax.random.PRNGKey(1))
    error = np.linalg.norm(np.asarray(obs.x_est[:3] - state.plant.x[:3]))
    assert error < 0.1 and 0.0 < float(obs.position_cov_trace) < 3 * 0.3 ** 2  # the corners narrowed the prior
    assert bool(obs.detection.found)
    assert not np.array_equal(updated.filter.latest.cov, state.filter.latest.cov)  # the filter stepped
    # one second of hover with honest detections narrows the prior (a lie at the first tick, within the prior's
    # 0.3 m and 0.03 rad, is still believable)
    step = jax.jit(filtered.step)
    for i in range(40):
        state, _ = observe(world, state, jax.random.PRNGKey(i))
        state = step(world, state, HOVER, jax.random.PRNGKey(i))
    _, honest = observe(world, state, jax.random.PRNGKey(41))
    assert bool(honest.detection.found)
    # then a lie (gate 1's image under gate 0's name): the filter's gate rejects every corner and the controller is
    # told nothing was found, where on the true state it is handed the lie
    lying = env_lib.EnvConfig(faults=Faults(false_rate=1.0))
    for estimator, found in (("eskf", False), ("truth", True)):
        env = env_lib.make_env(dataclasses.replace(lying, estimator=estimator))
        start = state if estimator == "eskf" else env.reset(world, jax.random.PRNGKey(0))
        _, obs = jax.jit(env.observe)(world, start, jax.random.PRNGKey(41))
        assert bool(obs.detection.found) == found, estimator


def test_the_kalman_filter_aligned_on_the_pad_starts_with_the_faulty_imus_gyro_bias(world):
    """``ESKFConfig.align_s``: the reset's filter has learnt the IMU fault's gyro bias from the readings at rest
    (within their noise over 2 s, about 1.2 mrad/s per axis) and its covariance narrowed; without it the bias
    starts at zero, and the same fault-free reset stays the plain one."""
    from pixelmpc_jax.perception.eskf import ESKFConfig
    from pixelmpc_jax.sim.faults import Faults

    gyro_bias = np.asarray([0.01, -0.01, 0.01], np.float32)
    faulty = Faults(imu_accel_bias=(0.1, -0.1, 0.2), imu_gyro_bias=tuple(gyro_bias))
    filters = {}
    for align_s in (0.0, 2.0):
        config = env_lib.EnvConfig(estimator="eskf", eskf=ESKFConfig(align_s=align_s), faults=faulty)
        filters[align_s] = jax.jit(env_lib.make_env(config).reset)(world, jax.random.PRNGKey(3)).filter.latest
    np.testing.assert_array_equal(np.asarray(filters[0.0].bias), 0.0)
    aligned = filters[2.0]
    assert np.all(np.abs(np.asarray(aligned.bias[3:]) - gyro_bias) < 4e-3)
    assert abs(float(aligned.bias[2]) - 0.2) < 0.01
    assert np.all(np.diag(np.asarray(aligned.cov))[12:] < 0.1 * np.diag(np.asarray(filters[0.0].cov))[12:])


def test_an_estimator_config_that_cannot_work_is_refused():
    from pixelmpc_jax.perception.eskf import ESKFConfig
    from pixelmpc_jax.perception.filter_guards import GuardConfig
    from pixelmpc_jax.sim.faults import Faults

    with pytest.raises(ValueError, match="window"):
        env_lib.EnvConfig(estimator="eskf", eskf=ESKFConfig(max_delay_ticks=1), faults=Faults(detection_delay_ticks=2))
    with pytest.raises(ValueError, match="particle filter"):
        env_lib.EnvConfig(estimator="eskf", guards=GuardConfig(detection_gate_px=30.0))
    with pytest.raises(ValueError, match="estimator must be one of"):
        env_lib.EnvConfig(estimator="ekf")


@pytest.mark.parametrize("kind", ["mppi", "pixelmpc", "pixelmpc_look_ahead"])
def test_a_policy_acts_within_the_control_bounds(world, kind):
    mppi_config = pixelmpc_lib.paper_mppi_config(num_samples=64, horizon=20)
    if kind == "mppi":
        policy = policies.nominal_mppi_policy(mppi_config)
    else:
        policy = policies.pixelmpc_policy(pixelmpc_lib.ControllerConfig(
            mppi=mppi_config, pixel_model="projection", look_ahead=1.0 if kind.endswith("look_ahead") else 0.0))
    env = env_lib.make_env(CONFIG)
    state = env.reset(world, jax.random.PRNGKey(0))
    _, obs = env.observe(world, state, jax.random.PRNGKey(1))
    policy_state = jax.jit(policy.init)(jax.random.PRNGKey(2), world)
    assert bool(jnp.all(jnp.isnan(policy_state.step_progress)))  # no plan yet
    # the racing cost's per-track constants, once per episode: this world's path and speed cap
    cost_config = costs.RacingCostConfig()
    constants = policy_state.racing_constants
    np.testing.assert_array_equal(constants.points, world.track.path_points[::cost_config.path_stride])
    np.testing.assert_array_equal(constants.attributes[:, 3],
                                  costs.speed_cap(world.track, cost_config)[::cost_config.path_stride])
    u, policy_state, prediction = jax.jit(policy.act)(policy_state, obs, world)
    lo, hi = np.asarray(mppi_config.u_min), np.asarray(mppi_config.u_max)
    assert u.shape == (4,) and np.all(np.asarray(u) >= lo) and np.all(np.asarray(u) <= hi)
    assert prediction.shape == (21, {"mppi": 10, "pixelmpc": 12, "pixelmpc_look_ahead": 14}[kind])
    if kind == "pixelmpc_look_ahead":  # the next gate's pixel, from the map and the start: gate 1 straight ahead
        next_pixel, _ = pixelmpc_lib.map_pixel_state(world.track.gate(1), obs.x_est, world.camera)
        np.testing.assert_allclose(prediction[0, 12:], next_pixel, atol=1e-6)
    # the next tick's path windows follow the plan forward from the start
    progress = np.asarray(policy_state.step_progress)
    assert progress.shape == (20,) and np.all(np.isfinite(progress)) and np.all(np.diff(progress) >= -1e-3)
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, policy_state.racing_constants, constants))


def test_vdofs_size_cue_takes_the_corners_out_of_view_from_the_map(world):
    """A detection that reports two corners (the others out of view, zeros as a camera's detector gives them): vdof's
    box size comes from the corners in view and the map's projection of the others, as with all four in view; the
    zeros would make it another (here nearly twice as large, the quad stretched to the image's origin)."""
    from pixelmpc_jax.dynamics import vdof as vdof_lib

    learned = world.replace(dof=vdof_lib.load_packaged_vdof())
    env = env_lib.make_env(CONFIG)
    _, whole = env.observe(learned, env.reset(learned, jax.random.PRNGKey(0)), jax.random.PRNGKey(1))
    assert bool(jnp.all(whole.detection.corners_visible))
    in_view = jnp.asarray([False, True, True, False])
    half = whole._replace(detection=whole.detection.replace(
        corners=jnp.where(in_view[:, None], whole.detection.corners, 0.0), corners_visible=in_view))
    policy = policies.pixelmpc_policy(pixelmpc_lib.ControllerConfig(
        mppi=pixelmpc_lib.paper_mppi_config(num_samples=16, horizon=4), pixel_model="vdof"))
    act, state = jax.jit(policy.act), jax.jit(policy.init)(jax.random.PRNGKey(2), learned)
    size = {name: float(act(state, obs, learned)[2][0, 12]) for name, obs in (("whole", whole), ("half", half))}
    assert size["half"] == pytest.approx(size["whole"], rel=1e-5)
    assert float(vdof_lib.box_size(half.detection.corners)) > 1.5 * size["whole"]


def test_a_gate_cut_by_the_image_border_starts_from_the_map_with_partial_target_map(world):
    """A detection with two opening corners out of view reports the centre of its visible outline: the controller
    plans from it with ``partial_target="detected"`` and from the gate's centre and corners projected from the map
    and the estimate with "map"; a detection with every corner in view is planned from the detection either way."""
    from pixelmpc_jax.dynamics import vdof as vdof_lib

    learned = world.replace(dof=vdof_lib.load_packaged_vdof())
    env = env_lib.make_env(CONFIG)
    _, whole = env.observe(learned, env.reset(learned, jax.random.PRNGKey(0)), jax.random.PRNGKey(1))
    assert bool(jnp.all(whole.detection.corners_visible))
    in_view = jnp.asarray([False, True, True, False])
    clipped_centre = jnp.asarray([0.8, 0.5], jnp.float32)  # the visible outline's centre, the gate's right part
    half = whole._replace(detection=whole.detection.replace(
        centre=clipped_centre, corners=jnp.where(in_view[:, None], whole.detection.corners, 0.0),
        corners_visible=in_view))
    mapped, mapped_corners = pixelmpc_lib.map_pixel_state(learned.track.gate(half.target_gate), half.x_est,
                                                          learned.camera)
    assert float(jnp.abs(mapped - clipped_centre).max()) > 0.2
    started = {}
    for partial_target in ("detected", "map"):
        policy = policies.pixelmpc_policy(pixelmpc_lib.ControllerConfig(
            mppi=pixelmpc_lib.paper_mppi_config(num_samples=16, horizon=4), pixel_model="vdof",
            partial_target=partial_target))
        act, state = jax.jit(policy.act), jax.jit(policy.init)(jax.random.PRNGKey(2), learned)
        started[partial_target] = {name: np.asarray(act(state, obs, learned)[2][0, 10:13])
                                   for name, obs in (("whole", whole), ("half", half))}
    np.testing.assert_allclose(started["detected"]["half"][:2], clipped_centre, atol=1e-6)
    np.testing.assert_allclose(started["map"]["half"], vdof_lib.initial_pixel_state(mapped, mapped_corners),
                               atol=1e-6)
    np.testing.assert_array_equal(started["map"]["whole"], started["detected"]["whole"])
    np.testing.assert_allclose(started["map"]["whole"][:2], whole.detection.centre, atol=1e-6)
    with pytest.raises(ValueError, match="partial_target must be one of"):
        pixelmpc_lib.ControllerConfig(partial_target="guess")


def test_the_kept_pixel_charges_a_lost_target_with_the_pixel_its_model_predicted(world):
    """``target_prior="kept"``: once the target has been seen, a tick without a detection is planned from the pixel
    the controller's pixel model predicted for it at the last tick, and charged; a new target not yet seen is not,
    nor is a lost one under the paper's prior."""
    mppi_config = pixelmpc_lib.paper_mppi_config(num_samples=64, horizon=20)
    env = env_lib.make_env(CONFIG)
    state = env.reset(world, jax.random.PRNGKey(0))
    _, seen = env.observe(world, state, jax.random.PRNGKey(1))
    assert bool(seen.detection.found)
    lost = seen._replace(detection=seen.detection.replace(found=jnp.asarray(False)))
    switched = lost._replace(target_gate=lost.target_gate + 1)
    for prior in ("kept", "none"):
        policy = policies.pixelmpc_policy(pixelmpc_lib.ControllerConfig(mppi=mppi_config, pixel_model="projection",
                                                                        target_prior=prior))
        act = jax.jit(policy.act)
        first = jax.jit(policy.init)(jax.random.PRNGKey(2), world)
        _, after_seen, prediction = act(first, seen, world)
        if prior == "none":
            assert after_seen.kept is None
            continue
        np.testing.assert_array_equal(after_seen.kept.pixel, prediction[1, 10:12])
        assert bool(after_seen.kept.valid) and int(after_seen.kept.gate) == int(seen.target_gate)
        _, after_lost, kept_prediction = act(after_seen, lost, world)
        np.testing.assert_allclose(kept_prediction[0, 10:12], prediction[1, 10:12], atol=1e-6)  # planned from it
        assert bool(after_lost.kept.valid)  # charged, and kept alive for the next tick
        _, after_switch, _ = act(after_seen, switched, world)
        assert not bool(after_switch.kept.valid)  # the next target starts unseen
        _, never, _ = act(first, lost, world)
        assert not bool(never.kept.valid)


def test_the_seeded_pixel_charges_an_unseen_target_from_the_map_and_a_lost_one_from_its_model(world):
    """``target_prior="seeded"``: a target not detected since it became the target is planned from its pixel from the
    map and the estimate, tick after tick, and is not taken for seen; once detected and then lost it is planned from
    the pixel the model predicted, as with "kept"."""
    mppi_config = pixelmpc_lib.paper_mppi_config(num_samples=64, horizon=20)
    env = env_lib.make_env(CONFIG)
    state = env.reset(world, jax.random.PRNGKey(0))
    _, seen = env.observe(world, state, jax.random.PRNGKey(1))
    lost = seen._replace(detection=seen.detection.replace(found=jnp.asarray(False)))
    # the next target, seen from 1.5 m aside: off the image centre, where the detector's absent pixel would sit
    switched = lost._replace(target_gate=lost.target_gate + 1, x_est=lost.x_est.at[1].add(1.5))
    policy = policies.pixelmpc_policy(pixelmpc_lib.ControllerConfig(mppi=mppi_config, pixel_model="projection",
                                                                    target_prior="seeded"))
    act = jax.jit(policy.act)
    first = jax.jit(policy.init)(jax.random.PRNGKey(2), world)
    _, after_seen, prediction = act(first, seen, world)
    assert bool(after_seen.kept.valid)
    _, after_lost, kept_prediction = act(after_seen, lost, world)
    np.testing.assert_allclose(kept_prediction[0, 10:12], prediction[1, 10:12], atol=1e-6)  # the model's pixel
    assert bool(after_lost.kept.valid)
    mapped, _ = pixelmpc_lib.map_pixel_state(world.track.gate(switched.target_gate), switched.x_est, world.camera)
    assert np.abs(mapped - prediction[1, 10:12]).max() > 0.02  # the two sources differ here
    state = after_seen
    for _ in range(2):  # unseen after the switch: from the map at every tick, never taken for seen
        _, state, switch_prediction = act(state, switched, world)
        np.testing.assert_allclose(switch_prediction[0, 10:12], mapped, atol=1e-6)
        assert not bool(state.kept.valid) and int(state.kept.gate) == int(switched.target_gate)
