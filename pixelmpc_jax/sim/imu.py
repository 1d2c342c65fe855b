"""The drone's IMU as a datasheet states it: its white noise and its biases, drawn per lap (issue 74, item 3).

The simulated vehicle's IMU (``pixelmpc_jax/data/alphapilot_course.json``, ``vehicle.imu_noise_variance``;
:mod:`pixelmpc_jax.sim.plant`) has no bias, and the filters are told its noise exactly. With an :class:`ImuSpec`
on (``EnvConfig.imu``), the IMU the filter reads is a racing flight controller's: each lap draws the sensor's
biases within the datasheet's initial tolerance (:func:`draw_errors`), and every sample gains white noise of the
datasheet's density at the plant's rate (:func:`read`). The filter is configured from the same datasheet
(:func:`filter_config`: its noise densities and its bias prior), not from the simulator.

What is modelled, and what not:

- **Bias.** Each axis's bias is drawn uniformly within the datasheet's ``+-`` initial tolerance (the zero-rate
  offset of the gyro, the zero-g offset of the accelerometer), once per lap and constant through it: a lap lasts
  under a minute, and the datasheets state the change with temperature (``ZRO variation over temperature``), not a
  drift in time, which a lap's few degrees of warming would keep far below the tolerance. A flight controller
  calibrating its gyro on the pad is what the Kalman filter's alignment does (``ESKFConfig.align_s``); the bias
  drawn is the one before it.
- **Noise.** White noise of the datasheet's density, ``density / sqrt(PLANT_DT)`` per sample at 960 Hz, so the
  tick's mean of 24 samples carries ``density / sqrt(CONTROL_DT)``. It comes on top of the simulator's own IMU noise
  (FlightGoggles' vehicle: 0.071 m/s^2 and 0.055 rad/s per sample, densities 3.3 and 36 times the ICM-42688-P's),
  which stays: it stands for what a datasheet does not state (the frame's vibration in flight). The filter is told
  the datasheet's density only, as a filter configured from the datasheet is.
- **The filter's prior.** Its bias prior std per axis is the tolerance itself (a ``+-`` bound read as one sigma; the
  drawn law's own std is the tolerance over sqrt(3)), its noise densities the datasheet's. Its bias random walks stay
  the configuration's (the datasheets below state no bias instability).

Random draws come from keys folded out of the episode's keys with stream numbers of their own (far from the faults'
and the pad's), so a lap without the spec draws what it drew before.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.perception import eskf as eskf_lib
from pixelmpc_jax.sim import faults as faults_lib
from pixelmpc_jax.sim import plant as plant_lib

GRAVITY = 9.80665  # m/s^2 per g (the datasheets' unit)
DEG = math.pi / 180.0
_BIAS_STREAM, _NOISE_STREAM = 2905, 2906  # fold_in stream numbers (the faults use 2801-2804, the pad 2901)


@dataclasses.dataclass(frozen=True)
class ImuSpec:
    """An IMU as its datasheet states it (SI units; a ``+-`` tolerance per axis).

    Attributes:
        name: the part.
        source: the datasheet (document number and revision) the figures come from, and which were verified.
        gyro_noise_density: rad/s/sqrt(Hz), the gyro's rate noise spectral density.
        accel_noise_density: m/s^2/sqrt(Hz), the accelerometer's noise spectral density.
        gyro_bias_tolerance: rad/s, the gyro's initial zero-rate offset, ``+-`` per axis.
        accel_bias_tolerance: m/s^2, the accelerometer's initial zero-g offset, ``+-`` per axis.
    """

    name: str
    source: str
    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_tolerance: float
    accel_bias_tolerance: float

    def __post_init__(self):
        for name in ("gyro_noise_density", "accel_noise_density", "gyro_bias_tolerance", "accel_bias_tolerance"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value >= 0):
                raise ValueError(f"ImuSpec.{name} must be a finite number >= 0, got {value!r}")


# TDK InvenSense ICM-42688-P, an IMU common on racing flight controllers (Betaflight and PX4 both drive it).
# Datasheet DS-000347, revision 1.7. Verified against the datasheet's first page (its
# "Features" list): gyroscope noise 2.8 mdps/sqrt(Hz), accelerometer noise 70 ug/sqrt(Hz). The gyroscope's initial
# ZRO tolerance, +-0.5 dps (board level, all axes; with +-0.005 dps/degC over temperature), is the datasheet's
# Table 1 as quoted by two independent sources; the table itself could not be read here. The accelerometer's initial
# zero-g tolerance, +-20 mg (board level, all axes), is Table 2's as remembered, NOT verified here (a comparison table
# gives its temperature coefficient, +-0.15 mg/degC, but not the offset). The datasheet states no bias instability.
ICM_42688_P = ImuSpec(
    name="ICM-42688-P",
    source="TDK InvenSense ICM-42688-P datasheet, DS-000347 rev. 1.7: noise densities verified (first page); gyro "
           "initial ZRO tolerance +-0.5 dps from Table 1 as quoted; accel initial zero-g tolerance +-20 mg from "
           "Table 2, not verified",
    gyro_noise_density=2.8e-3 * DEG,
    accel_noise_density=70e-6 * GRAVITY,
    gyro_bias_tolerance=0.5 * DEG,
    accel_bias_tolerance=20e-3 * GRAVITY,
)
IMU_SPECS = {"icm42688p": ICM_42688_P}


class ImuErrors(NamedTuple):
    """One lap's IMU biases, body frame: accel_bias (3,) m/s^2, gyro_bias (3,) rad/s (added to the readings)."""

    accel_bias: jax.Array
    gyro_bias: jax.Array


