"""The ESKF: equations (a hand-computed propagation, Jacobians against ``jax.jacfwd``), transformations (jit ==
no-jit, no recompilation), and behaviour on open-loop replays of flown laps with 2 px corner noise
(``tests/eskf_replay.py``): IMU biases learnt, a false detection ignored, a late detection applied where it
belongs, and the filter consistent (NEES and NIS inside their 95 % bands)."""

import dataclasses
import functools
import math

import eskf_replay
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import devices, timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import eskf as E
from pixelmpc_jax.perception.estimator import EstimatorParams
from pixelmpc_jax.sim import faults as faults_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

# the replays fly the map's own gates, so the filter is told the map is exact: its consistency, its gates and its
# noise's adaptation are measured against that (the default, a surveyed map's accuracy, widens every corner's noise)
CONFIG = E.ESKFConfig(map_sigma_m=0.0)
SPREAD = (0.3, 0.03, 0.2)  # the initial std of position m, attitude rad, velocity m/s (the environment's PF spread)
TICKS = 800  # 20 s per replay
NUM_REPLAYS = 20
ACCEL_BIAS = (0.2, -0.2, 0.2)  # m/s^2
GYRO_BIAS = (0.01, -0.01, 0.01)  # rad/s


@pytest.fixture(scope="module")
def course():
    return course_lib.load_course(), camera_lib.default_camera()


@pytest.fixture(scope="module")
def flights(course):
    """20 laps' first 20 s at 8.5 m/s, each with its own plant and detector noise (2 px), batched on axis 0."""
    track, camera = course
    keys = jax.random.split(jax.random.PRNGKey(2024), NUM_REPLAYS)
    fly = jax.jit(jax.vmap(lambda key: eskf_replay.fly(track, camera, key, TICKS, speed=8.5, pixel_noise_px=2.0)))
    return jax.device_get(fly(keys))


def _flight(flights, i):
    return jax.tree_util.tree_map(lambda a: a[i], flights)


@functools.cache
def _filter(config: E.ESKFConfig = CONFIG, spread: tuple = SPREAD) -> devices.CompiledEstimator:
    """The filter compiled once per configuration and spread."""
    return devices.compile_estimator(E.make_eskf(config, spread))


def _init(x0, config=CONFIG, spread=SPREAD):
    return _filter(config, spread).init(jax.random.PRNGKey(0), x0)


def _step(state, imu, detection, delay_ticks, track, camera, config=CONFIG):
    """One compiled tick. -> (the whole ``ESKFEstimate``, state, info)."""
    params = EstimatorParams(gates=track.gates, camera=camera, delay_ticks=delay_ticks)
    _, state, info = _filter(config).step(state, imu, detection, params)
    return info.estimate, state, info


def _run(imu, detections, delays, x0, track, camera, config=CONFIG):
    """The filter over a replay: its pure ``step`` per tick in a scan. -> (estimates, infos), leading axis T+1."""
    eskf = E.make_eskf(config, SPREAD)

    def tick(state, inputs):
        imu_k, detection_k, delay_k = inputs
        _, state, info = eskf.step(state, imu_k, detection_k, EstimatorParams(track.gates, camera, delay_k))
        return state, (info.estimate, info)

    return jax.lax.scan(tick, eskf.init(jax.random.PRNGKey(0), x0), (imu, detections, delays))[1]


_replay = jax.jit(_run)  # every replay has the same shapes: one compilation


@functools.cache
def _batched_run(config):
    """:func:`_run` with ``config`` over replays batched on axis 0, compiled once per config and shape."""
    return jax.jit(jax.vmap(functools.partial(_run, config=config), in_axes=(0, 0, 0, 0, None, None)))


def _replays(flights, course, config, imu=None):
    """The filter with ``config`` over batched ``flights``, every detection on time (``imu``: the flights' own when
    None). -> (estimates, infos), leading axes (replays, T+1)."""
    track, camera = course
    delays = np.zeros(flights.states.shape[:2], np.int32)
    return _batched_run(config)(flights.imu if imu is None else imu, flights.detections, delays,
                                flights.states[:, 0], track, camera)


def _on_time(flight):
    return np.zeros(flight.states.shape[0], np.int32)


def _without(detections, ticks):
    """The detections with those at ``ticks`` replaced by "nothing found"."""
    found = np.asarray(detections.found).copy()
    visible = np.asarray(detections.corners_visible).copy()
    found[list(ticks)], visible[list(ticks)] = False, False
    return detections.replace(found=found, corners_visible=visible)


def _replace_tick(detections, tick, detection):
    def put(a, b):
        a = np.asarray(a).copy()
        a[tick] = b
        return a

    return jax.tree_util.tree_map(put, detections, detection)


