"""Where the filter believes the drone starts: the start pad's pose, off the true one by a hand's placing (issue 74,
item 3).

Without it (``EnvConfig.start_error`` off) both filters start about the exact true state. With it, each lap the
filter's first state is the true start plus an error drawn from :data:`START_ERROR_STD` (:func:`draw_start`): a
drone set down by hand on a start pad, the filter told the pad's pose. The figures, one standard deviation per axis:

- **Position** 0.1 m along and across the course (a drone placed on the mark of a pad half a metre wide, by eye),
  0.02 m in height (it sits on its landing gear on the pad; the pad's height is known).
- **Roll and pitch** 2 deg (the pad and the floor are not level, the landing gear not even); gravity shows these, so
  the Kalman filter's alignment on the pad (``ESKFConfig.align_s``) takes them out.
- **Yaw** 5 deg (the drone pointed down the course by eye); nothing at rest shows it, the gates must.
- **Velocity** 0: the drone rests on the pad and the filter knows it (it starts at rest, as the true vehicle does).

The error is drawn in the filter's own terms: position and velocity added, the attitude turned by a body-frame
rotation vector (``q_filter = q_true exp(dtheta)``). The filter's initial spread covers it (:func:`covering`): each
of its stds at least the error's. The true start stays the course's: the world flies the lap it flew before, and
only the filter begins elsewhere.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.dynamics import quadrotor

_START_STREAM = 2907  # fold_in stream number of the draw (the faults use 2801-2804, the pad 2901, the IMU 2905-2906)


class StartError(NamedTuple):
    """Standard deviations of the filter's initial error, per axis.

    Attributes:
        position_m: (x, y, z) m, world frame.
        attitude_rad: (roll, pitch, yaw) rad, a body-frame rotation vector.
        velocity_mps: m/s per axis.
    """

    position_m: tuple
    attitude_rad: tuple
    velocity_mps: float


START_ERROR_STD = StartError(position_m=(0.1, 0.1, 0.02), attitude_rad=(math.radians(2.0), math.radians(2.0),
                                                                         math.radians(5.0)), velocity_mps=0.0)


def draw_start(x0: jax.Array, key: jax.Array, std: StartError = START_ERROR_STD) -> jax.Array:
    """(10,) the filter's first state: the true start ``x0`` (10,) plus an error drawn with ``std`` (Gaussian per
    axis); ``key``: the episode's reset key (a stream is folded out of it)."""
    key_position, key_attitude, key_velocity = jax.random.split(jax.random.fold_in(key, _START_STREAM), 3)
    dtype = x0.dtype
    position = x0[quadrotor.POS] + jnp.asarray(std.position_m, dtype) * jax.random.normal(key_position, (3,), dtype)
    rotation = jnp.asarray(std.attitude_rad, dtype) * jax.random.normal(key_attitude, (3,), dtype)
    attitude = quadrotor.normalize_quat(quadrotor.quat_multiply(x0[quadrotor.QUAT], quadrotor.quat_exp(rotation, 1.0)))
    velocity = x0[quadrotor.VEL] + std.velocity_mps * jax.random.normal(key_velocity, (3,), dtype)
    return jnp.concatenate([position, attitude, velocity])


def covering(spread: tuple, std: StartError = START_ERROR_STD) -> tuple[float, float, float]:
    """A filter's initial ``spread`` (position m, attitude rad, velocity m/s; one std each, every axis) widened where
    needed to cover ``std``: each at least the largest of the error's stds of that kind."""
    position, attitude, velocity = (float(s) for s in spread)
    return (max(position, *std.position_m), max(attitude, *std.attitude_rad), max(velocity, std.velocity_mps))
