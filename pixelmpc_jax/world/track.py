"""The race course: gates, the closed hall, the desired path, gate passage and collisions (building a
course from a course file, the straight course and perturbed courses: :mod:`pixelmpc_jax.world.course`).

World frame ENU (z up), metres. A gate's ``rotation`` has the columns ``[normal, lateral, up]``: the
normal is the direction of travel through the gate, ``lateral = up x normal`` points left when looking
along the normal and ``up`` is the opening's height axis, so the frame is right-handed like the body
frame (x forward, y left, z up). Seen from the approach side (looking along the normal) image u grows
along ``-lateral`` and v along ``-up``.

Geometry choices (the paper's FlightGoggles hall is not in the facts file):

- Gate corners in the course file are the inner opening's corners; the frame is ``border`` (0.3 m,
  ``race.gate_frame_width_m``) wide around it and ``GATE_DEPTH`` (0.1 m) thick along the normal.
- The hall is a closed box: ``HALL_MARGIN`` (8 m) horizontally around every gate frame, the start and
  the desired path; floor at z = 0; ceiling at ``max(HALL_CEILING, highest point + 3 m)``. A perturbed
  course keeps its hall (it is a building); the margin exceeds the largest AlphaPilot perturbation (5 m).
- The vehicle is a sphere of radius ``VEHICLE_RADIUS`` (0.1 m) for collisions: ground below z = 0.1 m,
  walls and ceiling 0.1 m inside the hall box, gate frames inflated by 0.1 m.
- The desired path is a chain of cubic Hermite segments start -> gate 1 -> ... -> gate G -> run-out:
  the tangent at a gate is its normal, at the start the chord towards gate 1, each scaled by the
  segment's chord length (``PATH_TANGENT_SCALE``); it ends with a straight ``PATH_RUNOUT`` (5 m) past
  the last gate along its normal. The curve is resampled uniformly in arc length at about
  ``PATH_SPACING`` (0.25 m), which makes it C1 in arc length (unit tangent continuous). The number of
  path points P is fixed when a course is loaded; a perturbed course keeps P (its spacing changes by a
  few percent) so that perturbed tracks share shapes: they stack, vmap and never recompile.

Every function here is pure and compiles nothing itself: the caller's jit traces it, and a caller that runs one at
the top level compiles it through :func:`pixelmpc_jax.devices.compiled` (a new course's path: ``world/course.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

GATE_BORDER = 0.3  # m, frame width around the opening (race.gate_frame_width_m)
GATE_DEPTH = 0.1  # m, frame thickness along the normal
VEHICLE_RADIUS = 0.1  # m, collision sphere of the drone
HALL_MARGIN = 8.0  # m, horizontal clearance of the hall walls around the course
HALL_CEILING = 15.0  # m, minimum ceiling height
PATH_SPACING = 0.25  # m, target spacing of the dense desired path
PATH_RUNOUT = 5.0  # m, straight path past the last gate
PATH_TANGENT_SCALE = 1.0  # Hermite tangent magnitude, in chord lengths
_DENSE_PER_SEGMENT = 256  # Hermite samples per segment before the arc-length resampling
_WINDOW_SLACK = 1.25  # gate_window covers its metres on tracks with spacing >= PATH_SPACING / 1.25

CRASH_NONE = 0
CRASH_GATE = 1
CRASH_GROUND = 2
CRASH_WALL = 3
CRASH_NAMES = {CRASH_NONE: "none", CRASH_GATE: "gate", CRASH_GROUND: "ground", CRASH_WALL: "wall"}

def _unit(v: jax.Array, fallback: jax.Array | None = None) -> jax.Array:
    """v / |v| along the last axis; ``fallback`` (or zeros) where |v| = 0, with NaN-free gradients."""
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 1e-24
    u = v / jnp.sqrt(jnp.where(ok, n2, 1.0))
    return jnp.where(ok, u, jnp.zeros_like(v) if fallback is None else fallback)


def _dot(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.sum(a * b, axis=-1)


# --------------------------------------------------------------------------------------------------
# Gates.
# --------------------------------------------------------------------------------------------------


@struct.dataclass
class Gate:
    """A rectangular gate; a single gate has the shapes below, a batch of G gates a leading axis G.

    Attributes:
        centre: (..., 3) centre of the opening, world frame.
        rotation: (..., 3, 3) columns ``[normal, lateral, up]`` (gate to world).
        width: (...,) inner opening width along ``lateral``, m.
        height: (...,) inner opening height along ``up``, m.
        border: (...,) frame width around the opening, m.
        depth: (...,) frame thickness along the normal, m.
    """

    centre: jax.Array
    rotation: jax.Array
    width: jax.Array
    height: jax.Array
    border: jax.Array
    depth: jax.Array

    @property
    def normal(self) -> jax.Array:
        """(..., 3) unit direction of travel through the gate."""
        return self.rotation[..., :, 0]

    @property
    def lateral(self) -> jax.Array:
        """(..., 3) unit width axis, pointing left when looking along the normal."""
        return self.rotation[..., :, 1]

    @property
    def up(self) -> jax.Array:
        """(..., 3) unit height axis."""
        return self.rotation[..., :, 2]

    def corners(self) -> jax.Array:
        """(..., 4, 3) inner corners: top-left, top-right, bottom-right, bottom-left seen along the normal."""
        return _rectangle(self, self.width, self.height)

    def outer_corners(self) -> jax.Array:
        """(..., 4, 3) outer frame corners, same order as :meth:`corners`."""
        return _rectangle(self, self.width + 2 * self.border, self.height + 2 * self.border)

    def to_local(self, points: jax.Array) -> jax.Array:
        """Gate-frame coordinates ``[along normal, along lateral, along up]`` of world points.

        points: (..., 3), broadcast against the gate's batch shape -> (..., 3).
        """
        shape = jnp.broadcast_shapes(jnp.shape(points), self.centre.shape)
        offset = jnp.broadcast_to(points, shape) - jnp.broadcast_to(self.centre, shape)
        return jnp.einsum("...ji,...j->...i", self.rotation, offset)


def make_gate(centre, rotation, width, height, border=GATE_BORDER, depth=GATE_DEPTH) -> Gate:
    """A float32 Gate from array-likes (shapes as in :class:`Gate`)."""
    centre = jnp.asarray(centre, jnp.float32)
    batch = centre.shape[:-1]
    full = lambda v: jnp.broadcast_to(jnp.asarray(v, jnp.float32), batch)  # noqa: E731
    return Gate(
        centre=centre,
        rotation=jnp.asarray(rotation, jnp.float32),
        width=full(width),
        height=full(height),
        border=full(border),
        depth=full(depth),
    )


_CORNER_SIGNS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))  # (lateral, up): TL, TR, BR, BL


def _rectangle(gate: Gate, width: jax.Array, height: jax.Array) -> jax.Array:
    batch = gate.centre.shape[:-1]
    signs = jnp.asarray(_CORNER_SIGNS, dtype=gate.centre.dtype).reshape((1,) * len(batch) + (4, 2))
    half_l = (0.5 * width)[..., None, None] * signs[..., 0:1]  # (..., 4, 1)
    half_u = (0.5 * height)[..., None, None] * signs[..., 1:2]
    return gate.centre[..., None, :] + half_l * gate.lateral[..., None, :] + half_u * gate.up[..., None, :]


def gate_corners(gate: Gate) -> jax.Array:
    """(..., 4, 3) inner-opening corners: top-left, top-right, bottom-right, bottom-left, as seen looking
    along the normal (image u = -lateral, v = -up)."""
    return gate.corners()


def gate_outer_corners(gate: Gate) -> jax.Array:
    """(..., 4, 3) outer frame corners, in the order of :func:`gate_corners`."""
    return gate.outer_corners()


def gate_rotation(normal: jax.Array) -> jax.Array:
    """(..., 3, 3) gate rotation ``[normal, lateral, up]`` of a (..., 3) normal, ``up`` closest to world z.

    The normal must not be vertical (a gate is not a trapdoor); ``course.load_course`` checks that.
    """
    n = _unit(normal)
    z = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], n.dtype), n.shape)
    up = _unit(z - _dot(z, n)[..., None] * n)
    lateral = jnp.cross(up, n)
    return jnp.stack([n, lateral, up], axis=-1)


def yaw_rotation(yaw: jax.Array) -> jax.Array:
    """(..., 3, 3) rotations about world z by ``yaw`` (...,) rad."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    zero, one = jnp.zeros_like(yaw), jnp.ones_like(yaw)
    return jnp.stack([jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1), jnp.stack([zero, zero, one], -1)],
                     -2)