def _at(tree, tick):
    return jax.tree_util.tree_map(lambda a: a[tick], tree)


def _informative_tick(flight, start, corners=2):
    """The first tick from ``start`` whose detection has at least ``corners`` corners in view."""
    visible = np.asarray(flight.detections.corners_visible).sum(-1) * np.asarray(flight.detections.found)
    return start + int(np.argmax(visible[start:] >= corners))


def _chi2_band(dof):
    """The two-sided 95 % interval of chi-square with ``dof`` degrees of freedom (Wilson-Hilferty; within 0.1 % of
    the exact quantiles for dof >= 100)."""
    z = 1.959963984540054
    dof = np.asarray(dof, np.float64)
    c = 2.0 / (9.0 * dof)
    return dof * (1.0 - c - z * np.sqrt(c)) ** 3, dof * (1.0 - c + z * np.sqrt(c)) ** 3


# --------------------------------------------------------------------------------------------------
# Configuration and equations.
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("field, value", [
    ("accel_noise_density", -1.0), ("gyro_noise_density", math.nan), ("accel_bias_walk", math.inf),
    ("gyro_bias_std", -0.1), ("velocity_walk", -1e-3), ("border_margin_px", math.nan),
    ("measurement_sigma_px", 0.0), ("gate_chi2", -3.0), ("robust_loss", "l2"), ("robust_threshold", 0.0),
    ("max_delay_ticks", -1), ("max_delay_ticks", 2.5), ("max_delay_ticks", True), ("gravity", "9.81"),
    ("map_sigma_m", -0.1), ("align_s", -1.0), ("align_s", math.nan), ("noise_adapt_rate", 1.5),
    ("noise_adapt_rate", -0.1), ("noise_scale_max", 0.5), ("noise_scale_max", math.inf),
])
def test_a_bad_config_raises_one_line(field, value):
    with pytest.raises(ValueError, match=field) as error:
        E.ESKFConfig(**{field: value})
    assert "\n" not in str(error.value)


def test_the_alignment_at_rest_learns_the_gyro_bias_and_the_accelerometers_along_gravity_only():
    """Readings at rest, level: the gyro reads its bias, the accelerometer gravity's specific force plus its bias.
    The update takes the gyro bias and the vertical accelerometer bias to within their readings' noise, and splits
    each lateral reading between a tilt and a bias in proportion to their priors (it cannot tell them apart), so
    the two together explain the reading. Without the bias the same readings leave the belief's mean alone."""
    config = dataclasses.replace(CONFIG, align_s=2.0)
    x0 = jnp.asarray([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], jnp.float32)
    eskf = E.make_eskf(config, SPREAD)
    state = eskf.init(jax.random.PRNGKey(0), x0)
    accel_bias, gyro_bias = np.asarray(ACCEL_BIAS, np.float32), np.asarray(GYRO_BIAS, np.float32)
    accel = np.asarray([0.0, 0.0, config.gravity], np.float32) + accel_bias
    aligned = jax.jit(eskf.align)(state, accel, gyro_bias)
    for leaf, anchor_leaf in zip(jax.tree_util.tree_leaves(aligned.latest), jax.tree_util.tree_leaves(aligned.anchor)):
        np.testing.assert_array_equal(np.asarray(leaf), np.asarray(anchor_leaf))  # the window starts aligned
    belief = aligned.latest
    bias, cov = np.asarray(belief.bias), np.asarray(belief.cov)
    noise_std = np.asarray([config.accel_noise_density, config.gyro_noise_density]) / math.sqrt(config.align_s)
    np.testing.assert_allclose(bias[3:], gyro_bias, atol=1e-4)
    assert abs(bias[2] - accel_bias[2]) < 1e-3
    assert np.all(np.sqrt(np.diag(cov)[12:15]) < 1.01 * noise_std[1]) and np.sqrt(cov[11, 11]) < 1.01 * noise_std[0]
    # across gravity: the tilt takes the share its prior gives it, the bias the rest, the two explain the reading
    tilt_var, bias_var = (SPREAD[1] * config.gravity) ** 2, config.accel_bias_std**2
    share = bias_var / (bias_var + tilt_var)
    np.testing.assert_allclose(bias[:2], share * accel_bias[:2], rtol=0.02)
    q = np.asarray(belief.x[3:7])
    felt = np.asarray(quadrotor.rotation_matrix(jnp.asarray(q))).T @ np.asarray([0.0, 0.0, config.gravity])
    np.testing.assert_allclose(felt[:2] + bias[:2], accel[:2], atol=2e-3)
    assert np.sqrt(cov[9, 9]) < 0.9 * config.accel_bias_std and cov[9, 7] != 0.0  # tied to the tilt, learnt in part
    kept = [0, 1, 2, 7, 8, 9]  # position and velocity: no reading at rest tells them (nor their prior ties them)
    np.testing.assert_array_equal(np.asarray(belief.x)[kept], np.asarray(x0)[kept])
    unbiased = jax.jit(eskf.align)(state, np.asarray([0.0, 0.0, config.gravity], np.float32),
                                   np.zeros(3, np.float32)).latest
    np.testing.assert_allclose(np.asarray(unbiased.x), np.asarray(x0), atol=1e-6)
    np.testing.assert_allclose(np.asarray(unbiased.bias), 0.0, atol=1e-6)
    assert E.make_eskf(CONFIG).align is None  # no readings on the pad: nothing to align on


