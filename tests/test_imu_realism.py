"""A racing drone's IMU and start (issue 74, item 3): the IMU the filter reads carries biases drawn per lap from a
datasheet and noise at its density, the Kalman filter is told the datasheet, and the filter starts off the truth, each
an option that is off by default. Nothing here flies a closed loop: the environment's reset and one step, and the
sensor model alone."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import cli, timing
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.commands.race import race_spec
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import eskf as eskf_lib
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import imu as imu_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.sim import start_error as start_lib
from pixelmpc_jax.world import course as course_lib

SPEC = imu_lib.ICM_42688_P
KALMAN = env_lib.EnvConfig(max_time_s=10.0, estimator="eskf")
HOVER = quadrotor.hover_control(quadrotor.QuadParams())


@pytest.fixture(scope="module")
def world():
    return env_lib.make_world(course_lib.straight_course(num_gates=3, spacing=15.0, first_gate_x=12.0),
                              target_speed=8.0)


def _zero_tick(num_samples: int = timing.SUBSTEPS_PER_TICK) -> plant_lib.TickIMU:
    zero = jnp.zeros(3, jnp.float32)
    return plant_lib.TickIMU(accel=zero, gyro=zero, delta_q=jnp.asarray([1.0, 0.0, 0.0, 0.0]), delta_v=zero,
                             delta_p=zero, dt=jnp.asarray(num_samples * timing.PLANT_DT, jnp.float32),
                             num_samples=jnp.asarray(num_samples, jnp.float32))


def test_the_spec_holds_the_datasheet_figures_in_si_units():
    # DS-000347: 2.8 mdps/sqrt(Hz), 70 ug/sqrt(Hz), +-0.5 dps, +-20 mg
    assert SPEC.gyro_noise_density == pytest.approx(2.8e-3 * math.pi / 180.0)  # 4.89e-5 rad/s/sqrt(Hz)
    assert SPEC.accel_noise_density == pytest.approx(70e-6 * 9.80665)  # 6.86e-4 m/s^2/sqrt(Hz)
    assert SPEC.gyro_bias_tolerance == pytest.approx(0.5 * math.pi / 180.0)  # 8.73e-3 rad/s
    assert SPEC.accel_bias_tolerance == pytest.approx(0.02 * 9.80665)  # 0.196 m/s^2
    assert "DS-000347" in SPEC.source and imu_lib.IMU_SPECS["icm42688p"] is SPEC
    with pytest.raises(ValueError, match="gyro_noise_density must be a finite number >= 0"):
        dataclasses.replace(SPEC, gyro_noise_density=-1.0)


def test_each_lap_draws_its_own_biases_within_the_datasheet_tolerance():
    errors = jax.vmap(lambda key: imu_lib.draw_errors(SPEC, key))(jax.random.split(jax.random.PRNGKey(3), 2000))
    for bias, tolerance in ((errors.accel_bias, SPEC.accel_bias_tolerance),
                            (errors.gyro_bias, SPEC.gyro_bias_tolerance)):
        bias = np.asarray(bias)
        assert np.all(np.abs(bias) <= tolerance) and np.max(np.abs(bias)) > 0.95 * tolerance
        np.testing.assert_allclose(bias.std(axis=0), tolerance / math.sqrt(3.0), rtol=0.08)  # uniform in +-tolerance
        assert len(np.unique(bias, axis=0)) == len(bias)  # a different bias for every lap key


def test_the_noise_has_the_datasheet_density_at_the_plant_rate():
    """A tick's mean of 24 samples of white noise of density d at 960 Hz has std d / sqrt(1/40 s); the pad's mean
    over 2 s, d / sqrt(2 s)."""
    none = imu_lib.ImuErrors(accel_bias=jnp.zeros(3), gyro_bias=jnp.zeros(3))
    keys = jax.random.split(jax.random.PRNGKey(5), 6000)
    for tick in (_zero_tick(), _zero_tick(1920)):
        read = jax.vmap(lambda key, tick=tick: imu_lib.read(tick, none, SPEC, key))(keys)
        seconds = float(tick.dt)
        np.testing.assert_allclose(np.asarray(read.accel).std(axis=0), SPEC.accel_noise_density / math.sqrt(seconds),
                                   rtol=0.05)
        np.testing.assert_allclose(np.asarray(read.gyro).std(axis=0), SPEC.gyro_noise_density / math.sqrt(seconds),
                                   rtol=0.05)
        np.testing.assert_allclose(read.delta_v, read.accel * seconds, rtol=1e-5, atol=1e-9)  # integrated alike
    accel_std, gyro_std = imu_lib.sample_std(SPEC)
    assert accel_std == pytest.approx(SPEC.accel_noise_density * math.sqrt(960.0))


def test_the_imu_the_filter_reads_carries_the_laps_bias(world):
    """Reset and one tick with the spec's IMU against the same tick without it (same keys, same plant): the filter's
    tick differs by the lap's bias plus noise at the datasheet's density; another lap key draws another bias."""
    key, tick_key = jax.random.PRNGKey(11), jax.random.PRNGKey(12)
    plain, spec = env_lib.make_env(KALMAN), env_lib.make_env(dataclasses.replace(KALMAN, imu="icm42688p"))
    plain_state, spec_state = plain.reset(world, key), spec.reset(world, key)
    assert plain_state.imu_errors is None
    bias = spec_state.imu_errors
    assert not np.allclose(bias.gyro_bias, spec.reset(world, jax.random.PRNGKey(13)).imu_errors.gyro_bias)
    noise = 6.0 * SPEC.gyro_noise_density / math.sqrt(timing.CONTROL_DT), \
        6.0 * SPEC.accel_noise_density / math.sqrt(timing.CONTROL_DT)
    np.testing.assert_allclose(spec_state.imu.gyro - plain_state.imu.gyro, bias.gyro_bias, atol=noise[0])
    flown_plain = plain.step(world, plain_state, HOVER, tick_key)
    flown_spec = spec.step(world, spec_state, HOVER, tick_key)
    np.testing.assert_array_equal(flown_spec.plant.x, flown_plain.plant.x)  # the world flies the same tick
    np.testing.assert_allclose(flown_spec.imu.gyro - flown_plain.imu.gyro, bias.gyro_bias, atol=noise[0])
    np.testing.assert_allclose(flown_spec.imu.accel - flown_plain.imu.accel, bias.accel_bias, atol=noise[1])
    assert np.max(np.abs(bias.gyro_bias)) > 10 * noise[0] / 6.0  # the bias stands out of the noise


def test_the_kalman_filter_is_told_the_datasheet_not_the_simulator():
    told = env_lib.make_estimator(dataclasses.replace(KALMAN, imu="icm42688p")).config
    assert (told.accel_noise_density, told.gyro_noise_density) == (SPEC.accel_noise_density, SPEC.gyro_noise_density)
    assert (told.accel_bias_std, told.gyro_bias_std) == (SPEC.accel_bias_tolerance, SPEC.gyro_bias_tolerance)
    assert told.accel_bias_walk == KALMAN.eskf.accel_bias_walk  # the datasheet states no bias instability
    simulator = env_lib.make_estimator(KALMAN).config  # off: the simulator's own noise, as before
    assert simulator == eskf_lib.ESKFConfig()
    assert simulator.gyro_noise_density == pytest.approx(math.sqrt(eskf_lib.PLANT_GYRO_VARIANCE * timing.PLANT_DT))


def _attitude_error(q_filter, q_true) -> np.ndarray:
    """(3,) rad, the body-frame rotation vector from the true attitude to the filter's."""
    return np.asarray(eskf_lib.rotation_vector(quadrotor.quat_multiply(quadrotor.quat_conjugate(q_true), q_filter)))