def offset_gates(gates: Gate, offset: jax.Array) -> Gate:
    """``gates`` (a G-batch) each moved by its ``offset`` (G, 4) ``[dx, dy, dz (m), dyaw (rad)]``: the centre shifted,
    the gate turned about world z through its centre by ``dyaw`` (as ``course.perturb_gates`` moves one)."""
    offset = jnp.asarray(offset, gates.centre.dtype)
    return gates.replace(centre=gates.centre + offset[..., :3],
                         rotation=yaw_rotation(offset[..., 3]) @ gates.rotation)


def gate_passed(gate: Gate, p0: jax.Array, p1: jax.Array) -> jax.Array:
    """Whether the segment p0 -> p1 crosses the gate plane, forwards along the normal, inside the opening.

    Starting behind the plane (strictly) and ending on or past it counts; a backwards crossing does not.

    Args:
        gate: one gate, or a batch (G leading axes).
        p0, p1: (3,) segment end points (the vehicle centre at two instants).

    Returns:
        (...,) bool, the gate's batch shape.
    """
    l0 = gate.to_local(p0)
    l1 = gate.to_local(p1)
    d0, d1 = l0[..., 0], l1[..., 0]
    crosses = (d0 < 0.0) & (d1 >= 0.0)
    denom = jnp.where(crosses, d0 - d1, 1.0)
    t = jnp.where(crosses, d0 / denom, 0.0)
    x = l0 + t[..., None] * (l1 - l0)
    inside = (jnp.abs(x[..., 1]) <= 0.5 * gate.width) & (jnp.abs(x[..., 2]) <= 0.5 * gate.height)
    return crosses & inside