def test_bad_inputs_raise_one_line(course):
    track, camera = course
    with pytest.raises(ValueError, match="x0 must have shape") as error:
        _init(jnp.zeros(9))
    assert "\n" not in str(error.value)
    state = _init(track.start)
    with pytest.raises(ValueError, match="delay_ticks must lie in") as error:
        _step(state, None, None, CONFIG.max_delay_ticks + 1, track, camera)
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="max_delay_ticks=1"):
        E.make_eskf(dataclasses.replace(CONFIG, max_delay_ticks=1)).check(
            state, None, None, EstimatorParams(track.gates, camera))


def test_at_rest_the_state_stays_and_the_covariance_grows_by_hand(course):
    """At rest, level, yawed, with a perfect hover IMU and no detection: one tick from a prior on the biases only
    (no position, velocity or attitude uncertainty) gives, with T = 1/40 s, sigma_a, sigma_g the noise densities,
    s_a, s_g the bias stds, q_a, q_g their walks, w_v, w_th the velocity and attitude walks and R the attitude:
    P_vv = (T^2 s_a^2 + sigma_a^2 T + w_v^2 T) I, P_pp = T^2 / 4 (T^2 s_a^2 + sigma_a^2 T) I, P_pv = T / 2 (same),
    P_thth = (T^2 s_g^2 + sigma_g^2 T + w_th^2 T) I, P_v,ba = -T s_a^2 R, P_p,ba = -T^2 / 2 s_a^2 R,
    P_th,bg = -T s_g^2 I, P_ba = (s_a^2 + q_a^2 T) I, P_bg = (s_g^2 + q_g^2 T) I. Over 2 s the nominal state does
    not move and the position covariance grows every tick."""
    track, camera = course
    x0 = quadrotor.hover_state((1.0, 2.0, 3.0), yaw=0.6)
    imu = plant_lib.hover_tick_imu(timing.CONTROL_DT)
    state = _init(x0, spread=(0.0, 0.0, 0.0))
    estimate, state, _ = _step(state, imu, None, 0, track, camera)
    T, c = timing.CONTROL_DT, CONFIG
    R = np.asarray(quadrotor.rotation_matrix(x0[3:7]))
    accel = T * T * c.accel_bias_std**2 + c.accel_noise_density**2 * T  # the accelerometer's share of P_vv
    I3 = np.eye(3)
    blocks = {(0, 0): T * T / 4 * accel * I3, (0, 3): T / 2 * accel * I3, (3, 3): (accel + c.velocity_walk**2 * T) * I3,
              (6, 6): (T * T * c.gyro_bias_std**2 + (c.gyro_noise_density**2 + c.attitude_walk**2) * T) * I3,
              (3, 9): -T * c.accel_bias_std**2 * R, (0, 9): -T * T / 2 * c.accel_bias_std**2 * R,
              (6, 12): -T * c.gyro_bias_std**2 * I3, (9, 9): (c.accel_bias_std**2 + c.accel_bias_walk**2 * T) * I3,
              (12, 12): (c.gyro_bias_std**2 + c.gyro_bias_walk**2 * T) * I3}
    expected = np.zeros((15, 15))
    for (i, j), block in blocks.items():
        expected[i:i + 3, j:j + 3] = block
        expected[j:j + 3, i:i + 3] = block.T
    cov = np.asarray(estimate.covariance, np.float64)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))  # correlations: every entry to the same scale
    np.testing.assert_allclose(cov / scale, expected / scale, atol=2e-5)
    traces = []
    for _ in range(80):
        estimate, state, info = _step(state, imu, None, 0, track, camera)
        traces.append(float(info.position_cov_trace))
    np.testing.assert_allclose(estimate.mean, x0, atol=2e-5)
    np.testing.assert_array_equal(estimate.bias, 0.0)
    assert np.all(np.diff(traces) > 0)


