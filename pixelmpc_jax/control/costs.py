"""Costs for MPPI: the racing cost, Eq. (19), over every predicted state at once, its per-step parameters; waypoints.

The waypoint cost is a pure function of one state; the racing cost (``racing_costs``) of every sample at every
horizon step at once, as the controllers call it after the rollout. The targets a cost reads (waypoints, gate
geometry, speeds) come in ``params``, so changing them never recompiles. What depends only on the track
(``racing_constants``) can be built once per track.
"""

from __future__ import annotations

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.settings import Range, check, setting
from pixelmpc_jax.world import track as track_lib

SPEED_CAP_NONE = 1e30  # m/s, the speed cap of the cost without one (max_lateral_acc None): above any target speed


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
    chex.assert_shape([x, waypoint], [(quadrotor.STATE_DIM,), (4,)])
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
        window_behind_m, window_ahead_m: the stretch of path searched for a predicted state at horizon
            step t, around the progress the previous plan predicted for that step. Samples are
            perturbations of that plan, so a short window per step replaces a search of the whole
            horizon's path for every state (the hot spot of the step: 13 segments instead of ~50).
        path_stride: take every ``path_stride``-th sample of the track's path (0.25 m) for the cost; the
            distance is to the polyline, so 1 m chords of the smooth path cost a few centimetres at most.
        max_lateral_acc: m/s^2. The desired speed is ``min(target_speed, sqrt(max_lateral_acc * R(s)))``
            with R the path's radius of curvature: a constant target speed is not flyable on the AlphaPilot
            path (turn radii down to 2.8 m; at 16 m/s that needs 90 m/s^2 sideways, while thrust leaves
            about 24 m/s^2 after gravity and drag). The paper gives v_d only as "the target speed"; this
            caps it where the vehicle cannot follow it and leaves it untouched elsewhere. None disables it.
        curvature_lookaround_m: the cap at s uses the tightest radius within this distance of s, so a
            turn is entered slow, not only its apex.
        progress_weight: 1/m^2. The closest point of a window is the one minimising
            ``d^2 + progress_weight * (s - s_expected)^2``, s_expected the progress the previous plan
            predicts for that step. Where the path doubles back (a U-turn through consecutive gates), a
            window holds both legs; pure nearest-point projection then flips between legs whose tangents
            point opposite ways, and hovering between them minimises the velocity term (a trap seen in
            closed loop). The returned distance is still the true distance to the chosen segment.
        max_tilt_deg: a predicted attitude whose body z axis is tilted further than this from world up
            counts as a crash (h = crash_value). Beyond acos(m g / f_max) = 74.6 deg no thrust holds the
            altitude, and the laps that failed in our closed loop all flipped past 90 deg first; the paper's
            cost has no such term. None disables it.
        heading_weight: the share of the attitude term (c2) that pins the heading to the path tangent. 1 (the
            paper's): q_d faces along the path. Below 1 the term is ``w |q_d - q|^2 + (1 - w) |q_lvl - q|^2``
            with q_lvl level at the vehicle's own heading, so the tilt is held as before while the heading is
            left (partly) to other terms, e.g. PixelMPC's pixel cost: a quadrotor can yaw without changing
            its translational dynamics.
    """

    c1: float = 400.0
    c2: float = 250.0
    c3: float = 8.0
    corridor_halfwidth: float = 2.0
    crash_value: float = 1000.0
    crash_slab_halfwidth: float = 0.25
    vehicle_radius: float = setting(0.1, range=Range(0.05, 1.0, unit="m"), help="m: the racing cost's clearance to "
                                    "gate frames, floor and walls (the world keeps the vehicle's 0.1 m)")
    window_behind_m: float = 4.0
    window_ahead_m: float = 8.0
    path_stride: int = 4
    max_lateral_acc: float | None = 20.0
    curvature_lookaround_m: float = 3.0
    max_tilt_deg: float | None = 75.0
    progress_weight: float = 0.25
    heading_weight: float = setting(1.0, range=Range(0.0, 1.0), help="share of the racing cost's attitude term that "
                                    "pins the heading to the path, in {range} (1: the paper's)")

    def __post_init__(self):
        check(self)

    def window_length(self, path_spacing: float = 0.25) -> int:
        """Number of path samples in each step's window (static)."""
        return int(round((self.window_behind_m + self.window_ahead_m) / (path_spacing * self.path_stride))) + 1


@struct.dataclass
class RacingParams:
    """Dynamic inputs of the racing cost for one control tick (a pytree: changing them never recompiles).

    Attributes:
        path_xyz: (T, 3, L) per horizon step, the window of the desired path (coordinates first, so the
            distance computation runs on contiguous (L,) rows).
        path_s: (T, L) arc length of the window's points, m.
        expected_s: (T,) the progress the previous plan predicts for each step, m.
        tangent_xyz: (T, 4, L) unit path tangents at those points and, in row 3, the speed cap (m/s).
        gates: the course's gates (leading axis G), for the crash term.
        hall_min, hall_max: (3,) the hall's box.
        target_speed: () desired speed along the path, m/s.
    """

    path_xyz: jax.Array
    path_s: jax.Array
    expected_s: jax.Array
    tangent_xyz: jax.Array
    gates: track_lib.Gate
    hall_min: jax.Array
    hall_max: jax.Array
    target_speed: jax.Array


@struct.dataclass
class RacingConstants:
    """The racing cost's inputs that depend only on the track and the config: built once per track and
    config by :func:`racing_constants` and handed to :func:`racing_params` at every tick (which otherwise
    rebuilds them, the speed cap's curvature search included, every time).

    Attributes:
        points: (P', 3) every ``path_stride``-th sample of the track's path.
        arc: (P',) their arc length, m.
        attributes: (P', 4) the unit path tangents there and, in column 3, the speed cap (m/s; ``SPEED_CAP_NONE``
            where there is none).
        spacing: () distance between consecutive points, m.
    """

    points: jax.Array
    arc: jax.Array
    attributes: jax.Array
    spacing: jax.Array


def racing_constants(track: track_lib.Track, config: RacingCostConfig) -> RacingConstants:
    """The per-track constants of the racing cost (jit-able; compute once per track and config)."""
    stride = config.path_stride
    cap = speed_cap(track, config)[::stride]
    if config.max_lateral_acc is None:  # no cap: a finite stand-in, since the cost interpolates it (inf - inf = NaN)
        cap = jnp.full_like(cap, SPEED_CAP_NONE)
    return RacingConstants(
        points=track.path_points[::stride],
        arc=track.path_s[::stride],
        attributes=jnp.concatenate([track.path_tangents[::stride], cap[:, None]], axis=1),  # (P', 4)
        spacing=track.path_spacing * stride,
    )


def racing_params(track: track_lib.Track, step_progress: jax.Array, target_speed, config: RacingCostConfig,
                  constants: RacingConstants | None = None) -> RacingParams:
    """Cut each horizon step's window of the desired path (jit-able).

    Args:
        track: the course.
        step_progress: (T,) arc length (m) around which step t's window is cut: the progress the previous
            plan predicts for that step (a scalar is broadcast to every step, e.g. at the first tick).
        target_speed: () m/s.
        config: the cost's static settings.
        constants: :func:`racing_constants` of this track and config, computed once; None computes them here.
    """
    expected_points = -(-track.num_path_points // config.path_stride)
    if constants is None:
        constants = racing_constants(track, config)
    elif constants.points.shape != (expected_points, 3):
        raise ValueError(f"constants hold {constants.points.shape[0]} path points, but this track with path_stride "
                         f"{config.path_stride} has {expected_points}: build them with racing_constants(track, config)")
    points, arc, attributes = constants.points, constants.arc, constants.attributes
    length = min(config.window_length(float(track_lib.PATH_SPACING)), points.shape[0])
    step_progress = jnp.atleast_1d(jnp.asarray(step_progress, jnp.float32))
    first = jnp.floor((step_progress - config.window_behind_m) / constants.spacing).astype(jnp.int32)
    starts = jnp.clip(first, 0, points.shape[0] - length)  # (T,)

    def window(start):
        return (jax.lax.dynamic_slice_in_dim(points, start, length).T,
                jax.lax.dynamic_slice_in_dim(arc, start, length),
                jax.lax.dynamic_slice_in_dim(attributes, start, length).T)

    path_xyz, path_s, tangent_xyz = jax.vmap(window)(starts)
    return RacingParams(
        path_xyz=path_xyz,
        path_s=path_s,
        expected_s=jnp.broadcast_to(step_progress, starts.shape),
        tangent_xyz=tangent_xyz,
        gates=track.gates,
        hall_min=track.hall_min,
        hall_max=track.hall_max,
        target_speed=jnp.asarray(target_speed, jnp.float32),
    )


def check_racing_params(params: RacingParams, horizon: int) -> None:
    """A ValueError unless ``params`` holds one path window per horizon step: ``expected_s`` (T,), ``path_s`` (T, L),
    ``path_xyz`` (T, 3, L), ``tangent_xyz`` (T, 4, L) and a scalar ``target_speed``. Shapes only: it runs when a step
    is traced (a window missing for a step would make every sample's cost NaN)."""
    if not isinstance(params, RacingParams):
        raise TypeError(f"the racing params must be a RacingParams (costs.racing_params), got {type(params).__name__}")
    T = horizon
    expected = jnp.shape(params.expected_s)
    if expected != (T,):
        raise ValueError(f"RacingParams.expected_s must have shape (T,) = ({T},), one progress per horizon step "
                         f"(costs.racing_params(track, step_progress of shape ({T},), ...)), got shape {expected}")
    L = jnp.shape(params.path_s)[-1] if jnp.ndim(params.path_s) == 2 else None
    for name, shape in (("path_s", (T, L)), ("path_xyz", (T, 3, L)), ("tangent_xyz", (T, 4, L))):
        if L is None or jnp.shape(getattr(params, name)) != shape:
            raise ValueError(f"RacingParams.{name} must have shape {shape} (horizon {T}, window L), got shape "
                             f"{jnp.shape(getattr(params, name))}")
    if jnp.shape(params.target_speed) != ():
        raise ValueError(f"RacingParams.target_speed must be a scalar, got shape {jnp.shape(params.target_speed)}")


def speed_cap(track: track_lib.Track, config: RacingCostConfig) -> jax.Array:
    """(P,) the highest desired speed (m/s) at each path sample: sqrt(max_lateral_acc * R), R the tightest
    radius of curvature within ``curvature_lookaround_m``; +inf everywhere when the cap is disabled."""
    num_points = track.num_path_points
    if config.max_lateral_acc is None:
        return jnp.full((num_points,), jnp.inf, jnp.float32)
    tangents = track.path_tangents
    spacing = track.path_spacing
    padded = jnp.concatenate([tangents[:1], tangents, tangents[-1:]], axis=0)
    curvature = jnp.linalg.norm(padded[2:] - padded[:-2], axis=1) / (2.0 * spacing)  # (P,)
    half = max(int(round(config.curvature_lookaround_m / float(track_lib.PATH_SPACING))), 0)
    if half > 0:
        shifted = [jnp.roll(curvature, k) for k in range(-half, half + 1)]
        curvature = jnp.max(jnp.stack(shifted), axis=0)  # the path is open: wrap-around only touches its ends
    return jnp.sqrt(config.max_lateral_acc / jnp.maximum(curvature, 1e-6))


def _path_term(distance: jax.Array, crash: jax.Array, q, config: RacingCostConfig) -> jax.Array:
    """h of Eq. (19): min(distance / corridor_halfwidth, 1), or ``crash_value`` on a crash (``crash``, or a tilt
    of the attitude q = [qw, qx, qy, qz] beyond ``max_tilt_deg``)."""
    h = jnp.minimum(distance / config.corridor_halfwidth, 1.0)
    if config.max_tilt_deg is not None:
        cos_tilt = 1.0 - 2.0 * (q[1] ** 2 + q[2] ** 2)  # R_33: body z against world z
        crash = crash | (cos_tilt < math.cos(math.radians(config.max_tilt_deg)))
    return jnp.where(crash, config.crash_value, h)


def racing_costs(X: jax.Array, steps: jax.Array, params: RacingParams, config: RacingCostConfig) -> jax.Array:
    """Eq. (19), c1 h^2 + c2 |q_d - q|^2 + c3 |v_d - v|^2, for a whole batch of predicted states at once: ``X``
    (T, N, >= 10) at horizon steps ``steps`` (T,) -> (T, N); ``X[t]`` is compared with step ``steps[t]``'s window.

    h = min(d / corridor_halfwidth, 1) with d the distance to the desired path, or ``crash_value`` on a
    crash (a gate frame, the floor, the walls, or a tilt beyond ``max_tilt_deg``); q_d is level and faces
    along the path tangent (the sign of q is chosen to make the distance smallest, since q and -q are one
    attitude); v_d = min(target_speed, speed cap at the closest point) * tangent (see
    ``RacingCostConfig.max_lateral_acc``).

    Every operation is elementwise over the (T, N) batch: the short axes (coordinates, the window's
    segments, the gates, quaternion components) are unrolled here rather than reduced, so XLA fuses the
    cost into a few loop kernels over all T x N samples instead of running small reductions at every
    step.
    """
    chex.assert_rank(X, 3)
    chex.assert_type(X, float)
    chex.assert_shape(steps, X.shape[:1])
    if X.shape[-1] < quadrotor.STATE_DIM:
        raise ValueError(f"X must hold the {quadrotor.STATE_DIM}-state quadrotor first on its last axis, got "
                         f"shape {X.shape}")
    comp = [X[..., i] for i in range(quadrotor.STATE_DIM)]  # (T, N) each
    p, q, v = comp[0:3], comp[3:7], comp[7:10]
    distance, tangent, cap = _closest_on_windows(params, steps, p, config.progress_weight)
    h = _path_term(distance, _crashed(p, params, config), q, config)
    attitude_error = _attitude_distance(_desired_attitude(tangent[0], tangent[1]), q)
    if config.heading_weight < 1.0:
        heading_y = 2.0 * (q[0] * q[3] + q[1] * q[2])  # the vehicle's own heading (yaw)
        heading_x = 1.0 - 2.0 * (q[2] ** 2 + q[3] ** 2)
        level = _desired_attitude(heading_x, heading_y)
        attitude_error = (config.heading_weight * attitude_error
                          + (1.0 - config.heading_weight) * _attitude_distance(level, q))
    speed = jnp.minimum(params.target_speed, cap)
    velocity_error = _sum3([(speed * tangent[i] - v[i]) ** 2 for i in range(3)])
    return config.c1 * h**2 + config.c2 * attitude_error + config.c3 * velocity_error


def _sum3(terms):
    """a + b + c (left to right) of three equally shaped arrays."""
    return terms[0] + terms[1] + terms[2]


def _closest_on_windows(params: RacingParams, steps: jax.Array, p: list, progress_weight: float):
    """The closest point of each step's window of the path to points p = [x, y, z], (T, N) each, step t's
    against its own window.

    The segment chosen minimises ``d^2 + progress_weight * (s - expected_s)^2`` (d^2 alone where the weight is
    0), s the arc length of the closest point of the segment; exact ties average the tied segments. The window's
    attributes (unit tangent, speed cap) are interpolated linearly along the segment and the tangent renormalised.

    Returns distance (T, N) to the chosen segment, the unit tangent [tx, ty, tz] and the speed cap, (T, N) each.
    """
    path = jnp.take(params.path_xyz, steps, axis=0)  # (T, 3, L)
    attributes = jnp.take(params.tangent_xyz, steps, axis=0)  # (T, C, L)
    arc = jnp.take(params.path_s, steps, axis=0)  # (T, L)
    expected = jnp.take(params.expected_s, steps, axis=0)[:, None]  # (T, 1)
    # per-step, per-segment constants (T, S), broadcast over the samples as (T, 1) columns
    start = path[:, :, :-1]
    delta = path[:, :, 1:] - start
    len2 = jnp.maximum(_sum3([delta[:, i] ** 2 for i in range(3)]), 1e-12)
    arc_start, arc_delta = arc[:, :-1], arc[:, 1:] - arc[:, :-1]
    attr_start, attr_delta = attributes[:, :, :-1], attributes[:, :, 1:] - attributes[:, :, :-1]
    num_segments = len2.shape[1]
    fraction, d2, metric = [], [], []
    for k in range(num_segments):
        r = [p[i] - start[:, i, k, None] for i in range(3)]
        ab = [delta[:, i, k, None] for i in range(3)]
        t = jnp.clip(_sum3([r[i] * ab[i] for i in range(3)]) / len2[:, k, None], 0.0, 1.0)
        dist2 = _sum3([(r[i] - t * ab[i]) ** 2 for i in range(3)])
        fraction.append(t)
        d2.append(dist2)
        if progress_weight > 0.0:
            s = arc_start[:, k, None] + t * arc_delta[:, k, None]
            metric.append(dist2 + progress_weight * (s - expected) ** 2)
        else:
            metric.append(dist2)
    best = metric[0]
    for m in metric[1:]:
        best = jnp.minimum(best, m)
    select = [(m <= best).astype(p[0].dtype) for m in metric]
    count = select[0]
    for k in range(1, num_segments):
        count = count + select[k]

    def chosen(values):  # the mean over the selected segments (one, barring exact ties)
        total = values[0] * select[0]
        for k in range(1, num_segments):
            total = total + values[k] * select[k]
        return total / count

    distance = jnp.sqrt(chosen(d2))
    attrs = [chosen([attr_start[:, c, k, None] + fraction[k] * attr_delta[:, c, k, None]
                     for k in range(num_segments)]) for c in range(attributes.shape[1])]
    norm = jnp.maximum(jnp.sqrt(_sum3([attrs[i] ** 2 for i in range(3)])), 1e-6)
    return distance, [attrs[i] / norm for i in range(3)], attrs[3]


def _crashed(p: list, params: RacingParams, config: RacingCostConfig) -> jax.Array:
    """Points p = [x, y, z], each of any shape, inside a gate frame's volume (one gate at a time), below the floor
    or outside the hall (bool, p's shape)."""
    gates = params.gates
    r = config.vehicle_radius
    frame = jnp.zeros(p[0].shape, bool)
    for g in range(gates.centre.shape[0]):
        offset = [p[j] - gates.centre[g, j] for j in range(3)]
        # gate-frame coordinates [along normal, lateral, up]: local_i = sum_j rotation[g, j, i] offset_j
        local = [_sum3([gates.rotation[g, j, i] * offset[j] for j in range(3)]) for i in range(3)]
        slab = jnp.abs(local[0]) <= jnp.maximum(0.5 * gates.depth[g] + r, config.crash_slab_halfwidth)
        outer = ((jnp.abs(local[1]) <= 0.5 * gates.width[g] + gates.border[g] + r)
                 & (jnp.abs(local[2]) <= 0.5 * gates.height[g] + gates.border[g] + r))
        opening = (jnp.abs(local[1]) < 0.5 * gates.width[g] - r) & (jnp.abs(local[2]) < 0.5 * gates.height[g] - r)
        frame = frame | (slab & outer & ~opening)
    ground = p[2] < params.hall_min[2] + r
    wall = ground
    for i in range(3):
        wall = wall | (p[i] < params.hall_min[i] + r) | (p[i] > params.hall_max[i] - r)
    return frame | wall


def _desired_attitude(tx: jax.Array, ty: jax.Array) -> list:
    """q_d, level and heading along the tangent (tx, ty, .), as [qw, qx, qy, qz]: the yaw rotation by psi, the
    heading of (tx, ty), i.e. [cos(psi / 2), 0, 0, sin(psi / 2)], up to the sign of the quaternion (q and -q
    are one attitude, and :func:`_attitude_distance` takes the nearer of the two).

    Without trigonometry: (cos, sin)(psi / 2) is the unit bisector of the x axis and (tx, ty), the direction
    of (r + tx, ty) with r = |(tx, ty)|, or equally of (ty, r - tx) (that times sign(psi)); the first is
    used where tx >= 0 and the second elsewhere, so neither divides a difference of nearly equal numbers.
    The same numbers as ``psi = arctan2(ty, tx)`` within float rounding, at a fraction of the cost of an
    arctangent, a sine and a cosine in every predicted state. A zero tangent gives the identity.
    """
    r = jnp.sqrt(tx * tx + ty * ty)
    forward = tx >= 0.0
    c = jnp.where(forward, r + tx, ty)
    s = jnp.where(forward, ty, r - tx)
    norm2 = c * c + s * s
    ok = norm2 > 0.0
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, norm2, 1.0)), 0.0)
    zero = jnp.zeros_like(r)
    return [jnp.where(ok, c * inv, 1.0), zero, zero, s * inv]