def frame_hit(gate: Gate, p0: jax.Array, p1: jax.Array, radius: float | jax.Array = VEHICLE_RADIUS):
    """Whether the segment p0 -> p1 touches the gate frame (box minus opening), the vehicle a sphere.

    The frame is the box ``|n| <= depth/2 + r, |lat| <= width/2 + border + r, |up| <= height/2 + border + r``
    (gate coordinates, r the radius) minus the opening prism ``|lat| < width/2 - r, |up| < height/2 - r``.
    The segment is clipped to the box (slab method); it hits unless it misses the box or its clipped
    part lies entirely in the opening prism (convex, so both clipped end points inside suffice).

    Returns:
        (...,) bool, the gate's batch shape.
    """
    l0 = gate.to_local(p0)
    l1 = gate.to_local(p1)
    d = l1 - l0
    half = jnp.stack(
        [
            0.5 * gate.depth + radius,
            0.5 * gate.width + gate.border + radius,
            0.5 * gate.height + gate.border + radius,
        ],
        axis=-1,
    )  # (..., 3)
    moving = jnp.abs(d) > 1e-9
    d_safe = jnp.where(moving, d, 1.0)
    ta = (-half - l0) / d_safe
    tb = (half - l0) / d_safe
    inside_axis = jnp.abs(l0) <= half
    t_lo = jnp.where(moving, jnp.minimum(ta, tb), jnp.where(inside_axis, -jnp.inf, jnp.inf))
    t_hi = jnp.where(moving, jnp.maximum(ta, tb), jnp.where(inside_axis, jnp.inf, -jnp.inf))
    t_in = jnp.maximum(jnp.max(t_lo, axis=-1), 0.0)
    t_out = jnp.minimum(jnp.min(t_hi, axis=-1), 1.0)
    touches_box = t_in <= t_out
    t_in_c = jnp.clip(t_in, 0.0, 1.0)[..., None]
    t_out_c = jnp.clip(t_out, 0.0, 1.0)[..., None]
    q_in = l0 + t_in_c * d
    q_out = l0 + t_out_c * d
    half_w = (0.5 * gate.width - radius)[..., None]
    half_h = (0.5 * gate.height - radius)[..., None]
    q = jnp.stack([q_in, q_out], axis=-2)  # (..., 2, 3)
    in_opening = jnp.all((jnp.abs(q[..., 1]) < half_w) & (jnp.abs(q[..., 2]) < half_h), axis=-1)
    return touches_box & ~in_opening