def _random_belief(key):
    key_p, key_q, key_v, key_b = jax.random.split(key, 4)
    q = quadrotor.normalize_quat(jax.random.normal(key_q, (4,)))
    x = jnp.concatenate([jax.random.normal(key_p, (3,)) * 2.0, q, jax.random.normal(key_v, (3,)) * 5.0])
    bias = jax.random.normal(key_b, (6,)) * jnp.asarray([0.3] * 3 + [0.03] * 3)
    return E.ESKFBelief(x=x, bias=bias, cov=jnp.eye(15), noise_scale=jnp.ones(()))


@jax.jit
def _propagation_jacfwd(belief, imu):
    """jax.jacfwd of the propagation of the injected error state, read back as an error state. -> (15, 21)."""
    x_next = E.propagate_nominal(belief.x, belief.bias, imu)

    def error_after(z):  # z (21,): the error state and the tick's mean IMU noise
        x, bias = E.inject(belief.x, belief.bias, z[:15])
        moved = E.propagate_preintegrated(x, imu, z[15:18] - bias[:3], z[18:] - bias[3:])
        return jnp.concatenate([E.state_error(x_next, moved), bias - belief.bias])

    return jax.jacfwd(error_after)(jnp.zeros(21))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_propagation_jacobians_match_jacfwd(seed):
    belief = _random_belief(jax.random.PRNGKey(seed))
    key_q, key_v, key_p = jax.random.split(jax.random.PRNGKey(100 + seed), 3)
    delta_q = quadrotor.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.05 * jax.random.normal(key_q, (4,)))
    imu = E.ImuInput(delta_q=delta_q, delta_v=jax.random.normal(key_v, (3,)),
                     delta_p=0.01 * jax.random.normal(key_p, (3,)), dt=jnp.asarray(timing.CONTROL_DT))
    jacobian = _propagation_jacfwd(belief, imu)
    F, G = jax.jit(E.propagation_jacobians)(belief, imu)
    np.testing.assert_allclose(F, jacobian[:, :15], atol=2e-6)
    np.testing.assert_allclose(G, jacobian[:, 15:], atol=2e-6)


@jax.jit
def _corner_jacfwd(x, corners, camera):
    """jax.jacfwd of the pixels of the corners seen from the injected state. -> (4, 2), (4, 2, 15)."""
    scale = jnp.asarray([camera.width, camera.height])

    def pixels(dx):
        moved, _ = E.inject(x, jnp.zeros(6), dx)
        return camera_lib.project(corners, moved, camera)[0] * scale

    return pixels(jnp.zeros(15)), jax.jacfwd(pixels)(jnp.zeros(15))


@pytest.mark.parametrize("seed", [0, 1])
def test_corner_jacobian_matches_jacfwd(course, seed):
    track, camera = course
    gate = track.gate(0)
    key_p, key_a = jax.random.split(jax.random.PRNGKey(seed))
    x = track.start.at[:3].add(jnp.asarray([0.0, 8.0, 0.5]) + jax.random.normal(key_p, (3,)))
    x = x.at[3:7].set(quadrotor.quat_multiply(x[3:7], quadrotor.quat_exp(0.2 * jax.random.normal(key_a, (3,)), 1.0)))
    uv_px, jacobian, in_front = jax.jit(E.reproject_corners)(x, gate.corners(), camera)
    expected_uv, expected_jacobian = _corner_jacfwd(x, gate.corners(), camera)
    assert bool(jnp.all(in_front))
    np.testing.assert_allclose(uv_px, expected_uv, atol=1e-4)
    np.testing.assert_allclose(jacobian, expected_jacobian, rtol=1e-4, atol=1e-3)


def test_inject_and_state_error_are_inverse_and_nees_is_a_quadratic_form():
    belief = _random_belief(jax.random.PRNGKey(5))
    dx = 0.1 * jax.random.normal(jax.random.PRNGKey(6), (15,))
    x, bias = E.inject(belief.x, belief.bias, dx)
    np.testing.assert_allclose(E.state_error(belief.x, x), dx[:9], atol=2e-6)
    np.testing.assert_allclose(bias - belief.bias, dx[9:], atol=1e-7)
    cov = jnp.diag(jnp.arange(1.0, 16.0))
    estimate = E.ESKFEstimate(mean=belief.x, position_cov=cov[:3, :3], bias=belief.bias, covariance=cov)
    np.testing.assert_allclose(E.nees(estimate, x), np.sum(np.asarray(dx[:9]) ** 2 / np.arange(1.0, 10.0)),
                               rtol=1e-4)