def test_the_filter_starts_off_the_truth_only_with_the_option(world):
    x0 = world.track.start
    for estimator in ("eskf", "pf"):
        config = dataclasses.replace(KALMAN, estimator=estimator)
        for key in (jax.random.PRNGKey(1), jax.random.PRNGKey(2)):
            exact = env_lib.make_env(config).reset(world, key)
            off = env_lib.make_env(dataclasses.replace(config, start_error=True)).reset(world, key)
            np.testing.assert_array_equal(exact.plant.x, off.plant.x)  # the world starts where it did
            if estimator == "eskf":
                np.testing.assert_array_equal(exact.filter.latest.x, x0)
                start = np.asarray(off.filter.latest.x)
                assert np.linalg.norm(start[:3] - np.asarray(x0[:3])) > 1e-3
                assert np.linalg.norm(_attitude_error(start[3:7], x0[3:7])) > 1e-3
                np.testing.assert_array_equal(start[7:], x0[7:])  # at rest, and the filter knows it
                stds = np.sqrt(np.diag(np.asarray(off.filter.latest.cov)))
                assert stds[6:9].min() >= max(start_lib.START_ERROR_STD.attitude_rad)  # the spread covers the error
            else:
                assert not np.allclose(np.asarray(off.filter.particles).mean(0)[:3],
                                       np.asarray(exact.filter.particles).mean(0)[:3], atol=1e-3)