# --------------------------------------------------------------------------------------------------
# The track.
# --------------------------------------------------------------------------------------------------


@struct.dataclass
class Track:
    """A race course: gates in race order, the start, the hall and the dense desired path.

    Attributes:
        gates: Gate with leaves of leading axis G, in race order.
        start: (10,) robot state at the start pose (at rest).
        hall_min, hall_max: (3,) corners of the closed hall box (floor at hall_min[2]).
        path_points: (P, 3) desired path sampled uniformly in arc length.
        path_tangents: (P, 3) unit tangents of the path.
        path_s: (P,) arc length from the start, m.
        path_gate_s: (G,) arc length at each gate centre.
        perturbation_bounds: (G, 3) per-gate ``[dx m, dy m, dyaw deg]`` bounds of ``course.perturb_course``.
        names: static gate names in race order.
    """

    gates: Gate
    start: jax.Array
    hall_min: jax.Array
    hall_max: jax.Array
    path_points: jax.Array
    path_tangents: jax.Array
    path_s: jax.Array
    path_gate_s: jax.Array
    perturbation_bounds: jax.Array
    names: tuple[str, ...] = struct.field(pytree_node=False, default=())

    @property
    def num_gates(self) -> int:
        return int(self.gates.centre.shape[0])

    @property
    def num_path_points(self) -> int:
        return int(self.path_s.shape[0])

    @property
    def path_spacing(self) -> jax.Array:
        """() spacing of the path samples, m (about PATH_SPACING)."""
        return self.path_s[1] - self.path_s[0]

    def gate(self, index) -> Gate:
        """The gate at ``index`` (int or traced int) as a single Gate."""
        return jax.tree_util.tree_map(lambda leaf: leaf[index], self.gates)


# --------------------------------------------------------------------------------------------------
# The desired path.
# --------------------------------------------------------------------------------------------------


def _hermite(p0, p1, m0, m1, tau):
    """Cubic Hermite points and derivatives; p*, m*: (S, 3), tau: (M,) -> (S, M, 3) twice."""
    t = tau[None, :, None]
    t2, t3 = t * t, t * t * t
    h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + t, -2 * t3 + 3 * t2, t3 - t2
    g00, g10, g01, g11 = 6 * t2 - 6 * t, 3 * t2 - 4 * t + 1, -6 * t2 + 6 * t, 3 * t2 - 2 * t
    p0, p1, m0, m1 = (a[:, None, :] for a in (p0, p1, m0, m1))
    points = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
    derivs = g00 * p0 + g10 * m0 + g01 * p1 + g11 * m1
    return points, derivs


def dense_path(start_position: jax.Array, centres: jax.Array, normals: jax.Array):
    """Densely sampled Hermite chain start -> gates -> run-out (``_DENSE_PER_SEGMENT`` samples a segment).

    Returns:
        points: (N, 3), derivatives: (N, 3), arc length s: (N,), gate arc lengths: (G,).
    """
    runout_end = centres[-1] + PATH_RUNOUT * normals[-1]
    knots = jnp.concatenate([start_position[None], centres, runout_end[None]], axis=0)  # (G+2, 3)
    first = _unit(centres[0] - start_position, normals[0])
    tangents = jnp.concatenate([first[None], normals, normals[-1:]], axis=0)  # (G+2, 3)
    chord = jnp.linalg.norm(knots[1:] - knots[:-1], axis=-1, keepdims=True)  # (G+1, 1)
    m0 = PATH_TANGENT_SCALE * chord * tangents[:-1]
    m1 = PATH_TANGENT_SCALE * chord * tangents[1:]
    tau = jnp.arange(_DENSE_PER_SEGMENT, dtype=knots.dtype) / _DENSE_PER_SEGMENT
    pts, der = _hermite(knots[:-1], knots[1:], m0, m1, tau)  # (G+1, M, 3)
    points = jnp.concatenate([pts.reshape(-1, 3), knots[-1:]], axis=0)
    derivs = jnp.concatenate([der.reshape(-1, 3), m1[-1:]], axis=0)
    steps = jnp.linalg.norm(points[1:] - points[:-1], axis=-1)
    s = jnp.concatenate([jnp.zeros((1,), points.dtype), jnp.cumsum(steps)])
    num_gates = centres.shape[0]
    gate_s = s[(jnp.arange(num_gates) + 1) * _DENSE_PER_SEGMENT]
    return points, derivs, s, gate_s