# --------------------------------------------------------------------------------------------------
# Transformations.
# --------------------------------------------------------------------------------------------------


def test_one_step_jit_equals_no_jit(course, flights):
    """A step that files a detection one tick late (a replay of two ticks), jitted and not."""
    track, camera = course
    flight = _flight(flights, 0)
    tick = _informative_tick(flight, 300)
    state = _init(flight.states[tick - 2])
    _, state, _ = _step(state, _at(flight.imu, tick - 1), None, 0, track, camera)
    args = (state, _at(flight.imu, tick), _at(flight.detections, tick - 1), 1, track, camera)
    jitted = _step(*args)
    with jax.disable_jit():
        plain = _step(*args)
    assert int(np.sum(jitted[2].accepted)) >= 2
    for a, b in zip(jax.tree_util.tree_leaves(jitted), jax.tree_util.tree_leaves(plain)):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=1e-4, atol=1e-6)


def test_no_recompilation_across_steps(course, flights):
    track, camera = course
    flight = _flight(flights, 1)
    state = _init(flight.states[0])
    _, state, _ = _step(state, _at(flight.imu, 0), _at(flight.detections, 0), 0, track, camera)
    before = _filter().num_compilations()
    for k in range(1, 4):
        _, state, _ = _step(state, _at(flight.imu, k), _at(flight.detections, k), k - 1, track, camera)
    assert _filter().num_compilations() == before


# --------------------------------------------------------------------------------------------------
# Behaviour on replays of flown laps.
# --------------------------------------------------------------------------------------------------


def test_a_constant_imu_bias_is_learnt_within_20_percent(course, flights):
    """The moderate IMU bias of ``sim/faults.py``'s size on every axis (0.2 m/s^2, 0.01 rad/s), added as the faults
    add it: after 20 s each axis of both biases is within 20 % of the truth and within 3 sigma of the filter's own
    covariance. (After 10 s the lateral accelerometer bias is not yet: the corners of a far gate barely tell a roll
    error from a lateral bias, and its 1 sigma is still 22 % of 0.2 m/s^2 on the median replay, even with every
    model walk set to zero; 12 of 20 replays had every axis within 20 % at 10 s, 19 at 15 s, all 20 at 20 s. The
    slow test below measures that bound.)"""
    track, camera = course
    flight = _flight(flights, 0)
    faults = faults_lib.Faults(imu_accel_bias=ACCEL_BIAS, imu_gyro_bias=GYRO_BIAS)
    imu = jax.vmap(lambda tick_imu: faults_lib.corrupt_imu(tick_imu, faults, jax.random.PRNGKey(0)))(flight.imu)
    estimates, _ = _replay(imu, flight.detections, _on_time(flight), flight.states[0], track, camera)
    truth = np.asarray(ACCEL_BIAS + GYRO_BIAS)
    final = np.asarray(estimates.bias[-1])
    sigma = np.sqrt(np.diag(np.asarray(estimates.covariance[-1]))[9:])
    assert np.all(np.abs(final - truth) <= 0.2 * np.abs(truth)), (final, truth)
    assert np.all(np.abs(final - truth) <= 3.0 * sigma), (final - truth, sigma)
    assert np.all(np.abs(np.asarray(estimates.bias[0]) - truth) > 0.5 * np.abs(truth))  # it started far off


@pytest.mark.slow  # ~15 s: the 20 replays twice; the evidence for asserting the bias at 20 s above, not 10 s
def test_at_10_s_the_lateral_accelerometer_bias_is_not_yet_in_the_data(course, flights):
    """Why the test above waits 20 s: both biases on the 20 replays, and the filter's own std of each bias at 10 s
    with every model walk (velocity, attitude, both biases) set to zero. Those walks only add noise to the
    vehicle's own, so this covariance is a lower bound (to first order) on any estimator's given the IMU and the
    target's corners. On the median replay the lateral (body y) accelerometer bias's 1 sigma at 10 s is still over
    15 % of 0.2 m/s^2 (measured 22 %): with 20 % as the bar, every axis within it is a toss of a coin, and the
    filter's errors match its stds (the default filter passes on 12 of 20). At 20 s the bound is under 10 % on
    every axis, and the default filter's errors are within 3 of its own sigmas."""
    faults = faults_lib.Faults(imu_accel_bias=ACCEL_BIAS, imu_gyro_bias=GYRO_BIAS)
    truth = np.abs(np.asarray(ACCEL_BIAS + GYRO_BIAS))
    ideal = dataclasses.replace(CONFIG, velocity_walk=0.0, attitude_walk=0.0, accel_bias_walk=0.0,
                                gyro_bias_walk=0.0)

    corrupt = jax.vmap(jax.vmap(lambda tick_imu: faults_lib.corrupt_imu(tick_imu, faults, jax.random.PRNGKey(0))))
    imu = corrupt(flights.imu)

    def replay(config):
        estimates, _ = _replays(flights, course, config, imu)
        sigma = np.sqrt(np.diagonal(np.asarray(estimates.covariance), axis1=-2, axis2=-1)[..., 9:])
        bias = np.asarray(estimates.bias)
        return np.abs(bias - np.asarray(ACCEL_BIAS + GYRO_BIAS)) / truth, sigma / truth  # relative to the bias

    ten, twenty = 10 * timing.CONTROL_HZ, TICKS
    _, bound = replay(ideal)
    assert np.median(bound[:, ten, 1]) > 0.15, np.median(bound[:, ten], 0)
    assert np.all(np.median(bound[:, twenty], 0) < 0.10), np.median(bound[:, twenty], 0)
    error, sigma = replay(CONFIG)
    assert np.all(error[:, twenty] <= 3.0 * sigma[:, twenty]), (error[:, twenty] / sigma[:, twenty]).max(0)
    assert np.sum(np.all(error[:, ten] <= 0.2, axis=1)) < NUM_REPLAYS  # some replay misses the 20 % bar at 10 s


