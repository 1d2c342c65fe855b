"""Faults a real flight brings (issue 28): each fault does what it says, against a hand computation or the plant with
the fault off; the levers against them; a short closed loop under every fault at once gives finite commands and a
named end; a race's faults travel in its spec and the ``--fault`` flag refuses a bad entry in one line."""

import dataclasses
import functools
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import cli, devices
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.commands import EXIT_USAGE
from pixelmpc_jax.commands.race import race_spec
from pixelmpc_jax.control import pixelmpc as PM
from pixelmpc_jax.dynamics import quadrotor as Q
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import filter_guards as guards_lib
from pixelmpc_jax.perception import particle_filter as pf_lib
from pixelmpc_jax.perception.eskf import SURVEYED_MAP_SIGMA_M
from pixelmpc_jax.perception.estimator import EstimatorParams
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import faults as F
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.sim import policies
from pixelmpc_jax.timing import CONTROL_DT
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

COURSE = course_lib.straight_course(num_gates=3, spacing=15.0, first_gate_x=12.0)
CAMERA = camera_lib.default_camera()
HOVER = jnp.asarray([0.0, 0.0, 0.0, 9.81], jnp.float32)
KEYS = jax.random.split(jax.random.PRNGKey(0), 4000)


def _level_state(velocity=(0.0, 0.0, 0.0), position=(0.0, 0.0, 2.0), yaw=0.0) -> jax.Array:
    return Q.hover_state(position, yaw).at[7:10].set(jnp.asarray(velocity, jnp.float32))


# --------------------------------------------------------------------------------------------------
# The configuration.
# --------------------------------------------------------------------------------------------------


def test_no_fault_is_on_by_default_and_a_fault_free_episode_carries_no_fault_state():
    assert F.Faults().active() == ()
    sim = env_lib.make_env(env_lib.EnvConfig()).reset(env_lib.make_world(COURSE), jax.random.PRNGKey(0))
    assert jax.tree_util.tree_leaves(sim.faults) == []
    assert F.plant_params(plant_lib.PlantParams(), F.Faults()) == plant_lib.PlantParams()


def test_every_named_level_is_a_fault_with_its_reason_and_combined_holds_them_all():
    for name, levels in F.FAULT_LEVELS.items():
        assert set(levels) == set(F.LEVELS)
        moderate, severe = (F.fault_level(name, level) for level in F.LEVELS)
        assert moderate.active() and moderate.active() == severe.active() and moderate != severe, name
        assert all(len(entry.why) > 20 for entry in levels.values()), name
    combined = F.fault_level(F.COMBINED, "moderate")
    assert set(combined.active()) == {f.name for f in dataclasses.fields(F.Faults)}
    with pytest.raises(ValueError, match="unknown fault 'fog'"):
        F.fault_level("fog", "moderate")
    with pytest.raises(ValueError, match="unknown fault level 'mild'"):
        F.fault_level("wind", "mild")


@pytest.mark.parametrize("settings, message", [
    ({"wind": (1.0, 2.0)}, "wind takes 3 finite numbers"), ({"latency_ticks": 4}, r"latency_ticks takes an integer"),
    ({"latency_ticks": True}, "latency_ticks takes an integer"), ({"miss_rate": 1.5}, "probability in"),
    ({"mass_factor": 0.0}, r"factor in \[0.2, 5\]"), ({"gust": -1.0}, "gust takes a number >= 0"),
    ({"pixel_noise_px": math.nan}, "finite number"),
])
def test_a_bad_fault_is_refused_saying_what_it_takes(settings, message):
    with pytest.raises(ValueError, match=message):
        F.Faults(**settings)


# --------------------------------------------------------------------------------------------------
# Each fault does what it says.
# --------------------------------------------------------------------------------------------------