def resample_path(points, derivs, s, num_points: int):
    """Uniform arc-length resampling of a dense polyline (:func:`dense_path`'s points, derivatives, arc length)
    -> points (P, 3), unit tangents (P, 3), s (P,); P = ``num_points``, static under jit."""
    s_new = jnp.linspace(0.0, s[-1], num_points, dtype=points.dtype)
    idx = jnp.clip(jnp.searchsorted(s, s_new, side="right") - 1, 0, s.shape[0] - 2)
    ds = s[idx + 1] - s[idx]
    frac = jnp.where(ds > 0, (s_new - s[idx]) / jnp.where(ds > 0, ds, 1.0), 0.0)[:, None]
    pts = points[idx] + frac * (points[idx + 1] - points[idx])
    chord = _unit(points[idx + 1] - points[idx])
    tan = _unit(derivs[idx] + frac * (derivs[idx + 1] - derivs[idx]), chord)
    return pts, tan, s_new


def build_path(start_position: jax.Array, gates: Gate, num_points: int):
    """The desired path through ``gates`` (leading axis G) from ``start_position`` (3,): :func:`dense_path`, then
    :func:`resample_path` to ``num_points`` samples.

    Pure and jit-able with ``num_points`` static (a perturbed course's path, inside the caller's jit or vmap). A new
    course's path, whose P comes from its length (:func:`path_point_count`), is built on the host from the two
    halves, each compiled by its caller (:func:`pixelmpc_jax.world.course.load_course` and the other builders).

    Returns:
        points (P, 3), unit tangents (P, 3), arc length s (P,), gate arc lengths (G,).
    """
    points, derivs, s, gate_s = dense_path(start_position, gates.centre, gates.normal)
    pts, tan, s_new = resample_path(points, derivs, s, num_points=num_points)
    return pts, tan, s_new, gate_s


def with_gates(track: Track, gates: Gate) -> Track:
    """``track`` with ``gates`` (the same G) and its desired path rebuilt through them with the same number of samples
    (:func:`build_path`), its start, hall and bounds kept. Pure: a course perturbed inside a jit, or the map as an
    estimator places its gates, tick by tick."""
    pts, tan, s_path, gate_s = build_path(track.start[:3], gates, track.num_path_points)
    return track.replace(gates=gates, path_points=pts, path_tangents=tan, path_s=s_path, path_gate_s=gate_s)


def path_point_count(length: float) -> int:
    """P for a path ``length`` m long: samples about ``PATH_SPACING`` apart, both ends included."""
    return int(math.ceil(length / PATH_SPACING)) + 1


class PathQuery(NamedTuple):
    """Result of :func:`path_query` for one position.

    Attributes:
        distance: () distance to the path, m.
        progress_s: () arc length of the closest point, m.
        tangent: (3,) unit path tangent at the closest point.
        closest_point: (3,) closest point on the path.
    """

    distance: jax.Array
    progress_s: jax.Array
    tangent: jax.Array
    closest_point: jax.Array


@struct.dataclass
class PathWindow:
    """A contiguous range of path samples: ``start`` (() int32, dynamic) and ``length`` (static int)."""

    start: jax.Array
    length: int = struct.field(pytree_node=False, default=2)