def test_the_corner_noise_adapts_to_a_noisier_detector_and_holds_at_the_told_one(course, flights):
    """Corners 3x noisier than the filter's 2 px (the severe fault's 6 px: 4 replays of 15 s, their corners given
    another sqrt(6^2 - 2^2) px of noise): told 2 px and not adapting, the gate rejects most corners and the estimate
    drifts metres off; with ``noise_adapt_rate`` the scale of the corners' variance settles near 3^2 = 9 and the
    estimate stays within a metre. On the same replays' 2 px corners the scale stays near 1, and without adapting it
    is 1 exactly."""
    camera = course[1]
    two_px = jax.tree_util.tree_map(lambda a: np.asarray(a[:4, :600]), flights)
    extra = math.sqrt(6.0**2 - 2.0**2) / np.asarray([camera.width, camera.height], np.float32)  # normalised uv
    noise = np.random.default_rng(31).normal(size=two_px.detections.corners.shape).astype(np.float32) * extra
    noisy = two_px._replace(detections=two_px.detections.replace(corners=two_px.detections.corners + noise))
    adapting = dataclasses.replace(CONFIG, noise_adapt_rate=0.05)

    def replay(config, flights):
        estimates, info = _replays(flights, course, config)
        error = np.linalg.norm(np.asarray(estimates.mean)[..., :3] - np.asarray(flights.states)[..., :3], axis=-1)
        return np.sqrt(np.mean(error**2, axis=1)), np.asarray(info.noise_scale)  # RMS per replay, scale per tick

    rms, scale = replay(adapting, noisy)
    assert np.all(rms < 1.0), rms
    assert 6.0 < np.median(scale[:, -200:]) < 13.0, np.median(scale[:, -200:])
    rms_told, scale_told = replay(CONFIG, noisy)
    assert np.all(scale_told == 1.0)
    assert np.median(rms_told) > 3.0 * np.median(rms), (rms_told, rms)
    rms_2px, scale_2px = replay(adapting, two_px)
    assert np.all(scale_2px >= 1.0) and np.all(scale_2px[:, 200:] < 1.6), scale_2px[:, 200:].max()
    assert np.median(scale_2px[:, 200:]) < 1.2
    assert np.all(rms_2px < 0.5), rms_2px


def test_a_false_detection_far_from_the_prediction_changes_nothing(course, flights):
    """The target's visible corners reported 40 px across and 30 px along the image from where they are: the
    estimate (state and covariance) over the whole replay is bit for bit that of a replay without a detection at
    that tick, while the true detection at that tick is accepted and does change it."""
    track, camera = course
    flight = _flight(flights, 0)
    tick = _informative_tick(flight, 400)
    true = _at(flight.detections, tick)
    corners = np.asarray(true.corners) * [camera.width, camera.height]
    visible = np.asarray(true.corners_visible)
    shift = np.where(corners[visible].mean(0) < [camera.width / 2, camera.height / 2], 1.0, -1.0) * [40.0, 30.0]
    moved = corners + shift
    assert np.all((moved[visible] > 10.0) & (moved[visible] < [camera.width - 10.0, camera.height - 10.0]))
    false = true.replace(corners=(moved / [camera.width, camera.height]).astype(np.float32))
    runs = {}
    for name, detection in (("true", true), ("false", false), ("none", None)):
        detections = _without(flight.detections, [tick]) if detection is None else \
            _replace_tick(flight.detections, tick, detection)
        runs[name] = _replay(flight.imu, detections, _on_time(flight), flight.states[0], track, camera)
    (false_estimates, false_info), (none_estimates, _) = runs["false"], runs["none"]
    assert not np.any(false_info.accepted[tick]) and np.all(false_info.corner_mahalanobis2[tick][visible] > 100.0)
    for a, b in zip(jax.tree_util.tree_leaves(false_estimates), jax.tree_util.tree_leaves(none_estimates)):
        np.testing.assert_array_equal(a, b)
    true_estimates, true_info = runs["true"]
    assert np.sum(true_info.accepted[tick]) >= 2
    assert np.max(np.abs(true_estimates.covariance[tick] - none_estimates.covariance[tick])) > 1e-5


