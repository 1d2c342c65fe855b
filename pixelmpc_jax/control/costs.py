"""Cost functions for one state, written for MPPI's ``running_cost(x, u, t, params)`` signature.

Every cost here is a pure function of one sample; the targets it reads (waypoints, gate geometry,
speeds) come in ``params``, so changing them never recompiles.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pixelmpc_jax.dynamics import quadrotor


@dataclasses.dataclass(frozen=True)
class WaypointWeights:
    """Weights of the hover-at-a-waypoint cost (static configuration)."""

    position: float = 10.0
    velocity: float = 1.0
    tilt: float = 50.0
    yaw: float = 5.0
    rates: float = 0.01


def waypoint_cost(x: jax.Array, u: jax.Array, waypoint: jax.Array, weights: WaypointWeights) -> jax.Array:
    """Stage cost of holding ``waypoint`` = [px, py, pz, yaw] (4,), level and at rest.

    c = w_p |p - p_d|^2 + w_v |v|^2 + w_tilt (qx^2 + qy^2) + w_yaw (1 - cos(yaw - yaw_d)) + w_r |w|^2,
    where ``qx^2 + qy^2 = (1 - R_33) / 2`` measures the tilt of the body z axis from world up.
    """
    p, q, v = x[quadrotor.POS], x[quadrotor.QUAT], x[quadrotor.VEL]
    position_error = p - waypoint[:3]
    yaw = quadrotor.euler_angles(q)[2]
    return (
        weights.position * jnp.sum(position_error**2)
        + weights.velocity * jnp.sum(v**2)
        + weights.tilt * (q[1] ** 2 + q[2] ** 2)
        + weights.yaw * (1.0 - jnp.cos(yaw - waypoint[3]))
        + weights.rates * jnp.sum(u[:3] ** 2)
    )