def test_the_start_error_has_its_stated_spread():
    x0 = jnp.asarray([1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    starts = np.asarray(jax.vmap(lambda key: start_lib.draw_start(x0, key))(jax.random.split(jax.random.PRNGKey(0),
                                                                                             4000)))
    std = start_lib.START_ERROR_STD
    np.testing.assert_allclose(starts[:, :3].std(0), std.position_m, rtol=0.06)
    errors = np.stack([_attitude_error(q, x0[3:7]) for q in starts[:400, 3:7]])
    np.testing.assert_allclose(errors.std(0), std.attitude_rad, rtol=0.15)
    assert start_lib.covering((0.3, 0.03, 0.2)) == (0.3, math.radians(5.0), 0.2)


def test_the_kalman_filter_aligns_from_the_start_error_on_the_pad(world):
    """On the pad with the spec's IMU, the alignment takes the start error's tilt out down to what the accelerometer's
    bias across gravity hides (a tilt of |b_xy| / g, which nothing at rest tells from one), and finds the lap's gyro
    bias to the pad's noise (the simulator's own IMU noise dominates it); the yaw error stays (nothing at rest shows
    it)."""
    config = dataclasses.replace(KALMAN, imu="icm42688p", start_error=True)
    aligned_env = env_lib.make_env(dataclasses.replace(config, eskf=eskf_lib.ESKFConfig(align_s=2.0)))
    unaligned_env = env_lib.make_env(config)
    q0 = world.track.start[3:7]
    pad_noise = math.sqrt(eskf_lib.PLANT_GYRO_VARIANCE / (2.0 * 960.0))  # rad/s, the 2 s mean of the plant's gyro
    for key in jax.random.split(jax.random.PRNGKey(4), 4):
        aligned, unaligned = aligned_env.reset(world, key), unaligned_env.reset(world, key)
        before = _attitude_error(unaligned.filter.latest.x[3:7], q0)
        after = _attitude_error(aligned.filter.latest.x[3:7], q0)
        hidden = np.linalg.norm(np.asarray(aligned.imu_errors.accel_bias[:2])) / 9.81
        # the priors' ratio leaves a twentieth of the start's tilt with the bias: the tilt left is the hidden one,
        # give or take a tenth of the start's
        tilt = np.linalg.norm(after[:2])
        assert abs(tilt - hidden) < 0.1 * np.linalg.norm(before[:2]) + 2e-3, (before, after, hidden)
        assert abs(after[2] - before[2]) < 0.05 * abs(before[2]) + 1e-3
        np.testing.assert_allclose(aligned.filter.latest.bias[3:], aligned.imu_errors.gyro_bias, atol=4 * pad_noise)


def test_each_realism_is_an_option_off_by_default_and_reaches_the_command_line():
    assert env_lib.EnvConfig().imu is None and env_lib.EnvConfig().start_error is False
    for name in ("imu", "start_error"):  # the race hands the environment the same setting
        race = {f.name: f for f in dataclasses.fields(RaceSpec)}[name]
        env = {f.name: f for f in dataclasses.fields(env_lib.EnvConfig)}[name]
        assert race.metadata == env.metadata and race.default == env.default
    with pytest.raises(ValueError, match="they need estimator='pf' or 'eskf'"):
        env_lib.EnvConfig(imu="icm42688p")
    with pytest.raises(ValueError, match="must be one of icm42688p"):
        env_lib.EnvConfig(estimator="eskf", imu="bmi270")
    assert RaceSpec(imu="icm42688p", start_error=True).imu is None  # on the true state they fly nothing
    spec, _ = race_spec(cli.build_parser().parse_args(["race", "--estimator", "eskf", "--imu", "icm42688p",
                                                       "--start-error"]))
    episode = spec.episode_config()
    assert (spec.imu, spec.start_error, episode.imu, episode.start_error) == ("icm42688p", True, "icm42688p", True)
    with pytest.raises(ValueError, match="--start-error acts on a filter"):
        race_spec(cli.build_parser().parse_args(["race", "--estimator", "truth", "--start-error"]))