def _attitude_distance(q_d: list, q: list) -> jax.Array:
    """min(|q_d - q|^2, |q_d + q|^2) of quaternions given as [qw, qx, qy, qz] lists of equally shaped arrays: q and
    -q are one attitude."""
    minus = ((q_d[0] - q[0]) ** 2 + (q_d[1] - q[1]) ** 2) + ((q_d[2] - q[2]) ** 2 + (q_d[3] - q[3]) ** 2)
    plus = ((q_d[0] + q[0]) ** 2 + (q_d[1] + q[1]) ** 2) + ((q_d[2] + q[2]) ** 2 + (q_d[3] + q[3]) ** 2)
    return jnp.minimum(minus, plus)


def plan_progress(track: track_lib.Track, trajectory: jax.Array, progress_s: jax.Array, horizon: int,
                  search_m: float = 60.0) -> jax.Array:
    """Progress (m) along the path of each state the next tick's horizon steps will be compared with.

    Takes the nominal trajectory predicted at this tick, (T+1, n) from x0, shifts it by one step (the next
    tick starts one step later) and repeats the last state, returning (T,) arc lengths. The search is
    limited to ``search_m`` of path after the current progress.
    """
    positions = trajectory[2:, :3]
    positions = jnp.concatenate([positions, positions[-1:]], axis=0)[:horizon]
    length = min(int(search_m / track_lib.PATH_SPACING) + 2, track.num_path_points)
    start = jnp.floor((progress_s - 2.0) / track.path_spacing).astype(jnp.int32)
    window = track_lib.PathWindow(start=start, length=length)
    return jax.vmap(lambda p: track_lib.path_query(track, p, window).progress_s)(positions)