def test_wind_adds_the_drag_of_the_air_relative_velocity_and_the_accelerometer_feels_it():
    """At rest in a 3 m/s wind along x: one substep gains dt c_d |w| w / m (0.9 m/s^2 for the reference vehicle)."""
    params = plant_lib.PlantParams().without_noise()
    state = plant_lib.init_plant(_level_state(), params)
    key, wind = jax.random.PRNGKey(1), jnp.asarray([3.0, 0.0, 0.0])
    still, imu_still = plant_lib.plant_substep(state, HOVER, key, params)
    windy, imu_windy = plant_lib.plant_substep(state, HOVER, key, params, wind=wind)
    dt, expected = plant_lib.PLANT_DT, 0.1 * 3.0 * 3.0 / 1.0
    np.testing.assert_allclose(windy.x[7:10] - still.x[7:10], [dt * expected, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(imu_windy.accel - imu_still.accel, [expected, 0.0, 0.0], atol=1e-3)
    # moving with the air: no drag at all, the wind cancels the still-air drag c_d |v| v
    np.testing.assert_allclose(plant_lib.wind_force(wind, wind, params), [expected, 0.0, 0.0], atol=1e-6)


def test_gusts_keep_the_dryden_std_and_decay_with_its_time_constants():
    """From the stationary law, one tick later: the std per axis is sigma (1, 1, 0.5) and the correlation with the
    tick before is exp(-dt / tau)."""
    faults = F.Faults(gust=2.0)
    start = jax.vmap(lambda k: F.init_fault_state(faults, k, COURSE.gates, HOVER).gust)(KEYS)
    after = jax.vmap(lambda g, k: F.gust_step(g, k, faults))(start, jax.random.split(jax.random.PRNGKey(1), 4000))
    sigma = 2.0 * np.asarray(F.GUST_AXIS_SHARE)
    np.testing.assert_allclose(np.std(np.asarray(start), 0), sigma, rtol=0.05)
    np.testing.assert_allclose(np.std(np.asarray(after), 0), sigma, rtol=0.05)
    correlation = [np.corrcoef(np.asarray(start)[:, i], np.asarray(after)[:, i])[0, 1] for i in range(3)]
    np.testing.assert_allclose(correlation, np.exp(-CONTROL_DT / np.asarray(F.GUST_TIME_CONSTANT_S)), atol=0.01)
    assert F.wind_velocity(F.Faults(), F.FaultState()) is None


def test_model_error_scales_the_plants_mass_drag_and_thrust_but_not_the_mixers():
    """Level at 4 m/s with the motors at the model's hover speed: one substep gives dv_z = dt (0.9 g / 1.1 - g) and
    dv_x = -dt 2 c_d 16 / 1.1; the mixer's commanded thrust T comes out of the motors as 0.9 T."""
    params = plant_lib.PlantParams().without_noise()
    faulty = F.plant_params(params, F.Faults(mass_factor=1.1, drag_factor=2.0, thrust_factor=0.9))
    state = plant_lib.init_plant(_level_state((4.0, 0.0, 0.0)), params)
    stepped, _ = plant_lib.plant_substep(state, HOVER, jax.random.PRNGKey(0), faulty)
    dt, g = plant_lib.PLANT_DT, 9.81
    np.testing.assert_allclose(stepped.x[9], dt * (0.9 * g / 1.1 - g), rtol=1e-4)
    np.testing.assert_allclose(stepped.x[7] - 4.0, -dt * 2.0 * 0.1 * 16.0 / 1.1, rtol=1e-4)
    speeds = plant_lib.mix(jnp.zeros(3), jnp.asarray(12.0), faulty)
    assert float(plant_lib.motor_wrench(speeds, faulty)[1]) == pytest.approx(0.9 * 12.0, rel=1e-5)
    assert float(plant_lib.motor_wrench(speeds, params)[1]) == pytest.approx(12.0, rel=1e-5)


def test_latency_applies_each_command_its_ticks_late():
    queue = F.init_fault_state(F.Faults(latency_ticks=2), jax.random.PRNGKey(0), COURSE.gates, HOVER).commands
    applied = []
    for k in range(1, 5):
        u, queue = F.fifo(queue, jnp.full((4,), float(k)))
        applied.append(np.asarray(u))
    np.testing.assert_array_equal(applied, [HOVER, HOVER, np.full(4, 1.0), np.full(4, 2.0)])


def test_imu_bias_and_noise_reach_the_filters_tick():
    """At rest: the mean readings gain the bias, the integrals b dt and b dt^2 / 2, the rotation exp(b_g dt); the
    extra noise's std on the tick's mean is sigma / sqrt(24)."""
    imu = plant_lib.hover_tick_imu(CONTROL_DT)
    accel_bias, gyro_bias = np.asarray([0.1, -0.2, 0.3]), np.asarray([0.01, 0.0, -0.02])
    biased = F.corrupt_imu(imu, F.Faults(imu_accel_bias=accel_bias, imu_gyro_bias=gyro_bias), jax.random.PRNGKey(0))
    dt, up = CONTROL_DT, np.asarray([0.0, 0.0, 9.81])
    np.testing.assert_allclose(biased.accel, up + accel_bias, atol=1e-6)
    np.testing.assert_allclose(biased.gyro, gyro_bias, atol=1e-7)
    np.testing.assert_allclose(biased.delta_v, (up + accel_bias) * dt, atol=1e-6)
    np.testing.assert_allclose(biased.delta_p, 0.5 * (up + accel_bias) * dt * dt, atol=1e-7)
    np.testing.assert_allclose(biased.delta_q, Q.quat_exp(jnp.asarray(gyro_bias, jnp.float32), dt), atol=1e-7)
    noisy = F.Faults(imu_accel_noise=0.5, imu_gyro_noise=0.2)
    draws = jax.vmap(lambda k: F.corrupt_imu(imu, noisy, k))(KEYS)
    np.testing.assert_allclose(np.std(np.asarray(draws.accel), 0), 0.5 / np.sqrt(24), rtol=0.05)
    np.testing.assert_allclose(np.std(np.asarray(draws.gyro), 0), 0.2 / np.sqrt(24), rtol=0.05)


def _seen_gate(gate_index=0):
    """The straight course's gate ``gate_index`` detected from 6 m before it, level and facing it."""
    gate = COURSE.gate(gate_index)
    x = _level_state(position=gate.centre - 6.0 * gate.normal)
    return x, detector_lib.detect_from_geometry(gate, x, CAMERA, gate_id=gate_index)


def _not_found(detection):
    return detection.replace(found=jnp.asarray(False), corners_visible=jnp.zeros(4, bool))


def test_missed_detections_come_at_their_rate_and_leave_nothing():
    _, seen = _seen_gate()
    draws = jax.vmap(lambda k: F.corrupt_detection(seen, _not_found(seen), F.Faults(miss_rate=0.3), k, CAMERA))(KEYS)
    assert np.mean(np.asarray(draws.found)) == pytest.approx(0.7, abs=0.03)
    assert not np.any(np.asarray(draws.corners_visible)[~np.asarray(draws.found)])


def test_false_detections_report_another_gate_or_a_made_up_box_as_the_target():
    _, seen = _seen_gate()
    lying = F.Faults(false_rate=1.0)
    box = F.corrupt_detection(_not_found(seen), _not_found(seen), lying, jax.random.PRNGKey(3), CAMERA)
    half = (box.corners[2] - box.corners[0]) / 2
    assert bool(box.found) and int(box.gate_id) == 0 and bool(np.all(box.corners_visible))
    np.testing.assert_allclose(box.corners[0] + half, box.centre, atol=1e-6)  # a square about its centre
    assert half[0] == pytest.approx(half[1]) and 0.05 <= float(half[0]) <= 0.2
    other = detector_lib.detect_from_geometry(COURSE.gate(1), _seen_gate()[0], CAMERA, gate_id=1)
    wrong = F.corrupt_detection(_not_found(seen), other, lying, jax.random.PRNGKey(3), CAMERA)
    np.testing.assert_array_equal(wrong.centre, other.centre)
    assert int(wrong.gate_id) == 0  # reported as the target
    honest = jax.vmap(lambda k: F.corrupt_detection(seen, other, F.Faults(false_rate=0.1), k, CAMERA).found)(KEYS)
    assert np.all(np.asarray(honest))  # a lie is a detection too


def test_pixel_noise_has_its_std_in_pixels():
    _, seen = _seen_gate()
    draws = jax.vmap(lambda k: F.corrupt_detection(seen, seen, F.Faults(pixel_noise_px=3.0), k, CAMERA))(KEYS)
    error_px = (np.asarray(draws.centre) - np.asarray(seen.centre)) * [CAMERA.width, CAMERA.height]
    np.testing.assert_allclose(np.std(error_px, 0), 3.0, rtol=0.05)
    corners_px = (np.asarray(draws.corners) - np.asarray(seen.corners)) * [CAMERA.width, CAMERA.height]
    np.testing.assert_allclose(np.std(corners_px, 0), 3.0, rtol=0.06)


def test_a_late_detection_arrives_its_ticks_later():
    _, seen = _seen_gate()
    queue = F.init_fault_state(F.Faults(detection_delay_ticks=1), jax.random.PRNGKey(0), COURSE.gates,
                               HOVER).detections
    first, queue = F.fifo(queue, seen)
    second, _ = F.fifo(queue, _not_found(seen))
    assert not bool(first.found) and int(first.gate_id) == -1  # nothing yet: the filter skips it
    jax.tree_util.tree_map(np.testing.assert_array_equal, second, seen)


def test_a_map_error_moves_every_gate_by_its_size_and_the_world_flies_the_moved_gates():
    state = F.init_fault_state(F.Faults(map_error_m=0.5), jax.random.PRNGKey(2), COURSE.gates, HOVER)
    shift = np.asarray(state.gates.centre - COURSE.gates.centre)
    np.testing.assert_allclose(np.linalg.norm(shift[:, :2], axis=1), 0.5, rtol=1e-5)
    np.testing.assert_array_equal(shift[:, 2], 0.0)
    assert F.true_track(COURSE, state).gates is state.gates and F.true_track(COURSE, F.FaultState()) is COURSE
    world = env_lib.make_world(COURSE)
    env = env_lib.make_env(env_lib.EnvConfig(faults=F.Faults(map_error_m=6.0)))
    sim = env.reset(world, jax.random.PRNGKey(2))
    moved, seen_by = sim.faults.gates, []
    for centre in (moved.centre[0], COURSE.gates.centre[0]):  # 5 m before the moved gate, then the map's
        x = _level_state(position=centre - 5.0 * COURSE.gates.normal[0])
        visibility = float(env_lib.target_visibility(world, sim._replace(plant=sim.plant.replace(x=x))))
        assert visibility == float(camera_lib.gate_visibility(jax.tree_util.tree_map(lambda a: a[0], moved), x,
                                                              CAMERA))
        seen_by.append((visibility, float(camera_lib.gate_visibility(COURSE.gate(0), x, CAMERA))))
    assert seen_by[0][0] == 1.0 and any(world_sees != map_sees for world_sees, map_sees in seen_by)


# --------------------------------------------------------------------------------------------------
# The levers.
# --------------------------------------------------------------------------------------------------

PF = pf_lib.PFConfig(num_particles=256)
PF_SPREAD = (0.05, 0.005, 0.05)
PF_PARAMS = EstimatorParams(gates=COURSE.gates, camera=CAMERA)


def _filter(x, offset=(0.0, 0.0, 0.0)):
    x = x.at[:3].add(jnp.asarray(offset, jnp.float32))
    return jax.jit(pf_lib.make_particle_filter(PF, PF_SPREAD).init)(jax.random.PRNGKey(4), x)


@functools.cache
def _guarded(guards: guards_lib.GuardConfig) -> devices.CompiledEstimator:
    """The filter with ``guards``, compiled once per guards."""
    return devices.compile_estimator(guards_lib.make_guarded_particle_filter(PF, guards, PF_SPREAD))


def test_the_detection_gate_keeps_the_gate_where_the_particles_see_it_and_rejects_a_made_up_box():
    x, seen = _seen_gate()
    state = _filter(x)
    box = F.made_up_box(jax.random.PRNGKey(0), 0).replace(centre=jnp.asarray([0.9, 0.1]))
    assert bool(guards_lib.detection_accepted(state, seen, COURSE.gates, CAMERA, 30.0))
    assert not bool(guards_lib.detection_accepted(state, box, COURSE.gates, CAMERA, 30.0))
    assert bool(guards_lib.detection_accepted(state, _not_found(box), COURSE.gates, CAMERA, 30.0))
    imu = plant_lib.hover_tick_imu(CONTROL_DT)
    estimate, _, info = _guarded(guards_lib.GuardConfig(detection_gate_px=30.0)).step(state, imu, box, PF_PARAMS)
    assert not bool(info.guards.accepted) and not bool(info.guards.recovered)
    assert not bool(estimate.detection.found)  # the loop is told the rejected detection as none


def test_recovery_respreads_a_filter_whose_particles_explain_no_detection():
    x, seen = _seen_gate()
    imu, guards = plant_lib.hover_tick_imu(CONTROL_DT), guards_lib.GuardConfig(recover_error_px=120.0)
    for offset, diverged in (((0.0, 2.5, 0.0), True), ((0.0, 0.0, 0.0), False)):
        state = guards_lib.init_guards(_filter(x, offset), guards)
        _, state, info = _guarded(guards).step(state, imu, seen, PF_PARAMS)
        info = info.guards
        assert bool(info.recovered) == diverged and bool(info.accepted) and int(state.unexplained) == 0
    spread = guards_lib.respread(_filter(x), (1.0, 0.05, 0.5), jax.random.PRNGKey(0))
    assert np.std(np.asarray(spread.particles[:, 1])) == pytest.approx(1.0, rel=0.15)
    np.testing.assert_allclose(np.exp(spread.log_weights), 1.0 / PF.num_particles, rtol=1e-5)
    with pytest.raises(ValueError, match="init_guards"):  # a state without the count cannot recover
        _guarded(guards).step(_filter(x), imu, seen, PF_PARAMS)


def test_recovery_waits_for_unexplained_detections_in_a_row():
    """Waiting for 3, a filter 2.5 m off re-spreads at its third unexplained detection, not before; a tick with no
    detection keeps the count, and a detection the particles explain clears it."""
    x, seen = _seen_gate()
    imu = plant_lib.hover_tick_imu(CONTROL_DT)
    guards = guards_lib.GuardConfig(recover_error_px=120.0, recover_after_ticks=3)
    state = guards_lib.init_guards(_filter(x, (0.0, 2.5, 0.0)), guards)
    for detection, count, recovered in ((seen, 1, False), (_not_found(seen), 1, False), (seen, 2, False),
                                        (seen, 0, True)):
        _, state, info = _guarded(guards).step(state, imu, detection, PF_PARAMS)
        assert (int(state.unexplained), bool(info.guards.recovered)) == (count, recovered)
    near = guards_lib.init_guards(_filter(x), guards).replace(unexplained=jnp.asarray(2, jnp.int32))
    _, near, info = _guarded(guards).step(near, imu, seen, PF_PARAMS)
    assert int(near.unexplained) == 0 and not bool(info.guards.recovered)  # explained: the row is broken
    with pytest.raises(ValueError, match=r"recover_after_ticks must be an integer in \[1, 1000\], got 0"):
        guards_lib.GuardConfig(recover_after_ticks=0)


def test_without_guards_the_guarded_step_is_the_filters_step():
    x, seen = _seen_gate()
    imu = plant_lib.hover_tick_imu(CONTROL_DT)
    plain = devices.compile_estimator(pf_lib.make_particle_filter(PF, PF_SPREAD)).step(_filter(x), imu, seen, PF_PARAMS)
    guarded = _guarded(guards_lib.GuardConfig()).step(_filter(x), imu, seen, PF_PARAMS)
    jax.tree_util.tree_map(np.testing.assert_array_equal, guarded, plain)
    with pytest.raises(ValueError, match=r"detection_gate_px must be a finite number in \(0, 10000\] px, got 0.0"):
        guards_lib.GuardConfig(detection_gate_px=0.0)


def test_the_disturbance_observer_learns_a_constant_push_with_its_time_constant():
    """The model's step adds dt a to the velocity; the observer integrates the residual of its one-tick prediction
    (a <- a + (v - v_expected) / tau), so a push the model lacks is learnt as 1 - (1 - dt / tau)^k."""
    params, dt, tau = Q.QuadParams(), CONTROL_DT, 0.25
    x, u, push = _level_state((3.0, 0.0, 0.0)), HOVER + jnp.asarray([0.2, 0.0, 0.0, 1.0]), jnp.asarray([2.0, -1.0, 0.5])
    np.testing.assert_allclose(PM.disturbed_step(x, u, dt, params, push),
                               Q.step(x, u, dt, params).at[7:10].add(dt * push), atol=1e-6)
    np.testing.assert_array_equal(PM.disturbed_step(x, u, dt, params, None), Q.step(x, u, dt, params))  # no push
    np.testing.assert_array_equal(policies.disturbance_update(push, jnp.full(10, jnp.nan), x, tau), push)

    def tick(estimate, _):
        expected = PM.disturbed_step(x, u, dt, params, estimate)
        return policies.disturbance_update(estimate, expected, PM.disturbed_step(x, u, dt, params, push), tau), None

    learnt = jax.lax.scan(tick, jnp.zeros(3), None, length=20)[0]
    np.testing.assert_allclose(learnt, push * (1 - (1 - dt / tau) ** 20), rtol=1e-4)
    with pytest.raises(ValueError, match="disturbance_time_constant_s"):
        PM.ControllerConfig(disturbance_time_constant_s=0.0)


def test_the_model_latency_rolls_the_estimate_through_the_pending_commands():
    params = Q.QuadParams()
    pending = jnp.asarray([[0.5, 0.0, 0.0, 12.0], [0.0, -0.3, 0.2, 8.0]], jnp.float32)
    x = _level_state((3.0, 0.0, 0.0))
    expected = Q.step(Q.step(x, pending[0], CONTROL_DT, params), pending[1], CONTROL_DT, params)
    np.testing.assert_allclose(policies.predict_through(x, pending, params, CONTROL_DT), expected, atol=1e-6)
    with pytest.raises(ValueError, match="model_latency_ticks"):
        PM.ControllerConfig(model_latency_ticks=4)


# --------------------------------------------------------------------------------------------------
# Every fault at once in a short closed loop.
# --------------------------------------------------------------------------------------------------

SMALL = PM.paper_mppi_config(num_samples=32, horizon=12)


@pytest.fixture(scope="module", params=["pixelmpc", pytest.param("mppi", marks=pytest.mark.slow)])  # same loop
def faulty_loop(request):
    """A few ticks of a controller on the filter under every fault at its severe level, with every lever on."""
    latency = F.fault_level(F.COMBINED, "severe").latency_ticks
    if request.param == "mppi":
        policy = policies.nominal_mppi_policy(SMALL, latency_ticks=latency, disturbance_tau=0.5)
    else:
        policy = policies.pixelmpc_policy(PM.ControllerConfig(mppi=SMALL, pixel_model="projection",
                                                            model_latency_ticks=latency,
                                                            disturbance_time_constant_s=0.5))
    config = env_lib.EnvConfig(max_time_s=0.4, estimator="pf", pf=pf_lib.PFConfig(num_particles=64),
                               faults=F.fault_level(F.COMBINED, "severe"),
                               guards=guards_lib.GuardConfig(detection_gate_px=30.0, recover_error_px=120.0,
                                                             imu_bias_std=(0.3, 0.02)))
    env, world = env_lib.make_env(config), env_lib.make_world(COURSE, target_speed=8.0)

    @jax.jit
    def tick(sim, policy_state, key):
        key_observe, key_step = jax.random.split(key)
        sim, obs = env.observe(world, sim, key_observe)
        u, policy_state, _ = policy.act(policy_state, obs, env_lib.policy_world(world))
        return env.step(world, sim, u, key_step), policy_state, u

    key, key_reset, key_policy = jax.random.split(jax.random.PRNGKey(5), 3)
    sim, policy_state, commands = env.reset(world, key_reset), policy.init(key_policy, env_lib.policy_world(world)), []
    while not bool(sim.done):
        key, key_tick = jax.random.split(key)
        sim, policy_state, u = tick(sim, policy_state, key_tick)
        commands.append(np.asarray(u))
    return sim, policy_state, np.stack(commands)


def test_every_fault_at_once_gives_finite_commands_and_a_named_end(faulty_loop):
    sim, policy_state, commands = faulty_loop
    assert commands.shape == (16, 4) and np.all(np.isfinite(commands))
    assert np.all(np.isfinite(np.asarray(sim.plant.x)))
    assert int(sim.end_cause) in env_lib.END_NAMES and int(sim.end_cause) != 0  # the 0.4 s limit: a timeout
    np.testing.assert_array_equal(policy_state.pending, commands[-3:])  # the commands the plant has not applied
    assert np.all(np.isfinite(np.asarray(policy_state.disturbance)))
    assert sim.filter.bias.shape == (64, 6) and np.all(np.isfinite(np.asarray(sim.filter.bias)))


# --------------------------------------------------------------------------------------------------
# A race's faults: the spec and the command line.
# --------------------------------------------------------------------------------------------------


def test_a_race_records_its_faults_and_keys_by_them():
    spec = RaceSpec("pixelmpc", speed=8.5, estimator="pf")
    record = spec.record()
    assert RaceSpec.from_record(record) == spec and record["faults"] == dataclasses.asdict(F.Faults())
    windy = spec.replace(faults=F.fault_level("wind", "moderate"), guards=guards_lib.GuardConfig(30.0))
    assert windy.key() != spec.key()
    assert RaceSpec.from_record(json.loads(json.dumps(windy.record()))).key() == windy.key()
    assert spec.replace(estimator="truth", guards=guards_lib.GuardConfig(30.0)).guards == guards_lib.GuardConfig()
    nominal = RaceSpec("mppi", PM.ControllerConfig(model_latency_ticks=2))
    assert nominal.config.model_latency_ticks == 2  # nominal MPPI flies the latency in its model too


def test_an_unknown_fault_in_a_record_is_refused_with_its_dotted_name():
    record = json.loads(json.dumps(RaceSpec(faults=F.Faults(gust=1.0)).record()))
    record["faults"]["gusts"] = 1.0
    with pytest.raises(ValueError, match="unknown setting faults.gusts: Faults has the fields"):
        RaceSpec.from_record(record)


@pytest.mark.parametrize("entry, message", [
    ("wind=3", "'wind=3': fault wind takes 3 numbers x,y,z"), ("wnd=1", "unknown fault 'wnd' in 'wnd=1'"),
    ("latency_ticks=1.5", "'latency_ticks=1.5': fault latency_ticks takes an integer"),
    ("miss_rate=2", "miss_rate takes a probability in [0, 1], got 2"), ("gust", "expected NAME=VALUE, got 'gust'"),
    ("gust=strong", "fault gust takes a number, got 'strong'"),
])
def test_the_fault_flag_refuses_a_bad_entry_in_one_line(entry, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as stop:
        cli.main(["race", "--out", str(tmp_path / "never"), "--fault", "gust=1", "--fault", entry])
    err = capsys.readouterr().err
    assert stop.value.code == EXIT_USAGE and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "never").exists()


def test_the_fault_flags_make_the_race(tmp_path):
    args = cli.build_parser().parse_args(
        ["race", "--out", str(tmp_path), "--estimator", "pf", "--fault", "gust=moderate", "--fault", "wind=1,2,0",
         "--fault", "gust=0.5", "--detection-gate", "25", "--pf-recover", "90", "--pf-recover-after", "3",
         "--model-latency", "1"])
    spec, _ = race_spec(args)
    assert spec.faults == F.Faults(wind=(1.0, 2.0, 0.0), gust=0.5)  # the later entry of a setting wins
    assert spec.guards == guards_lib.GuardConfig(detection_gate_px=25.0, recover_error_px=90.0,
                                                 recover_after_ticks=3)
    assert spec.config.model_latency_ticks == 1
    plain, _ = race_spec(cli.build_parser().parse_args(["race", "--out", str(tmp_path)]))
    assert plain.faults == F.Faults() and plain.guards == guards_lib.GuardConfig()


def test_the_kalman_filter_flags_set_it_and_need_it(tmp_path, capsys):
    args = cli.build_parser().parse_args(["race", "--out", str(tmp_path), "--estimator", "eskf",
                                          "--eskf-map-sigma", "0.5", "--eskf-align", "2",
                                          "--eskf-noise-adapt-rate", "0.05"])
    spec, _ = race_spec(args)
    assert spec.eskf.map_sigma_m == 0.5 and spec.eskf.align_s == 2.0 and spec.guards == guards_lib.GuardConfig()
    assert spec.eskf.noise_adapt_rate == 0.05
    plain, _ = race_spec(cli.build_parser().parse_args(["race", "--out", str(tmp_path), "--estimator", "eskf"]))
    assert plain.eskf.map_sigma_m == SURVEYED_MAP_SIGMA_M and plain.eskf.align_s == 0.0
    assert plain.eskf.noise_adapt_rate == 0.0
    exact, _ = race_spec(cli.build_parser().parse_args(["race", "--out", str(tmp_path), "--estimator", "eskf",
                                                        "--eskf-map-sigma", "0"]))
    assert exact.eskf.map_sigma_m == 0.0
    for argv, message in ((["--eskf-map-sigma", "0.2"], "--eskf-map-sigma sets the Kalman filter"),
                          (["--eskf-align", "2"], "--eskf-align sets the Kalman filter"),
                          (["--eskf-noise-adapt-rate", "0.05"], "--eskf-noise-adapt-rate sets the Kalman filter"),
                          (["--estimator", "eskf", "--eskf-noise-adapt-rate", "2"], "a finite number in [0, 1]"),
                          (["--estimator", "eskf", "--eskf-align", "-1"], "must be a finite number in [0, 60] s"),
                          (["--estimator", "eskf", "--eskf-map-sigma", "-1"], "must be a finite number in [0, 100] m")):
        try:
            code = cli.main(["race", "--out", str(tmp_path / "never"), *argv])
        except SystemExit as stop:  # argparse's own refusal
            code = stop.code
        err = capsys.readouterr().err
        assert code == EXIT_USAGE and message in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "never").exists()


def test_the_bias_flag_gives_the_filter_bias_states(tmp_path, capsys):
    args = cli.build_parser().parse_args(["race", "--out", str(tmp_path), "--estimator", "pf",
                                          "--pf-imu-bias", "0.3,0.02"])
    spec, _ = race_spec(args)
    assert spec.guards == guards_lib.GuardConfig(imu_bias_std=(0.3, 0.02)) and not spec.guards.active
    pf = guards_lib.filter_config(pf_lib.PFConfig(), spec.guards)
    assert pf.imu_bias_std == (0.3, 0.02) and pf.imu_bias_walk == pytest.approx((0.03, 0.002)) and pf.estimates_bias
    assert guards_lib.filter_config(pf_lib.PFConfig(), guards_lib.GuardConfig()) == pf_lib.PFConfig()
    with pytest.raises(SystemExit):
        cli.main(["race", "--out", str(tmp_path / "never"), "--pf-imu-bias", "0.3"])
    err = capsys.readouterr().err
    assert "takes two positive numbers ACCEL,GYRO" in err and len(err.strip().splitlines()) == 1