def draw_errors(spec: ImuSpec, key: jax.Array) -> ImuErrors:
    """One lap's biases: each axis uniform within the spec's ``+-`` tolerance; ``key``: the episode's reset key (a
    stream is folded out of it)."""
    key_accel, key_gyro = jax.random.split(jax.random.fold_in(key, _BIAS_STREAM))
    return ImuErrors(
        accel_bias=spec.accel_bias_tolerance * jax.random.uniform(key_accel, (3,), jnp.float32, -1.0, 1.0),
        gyro_bias=spec.gyro_bias_tolerance * jax.random.uniform(key_gyro, (3,), jnp.float32, -1.0, 1.0))


def sample_std(spec: ImuSpec) -> tuple[float, float]:
    """(accelerometer m/s^2, gyro rad/s) std of the spec's white noise per sample at the plant's rate:
    ``density / sqrt(PLANT_DT)``."""
    rate = 1.0 / math.sqrt(timing.PLANT_DT)
    return spec.accel_noise_density * rate, spec.gyro_noise_density * rate


def read(imu: plant_lib.TickIMU, errors: ImuErrors, spec: ImuSpec, key: jax.Array) -> plant_lib.TickIMU:
    """The tick's IMU (or the pad's, any number of samples) as the spec's sensor reads it: the lap's biases plus the
    spec's white noise, whose mean over the tick's S samples has std ``sample_std / sqrt(S)``
    (:func:`~pixelmpc_jax.sim.faults.imu_with_error` puts them into the preintegrated tick); ``key``: the tick's key (a
    stream is folded out of it)."""
    key_accel, key_gyro = jax.random.split(jax.random.fold_in(key, _NOISE_STREAM))
    accel_std, gyro_std = sample_std(spec)
    per_sample = jax.lax.rsqrt(jnp.maximum(imu.num_samples, 1.0))
    accel = errors.accel_bias.astype(imu.accel.dtype) + accel_std * per_sample * \
        jax.random.normal(key_accel, (3,), imu.accel.dtype)
    gyro = errors.gyro_bias.astype(imu.gyro.dtype) + gyro_std * per_sample * \
        jax.random.normal(key_gyro, (3,), imu.gyro.dtype)
    return faults_lib.imu_with_error(imu, accel, gyro)


def filter_config(spec: ImuSpec, config: eskf_lib.ESKFConfig) -> eskf_lib.ESKFConfig:
    """The Kalman filter ``config`` told the spec's IMU: its noise densities the datasheet's, its bias prior std per
    axis the datasheet's tolerance; the rest (the bias walks among it) as configured."""
    return dataclasses.replace(config, accel_noise_density=spec.accel_noise_density,
                               gyro_noise_density=spec.gyro_noise_density, accel_bias_std=spec.accel_bias_tolerance,
                               gyro_bias_std=spec.gyro_bias_tolerance)