def test_a_map_sigma_adds_the_gates_offset_to_the_corners_noise_and_moves_the_estimate_less(course):
    """A gate standing 0.3 m beside its mapped place (sideways, 5.5 px in the image), seen from 6 m before it by a
    filter sure of its pose to 5 cm: with ``map_sigma_m`` each corner's prior
    innovation covariance is the exact map's plus sigma^2 H_p H_p^T (H_p the corners' Jacobian with respect to the
    position), the joint NIS is smaller, and the estimate moves less toward the pose that explains the moved gate."""
    track, camera = course
    gate = track.gate(0)
    x0 = track.start.at[0:3].set(gate.centre - 6.0 * gate.normal)
    moved = gate.replace(centre=gate.centre + 0.3 * gate.rotation[:, 1])  # along the gate's lateral axis
    detection = detector_lib.detect_from_geometry(moved, x0, camera, gate_id=0)
    assert bool(detection.found) and int(np.sum(detection.corners_visible)) == 4
    sigma = 0.2
    runs = {}
    for name, config in (("exact", CONFIG), ("map", dataclasses.replace(CONFIG, map_sigma_m=sigma)),
                         ("tiny", dataclasses.replace(CONFIG, map_sigma_m=1e-4))):
        state = _init(x0, config, (0.05, 0.01, 0.1))
        estimate, _, info = _step(state, None, detection, 0, track, camera, config)
        runs[name] = estimate, info
    (exact, exact_info), (mapped, map_info), (tiny, _) = runs["exact"], runs["map"], runs["tiny"]
    assert np.all(exact_info.accepted) and np.all(map_info.accepted)
    _, H, _ = E.reproject_corners(x0, gate.corners(), camera)
    H_pos = np.asarray(H)[..., 0:3]
    expected = np.asarray(exact_info.innovation_cov) + sigma**2 * H_pos @ np.swapaxes(H_pos, -1, -2)
    np.testing.assert_allclose(map_info.innovation_cov, expected, rtol=1e-4)
    assert float(map_info.nis) < 0.8 * float(exact_info.nis)
    moved_exact = np.abs(np.asarray(E.state_error(x0, exact.mean)))  # [dp, dv, dtheta]
    moved_map = np.abs(np.asarray(E.state_error(x0, mapped.mean)))
    assert np.linalg.norm(moved_exact[0:3]) > 0.05 and moved_exact[8] > 0.01  # a step sideways and a turn (yaw)
    assert np.linalg.norm(moved_map[0:3]) < 0.5 * np.linalg.norm(moved_exact[0:3])
    assert moved_map[8] < 0.5 * moved_exact[8]
    np.testing.assert_allclose(tiny.mean, exact.mean, atol=1e-5)