def gate_window(track: Track, target_gate_index, before_m: float, after_m: float) -> PathWindow:
    """The path samples from ``before_m`` before to ``after_m`` after gate ``target_gate_index``.

    ``before_m`` and ``after_m`` are Python floats (they set the static length); the gate index may be
    traced and is clipped to the last gate (a finished lap keeps the last window). The length is sized at
    ``PATH_SPACING / 1.25``, so the window spans at least the requested metres on any track whose
    spacing is above that (loaded courses and their perturbations); it is clamped to the path.
    """
    num_points = track.num_path_points
    length = min(int(math.ceil(_WINDOW_SLACK * (before_m + after_m) / PATH_SPACING)) + 2, num_points)
    g = jnp.clip(jnp.asarray(target_gate_index, jnp.int32), 0, track.num_gates - 1)
    first = jnp.floor((track.path_gate_s[g] - before_m) / track.path_spacing).astype(jnp.int32)
    start = jnp.clip(first, 0, num_points - length)
    return PathWindow(start=start, length=length)


def path_query(track: Track, position: jax.Array, window: PathWindow | None = None) -> PathQuery:
    """Closest point of the desired path to ``position`` (3,), projected onto the sampled segments.

    With ``window`` only the window's samples are searched (``lax.dynamic_slice`` of static size: the
    cost is O(window), not O(P)); without it the whole path is. Ties go to the earlier segment.
    """
    points, tangents, s = track.path_points, track.path_tangents, track.path_s
    if window is not None:
        length = max(min(int(window.length), points.shape[0]), 2)
        start = jnp.clip(jnp.asarray(window.start, jnp.int32), 0, points.shape[0] - length)
        points = jax.lax.dynamic_slice_in_dim(points, start, length)
        tangents = jax.lax.dynamic_slice_in_dim(tangents, start, length)
        s = jax.lax.dynamic_slice_in_dim(s, start, length)
    a, b = points[:-1], points[1:]  # (L-1, 3)
    ab = b - a
    len2 = jnp.sum(ab * ab, axis=-1)
    position = jnp.asarray(position)[None, :]
    t = jnp.clip(_dot(position - a, ab) / jnp.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    closest = a + t[:, None] * ab
    dist2 = jnp.sum((position - closest) ** 2, axis=-1)
    i = jnp.argmin(dist2)
    ti = t[i]
    tangent = _unit(tangents[i] + ti * (tangents[i + 1] - tangents[i]), tangents[i])
    progress = s[i] + ti * (s[i + 1] - s[i])
    return PathQuery(
        distance=jnp.sqrt(jnp.maximum(dist2[i], 1e-20)) * (dist2[i] > 0),
        progress_s=progress,
        tangent=tangent,
        closest_point=closest[i],
    )


# --------------------------------------------------------------------------------------------------
# Collisions.
# --------------------------------------------------------------------------------------------------


def collision(track: Track, p0: jax.Array, p1: jax.Array, radius: float | jax.Array = VEHICLE_RADIUS):
    """Whether the segment p0 -> p1 (the vehicle centre, a sphere of ``radius``) crashes, and why.

    Causes, first match wins: CRASH_GATE (touches any gate frame, all gates at once), CRASH_GROUND
    (z below the floor + radius), CRASH_WALL (outside the hall box shrunk by the radius; the ceiling
    counts as a wall).

    Returns:
        hit: () bool; cause: () int32, one of the CRASH_* constants.
    """
    gate = jnp.any(frame_hit(track.gates, p0, p1, radius))
    z_min = jnp.minimum(p0[2], p1[2])
    ground = z_min < track.hall_min[2] + radius
    lo = jnp.minimum(p0, p1)
    hi = jnp.maximum(p0, p1)
    wall = jnp.any(lo < track.hall_min + radius) | jnp.any(hi > track.hall_max - radius)
    cause = jnp.where(gate, CRASH_GATE, jnp.where(ground, CRASH_GROUND, jnp.where(wall, CRASH_WALL, 0)))
    cause = cause.astype(jnp.int32)
    return cause != CRASH_NONE, cause
