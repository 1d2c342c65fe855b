"""Cost functions for one state, written for MPPI's ``running_cost(x, u, t, params)`` signature.

Every cost here is a pure function of one sample; the targets it reads (waypoints, gate geometry,
speeds) come in ``params``, so changing them never recompiles.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import track as track_lib


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


# --------------------------------------------------------------------------------------------------
# The racing cost, Eq. (19).
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RacingCostConfig:
    """Static settings of the racing cost; the paper's constants are the defaults.

    Attributes:
        c1, c2, c3: weights of the path, attitude and velocity terms of Eq. (19).
        corridor_halfwidth: distance to the path (m) that maps to ``h = 1``; ``h = min(d / this, 1)``.
            The paper normalises h into [-1, 1] without saying by what; 2 m keeps a 1 m offset at a
            quarter of the saturated cost and lets the crash term guard the gate frames.
        crash_value: the value of h on a crash (the paper: 1000), so a crash costs ``c1 * 1000^2``.
        crash_slab_halfwidth: half thickness (m) of the volume around a gate frame that counts as a crash
            for a predicted state. A single state (not a segment) is tested, so the slab is made thicker
            than the distance flown per step at racing speed (0.4 m at 16 m/s), so no prediction jumps it.
        vehicle_radius: m, the drone as a sphere (frame, floor and walls).
        window_before_m, window_after_m: the stretch of desired path searched by the cost, around the
            robot's progress at the start of the tick; it must cover one horizon of flight
            (T dt v = 2 s x 20 m/s = 40 m).
        path_stride: take every ``path_stride``-th sample of the track's path (0.25 m) for the cost; the
            distance is to the polyline, so 1 m chords of the smooth path cost a few centimetres at most.
    """

    c1: float = 400.0
    c2: float = 250.0
    c3: float = 8.0
    corridor_halfwidth: float = 2.0
    crash_value: float = 1000.0
    crash_slab_halfwidth: float = 0.25
    vehicle_radius: float = 0.1
    window_before_m: float = 5.0
    window_after_m: float = 45.0
    path_stride: int = 4

    def window_length(self, path_spacing: float = 0.25) -> int:
        """Number of path samples in the cost's window (static)."""
        span = self.window_before_m + self.window_after_m
        return int(span / (path_spacing * self.path_stride)) + 2


@struct.dataclass
class RacingParams:
    """Dynamic inputs of the racing cost for one control tick (a pytree: changing them never recompiles).

    Attributes:
        path_points: (L, 3) the window of the desired path.
        path_tangents: (L, 3) unit tangents at those points.
        gates: the course's gates (leading axis G), for the crash term.
        hall_min, hall_max: (3,) the hall's box.
        target_speed: () desired speed along the path, m/s.
    """

    path_points: jax.Array
    path_tangents: jax.Array
    gates: track_lib.Gate
    hall_min: jax.Array
    hall_max: jax.Array
    target_speed: jax.Array


def racing_params(track: track_lib.Track, progress_s: jax.Array, target_speed, config: RacingCostConfig
                  ) -> RacingParams:
    """Cut the cost's window of the desired path around the arc length ``progress_s`` (jit-able)."""
    stride = config.path_stride
    points = track.path_points[::stride]
    tangents = track.path_tangents[::stride]
    spacing = track.path_spacing * stride
    length = min(config.window_length(float(track_lib.PATH_SPACING)), points.shape[0])
    first = jnp.floor((progress_s - config.window_before_m) / spacing).astype(jnp.int32)
    start = jnp.clip(first, 0, points.shape[0] - length)
    return RacingParams(
        path_points=jax.lax.dynamic_slice_in_dim(points, start, length),
        path_tangents=jax.lax.dynamic_slice_in_dim(tangents, start, length),
        gates=track.gates,
        hall_min=track.hall_min,
        hall_max=track.hall_max,
        target_speed=jnp.asarray(target_speed, jnp.float32),
    )


def _closest_on_polyline(points: jax.Array, tangents: jax.Array, p: jax.Array):
    """Distance from p (3,) to the polyline points (L, 3) and the interpolated unit tangent there."""
    a, b = points[:-1], points[1:]
    ab = b - a
    len2 = jnp.sum(ab * ab, axis=-1)
    t = jnp.clip(jnp.sum((p - a) * ab, axis=-1) / jnp.maximum(len2, 1e-12), 0.0, 1.0)
    dist2 = jnp.sum((a + t[:, None] * ab - p) ** 2, axis=-1)
    i = jnp.argmin(dist2)
    tangent = tangents[i] + t[i] * (tangents[i + 1] - tangents[i])
    tangent = tangent / jnp.maximum(jnp.linalg.norm(tangent), 1e-6)
    return jnp.sqrt(dist2[i]), tangent


def crashed(p: jax.Array, params: RacingParams, config: RacingCostConfig) -> jax.Array:
    """() bool: a predicted position inside a gate frame's volume, below the floor or outside the hall."""
    gates = params.gates
    r = config.vehicle_radius
    local = gates.to_local(p)  # (G, 3)
    slab = jnp.abs(local[:, 0]) <= jnp.maximum(0.5 * gates.depth + r, config.crash_slab_halfwidth)
    outer = (jnp.abs(local[:, 1]) <= 0.5 * gates.width + gates.border + r) & (
        jnp.abs(local[:, 2]) <= 0.5 * gates.height + gates.border + r)
    opening = (jnp.abs(local[:, 1]) < 0.5 * gates.width - r) & (jnp.abs(local[:, 2]) < 0.5 * gates.height - r)
    frame = jnp.any(slab & outer & ~opening)
    ground = p[2] < params.hall_min[2] + r
    wall = jnp.any(p < params.hall_min + r) | jnp.any(p > params.hall_max - r)
    return frame | ground | wall


def desired_attitude(tangent: jax.Array) -> jax.Array:
    """q_d: level, heading along the path tangent (3,). -> (4,)."""
    return quadrotor.quat_from_yaw(jnp.arctan2(tangent[1], tangent[0]))


def racing_cost(x: jax.Array, params: RacingParams, config: RacingCostConfig) -> jax.Array:
    """Eq. (19) for one state: c1 h^2 + c2 |q_d - q|^2 + c3 |v_d - v|^2.

    h = min(d / corridor_halfwidth, 1) with d the distance to the desired path, or ``crash_value`` on a
    crash; q_d is level and faces along the path tangent (the sign of q is chosen to make the distance
    smallest, since q and -q are one attitude); v_d = target_speed * tangent.
    """
    p, q, v = x[quadrotor.POS], x[quadrotor.QUAT], x[quadrotor.VEL]
    distance, tangent = _closest_on_polyline(params.path_points, params.path_tangents, p)
    h = jnp.minimum(distance / config.corridor_halfwidth, 1.0)
    h = jnp.where(crashed(p, params, config), config.crash_value, h)
    q_d = desired_attitude(tangent)
    attitude_error = jnp.minimum(jnp.sum((q_d - q) ** 2), jnp.sum((q_d + q) ** 2))
    velocity_error = jnp.sum((params.target_speed * tangent - v) ** 2)
    return config.c1 * h**2 + config.c2 * attitude_error + config.c3 * velocity_error