def test_a_detection_two_ticks_late_gives_the_on_time_estimate(course, flights):
    """One detection: delivered on time, or 2 ticks late (the two ticks between without one), or never. From the
    tick it is delivered on, the late filter's estimate is the on-time one within 1e-5; before, it is not, and the
    late detection made a difference. A whole replay with every detection 2 ticks late: each detection's NIS is
    that of the on-time replay's at its capture tick, and the last estimate that of an on-time replay without the
    last two detections."""
    track, camera = course
    flight = _flight(flights, 0)
    tick = _informative_tick(flight, 300, corners=3)
    detection = _at(flight.detections, tick)
    on_time = _without(flight.detections, [tick + 1, tick + 2])
    never = _without(flight.detections, [tick, tick + 1, tick + 2])
    late = _replace_tick(never, tick + 2, detection)
    delays = _on_time(flight)
    late_delays = delays.copy()
    late_delays[tick + 2] = 2
    x0 = flight.states[0]
    on_time_estimates, on_time_info = _replay(flight.imu, on_time, delays, x0, track, camera)
    late_estimates, late_info = _replay(flight.imu, late, late_delays, x0, track, camera)
    never_estimates, _ = _replay(flight.imu, never, delays, x0, track, camera)
    for a, b in zip(jax.tree_util.tree_leaves(on_time_estimates), jax.tree_util.tree_leaves(late_estimates)):
        np.testing.assert_allclose(a[tick + 2:], b[tick + 2:], rtol=1e-5, atol=1e-5)
    assert np.max(np.abs(on_time_estimates.covariance[tick] - late_estimates.covariance[tick])) > 1e-5
    assert np.max(np.abs(never_estimates.covariance[tick + 2] - late_estimates.covariance[tick + 2])) > 1e-5
    np.testing.assert_allclose(late_info.nis[tick + 2], on_time_info.nis[tick], rtol=1e-5)
    assert int(late_info.delay_ticks[tick + 2]) == 2 and int(late_info.nis_dof[tick + 2]) >= 6

    stream = jax.tree_util.tree_map(lambda a: np.concatenate([np.zeros_like(a[:2]), a[:-2]]),
                                    flight.detections)  # detection k delivered at tick k + 2, none at ticks 0, 1
    stream_estimates, stream_info = _replay(flight.imu, stream, np.full_like(delays, 2), x0, track, camera)
    full_estimates, full_info = _replay(flight.imu, flight.detections, delays, x0, track, camera)
    np.testing.assert_allclose(stream_info.nis[2:], full_info.nis[:-2], rtol=1e-5, atol=1e-5)
    cut = _without(flight.detections, [TICKS - 1, TICKS])
    cut_estimates, _ = _replay(flight.imu, cut, delays, x0, track, camera)
    for a, b in zip(jax.tree_util.tree_leaves(_at(stream_estimates, -1)),
                    jax.tree_util.tree_leaves(_at(cut_estimates, -1))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_the_filter_is_consistent_over_20_replays(course, flights):
    """20 laps, each with its own plant, IMU and detector noise, an initial error drawn from the filter's spread and
    IMU biases drawn from its prior: on at least 90 % of the ticks where every replay has a detection, the
    run-averaged NEES of position, velocity and attitude (9 dof) lies in its 95 % band for 20 runs (chi-square with
    180 dof / 20, about [7.2, 11.0]), and the summed NIS of the accepted corners in its band (chi-square with their
    summed dof). Measured: 92 % (NEES) and 95 % (NIS) of the ticks here; over four sets of 20 laps the NEES share was
    85-92 %, the NIS share 94-95 %: the criterion sits at the edge of what this EKF does (module docstring)."""
    track, camera = course
    key_state, key_bias = jax.random.split(jax.random.PRNGKey(7))
    stds = np.asarray([SPREAD[0]] * 3 + [SPREAD[2]] * 3 + [SPREAD[1]] * 3)
    bias_stds = np.asarray([CONFIG.accel_bias_std] * 3 + [CONFIG.gyro_bias_std] * 3)
    nees, nis, dof = [], [], []
    for i in range(NUM_REPLAYS):
        flight = _flight(flights, i)
        error = stds * np.asarray(jax.random.normal(jax.random.fold_in(key_state, i), (9,)))
        bias = bias_stds * np.asarray(jax.random.normal(jax.random.fold_in(key_bias, i), (6,)))
        x0, _ = E.inject(flight.states[0], jnp.zeros(6), -np.concatenate([error, np.zeros(6)]))
        imu = jax.vmap(eskf_replay.with_imu_bias, in_axes=(0, None, None))(flight.imu, bias[:3], bias[3:])
        estimates, info = _replay(imu, flight.detections, _on_time(flight), x0, track, camera)
        nees.append(np.asarray(jax.vmap(E.nees)(estimates, flight.states)))
        nis.append(np.asarray(info.nis))
        dof.append(np.asarray(info.nis_dof))
    nees, nis, dof = np.stack(nees), np.stack(nis), np.stack(dof)  # (20, T+1)
    detected = np.all(dof > 0, axis=0)
    assert detected.sum() > 0.5 * (TICKS + 1)
    low, high = _chi2_band(9 * NUM_REPLAYS)
    summed_nees = nees.sum(0)[detected]
    inside = (summed_nees >= low) & (summed_nees <= high)
    assert inside.mean() >= 0.9, (inside.mean(), np.percentile(summed_nees / NUM_REPLAYS, [5, 50, 95]))
    total_dof = dof.sum(0)[detected]
    low, high = _chi2_band(total_dof)
    total_nis = nis.sum(0)[detected]
    inside = (total_nis >= low) & (total_nis <= high)
    assert inside.mean() >= 0.9, (inside.mean(), np.percentile(total_nis / total_dof, [5, 50, 95]))
