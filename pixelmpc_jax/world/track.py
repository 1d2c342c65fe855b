"""The race course: gates, the closed hall, the desired path, gate passage and collisions.

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
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax.dynamics import quadrotor

COURSE_FILE = Path(__file__).resolve().parent.parent / "data" / "alphapilot_course.json"

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

_TOP_LEVEL_FIELDS = {"about", "race", "gates", "camera", "vehicle"}
_RACE_FIELDS = {"gate_order", "init_pose", "timeout_s", "gate_frame_width_m", "perturbation_bounds_note"}
_POSE_FIELDS = {"position", "quaternion_xyzw", "note"}
_GATE_FIELDS = {"corners", "perturbation_bound"}


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

    The normal must not be vertical (a gate is not a trapdoor); :func:`load_course` checks that.
    """
    n = _unit(normal)
    z = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], n.dtype), n.shape)
    up = _unit(z - _dot(z, n)[..., None] * n)
    lateral = jnp.cross(up, n)
    return jnp.stack([n, lateral, up], axis=-1)


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
        perturbation_bounds: (G, 3) per-gate ``[dx m, dy m, dyaw deg]`` bounds of :func:`perturb_course`.
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


@jax.jit
def _dense_path(start_position: jax.Array, centres: jax.Array, normals: jax.Array):
    """Densely sampled Hermite chain start -> gates -> run-out.

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


def _resample(points, derivs, s, num_points: int):
    """Uniform arc-length resampling of a dense polyline -> points (P, 3), unit tangents (P, 3), s (P,)."""
    s_new = jnp.linspace(0.0, s[-1], num_points, dtype=points.dtype)
    idx = jnp.clip(jnp.searchsorted(s, s_new, side="right") - 1, 0, s.shape[0] - 2)
    ds = s[idx + 1] - s[idx]
    frac = jnp.where(ds > 0, (s_new - s[idx]) / jnp.where(ds > 0, ds, 1.0), 0.0)[:, None]
    pts = points[idx] + frac * (points[idx + 1] - points[idx])
    chord = _unit(points[idx + 1] - points[idx])
    tan = _unit(derivs[idx] + frac * (derivs[idx + 1] - derivs[idx]), chord)
    return pts, tan, s_new


_resample_jit = jax.jit(_resample, static_argnames="num_points")


def build_path(start_position: jax.Array, gates: Gate, num_points: int):
    """The desired path through ``gates`` (leading axis G) from ``start_position`` (3,).

    Pure and jit-able with ``num_points`` static.

    Returns:
        points (P, 3), unit tangents (P, 3), arc length s (P,), gate arc lengths (G,).
    """
    points, derivs, s, gate_s = _dense_path(start_position, gates.centre, gates.normal)
    pts, tan, s_new = _resample_jit(points, derivs, s, num_points=num_points)
    return pts, tan, s_new, gate_s


def _num_path_points(length: float) -> int:
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


# --------------------------------------------------------------------------------------------------
# Courses.
# --------------------------------------------------------------------------------------------------


_outer_corners_jit = jax.jit(gate_outer_corners)


def _hall(gates: Gate, start_position, path_points, ceiling_min: float = HALL_CEILING):
    pts = np.concatenate(
        [
            np.asarray(_outer_corners_jit(gates)).reshape(-1, 3),
            np.asarray(start_position)[None],
            np.asarray(path_points),
        ]
    )
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    hall_min = np.array([lo[0] - HALL_MARGIN, lo[1] - HALL_MARGIN, 0.0])
    hall_max = np.array([hi[0] + HALL_MARGIN, hi[1] + HALL_MARGIN, max(ceiling_min, hi[2] + 3.0)])
    return jnp.asarray(hall_min, jnp.float32), jnp.asarray(hall_max, jnp.float32)


def _assemble(names, gates: Gate, start, bounds) -> Track:
    """A Track with its path (P from the nominal length) and hall."""
    start = jnp.asarray(start, jnp.float32)
    points, derivs, s_dense, gate_s = _dense_path(start[:3], gates.centre, gates.normal)
    num_points = _num_path_points(float(s_dense[-1]))
    pts, tan, s = _resample_jit(points, derivs, s_dense, num_points=num_points)
    hall_min, hall_max = _hall(gates, start[:3], pts)
    return Track(
        gates=gates,
        start=start,
        hall_min=hall_min,
        hall_max=hall_max,
        path_points=pts,
        path_tangents=tan,
        path_s=s,
        path_gate_s=gate_s,
        perturbation_bounds=jnp.asarray(bounds, jnp.float32).reshape(len(names), 3),
        names=tuple(names),
    )


def _check_fields(found, allowed, where: str) -> None:
    unknown = sorted(set(found) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown}; expected a subset of {sorted(allowed)}")


def _vector(value, size: int, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: expected {size} numbers, got {value!r}") from err
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: expected {size} finite numbers, got {value!r}")
    return arr


def _gate_geometry(name: str, corners_raw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (3,), plane normal (3,) (unoriented) and corners (4, 3) of one gate from the file."""
    where = f"gate {name!r} corners"
    if not isinstance(corners_raw, list) or len(corners_raw) != 4:
        count = len(corners_raw) if isinstance(corners_raw, list) else type(corners_raw).__name__
        raise ValueError(f"{where}: expected 4 corners [[x, y, z], ...], got {count}")
    corners = np.stack([_vector(c, 3, f"{where}[{k}]") for k, c in enumerate(corners_raw)])
    centre = corners.mean(axis=0)
    _, sv, vt = np.linalg.svd(corners - centre)
    if sv[1] < 1e-2:
        raise ValueError(f"{where}: degenerate (coincident or collinear corners, singular values {sv})")
    if sv[2] > 0.05:
        raise ValueError(f"{where}: the 4 corners are not in one plane (out-of-plane spread {sv[2]:.3f} m)")
    normal = vt[2]
    if abs(normal[2]) > 0.5:
        raise ValueError(f"{where}: the gate plane is tilted over 60 deg from vertical (normal {normal})")
    return centre, normal, corners


def load_course(path: str | Path | None = None) -> Track:
    """The race course of a course file (default: the packaged AlphaPilot file) in ``race.gate_order``.

    Each gate's centre is its corners' mean, its normal the corners' plane normal (SVD) oriented along the
    direction of travel (from the previous waypoint, the start for the first gate, towards the next gate;
    towards the gate itself for the last one), width and height its extents along lateral and up.

    Raises:
        ValueError: unknown fields, a gate without 4 three-dimensional corners, degenerate corners, a
            gate in ``gate_order`` missing from ``gates``, a malformed start pose.
    """
    path = Path(path) if path is not None else COURSE_FILE
    data = json.loads(Path(path).read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    _check_fields(data, _TOP_LEVEL_FIELDS, f"{path}")
    for key in ("race", "gates"):
        if not isinstance(data.get(key), dict):
            raise ValueError(f"{path}: missing or malformed {key!r} block (an object is required)")
    race, gates_raw = data["race"], data["gates"]
    _check_fields(race, _RACE_FIELDS, "race")
    order = race.get("gate_order")
    if not isinstance(order, list) or not order or not all(isinstance(n, str) for n in order):
        raise ValueError(f"race.gate_order: expected a non-empty list of gate names, got {order!r}")
    missing = [n for n in order if n not in gates_raw]
    if missing:
        raise ValueError(f"race.gate_order names gate(s) {missing} missing from 'gates' {sorted(gates_raw)}")
    pose = race.get("init_pose")
    if not isinstance(pose, dict):
        raise ValueError("race.init_pose: expected {'position': [x, y, z], 'quaternion_xyzw': [x, y, z, w]}")
    _check_fields(pose, _POSE_FIELDS, "race.init_pose")
    position = _vector(pose.get("position"), 3, "race.init_pose.position")
    q_xyzw = _vector(pose.get("quaternion_xyzw"), 4, "race.init_pose.quaternion_xyzw")
    if np.linalg.norm(q_xyzw) < 1e-6:
        raise ValueError("race.init_pose.quaternion_xyzw: zero quaternion")
    q = np.array([q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]]) / np.linalg.norm(q_xyzw)
    border = float(race.get("gate_frame_width_m", GATE_BORDER))
    if not (math.isfinite(border) and border >= 0):
        raise ValueError(f"race.gate_frame_width_m: expected a finite number >= 0, got {border!r}")

    centres, normals, widths, heights, bounds = [], [], [], [], []
    for name, raw in gates_raw.items():
        if not isinstance(raw, dict):
            raise ValueError(f"gate {name!r}: expected an object with 'corners'")
        _check_fields(raw, _GATE_FIELDS, f"gate {name!r}")
        if "corners" not in raw:
            raise ValueError(f"gate {name!r}: missing 'corners'")
        _gate_geometry(name, raw["corners"])  # validate every gate, raced or not
        if "perturbation_bound" in raw:
            _vector(raw["perturbation_bound"], 3, f"gate {name!r} perturbation_bound")
    geometry = [_gate_geometry(n, gates_raw[n]["corners"]) for n in order]
    for k, (name, (centre, normal, corners)) in enumerate(zip(order, geometry, strict=True)):
        previous = position if k == 0 else geometry[k - 1][0]
        following = geometry[k + 1][0] if k + 1 < len(order) else centre
        travel = following - previous
        if np.dot(normal, travel) < 0:
            normal = -normal
        up = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
        up /= np.linalg.norm(up)
        rotation = np.stack([normal, np.cross(up, normal), up], axis=-1)  # as gate_rotation, in float64
        local = (corners - centre) @ rotation  # (4, 3): [n, lateral, up]
        centres.append(centre)
        normals.append(rotation)
        widths.append(np.ptp(local[:, 1]))
        heights.append(np.ptp(local[:, 2]))
        bound = gates_raw[name].get("perturbation_bound", [0.0, 0.0, 0.0])
        bounds.append(_vector(bound, 3, f"gate {name!r} perturbation_bound"))
    gates = make_gate(np.stack(centres), np.stack(normals), np.array(widths), np.array(heights), border)
    start = np.concatenate([position, q, np.zeros(3)])
    return _assemble(order, gates, start, np.stack(bounds))


def straight_course(
    num_gates: int = 5,
    spacing: float = 20.0,
    height: float = 3.0,
    first_gate_x: float = 20.0,
    width: float = 1.8,
    gate_height: float = 1.85,
    border: float = GATE_BORDER,
    perturbation_bound=(0.0, 0.0, 0.0),
) -> Track:
    """Gates in a row along +x (the paper's 20 m/s straight-lane test), the start at rest at
    ``(0, 0, height)`` heading +x, the first gate at ``x = first_gate_x``, gates ``spacing`` apart at
    centre height ``height``; gate size defaults to the AlphaPilot gates (1.8 x 1.85 m)."""
    if num_gates < 1 or spacing <= 0 or first_gate_x <= 0 or width <= 0 or gate_height <= 0:
        raise ValueError(
            "straight_course: need num_gates >= 1 and positive spacing, first_gate_x, width, gate_height; "
            f"got {num_gates}, {spacing}, {first_gate_x}, {width}, {gate_height}"
        )
    if height - 0.5 * gate_height - border < 0:
        raise ValueError(f"straight_course: gate centre height {height} puts the frame below the floor")
    x = first_gate_x + spacing * np.arange(num_gates)
    centres = np.stack([x, np.zeros(num_gates), np.full(num_gates, height)], axis=-1)
    rotation = np.broadcast_to(np.eye(3), (num_gates, 3, 3))
    gates = make_gate(centres, rotation, width, gate_height, border)
    start = quadrotor.hover_state((0.0, 0.0, height), yaw=0.0)
    names = tuple(f"Gate{k + 1}" for k in range(num_gates))
    bounds = np.broadcast_to(np.asarray(perturbation_bound, np.float64), (num_gates, 3))
    return _assemble(names, gates, start, bounds)


def perturb_course(track: Track, key: jax.Array, bounds=None) -> Track:
    """The track with each gate moved by ``[dx, dy, dyaw]`` drawn uniformly in ``[-b, b]`` (m, m, deg).

    ``bounds``: (G, 3) or (3,), default ``track.perturbation_bounds`` (the AlphaPilot per-gate bounds).
    The gate keeps its size and direction of travel; the yaw turns it about world z through its centre.
    The path is rebuilt with the same number of samples and the hall is kept. Pure and deterministic for
    a key; jit- and vmap-able (over keys).
    """
    b = track.perturbation_bounds if bounds is None else jnp.asarray(bounds, jnp.float32)
    b = jnp.broadcast_to(jnp.abs(b), (track.num_gates, 3))
    draw = jax.random.uniform(key, (track.num_gates, 3), jnp.float32, minval=-1.0, maxval=1.0) * b
    centre = track.gates.centre + jnp.concatenate([draw[:, :2], jnp.zeros((track.num_gates, 1))], axis=-1)
    yaw = jnp.deg2rad(draw[:, 2])
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    zero, one = jnp.zeros_like(yaw), jnp.ones_like(yaw)
    rz = jnp.stack(
        [jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1), jnp.stack([zero, zero, one], -1)], -2
    )  # (G, 3, 3)
    gates = track.gates.replace(centre=centre, rotation=rz @ track.gates.rotation)
    pts, tan, s_path, gate_s = build_path(track.start[:3], gates, track.num_path_points)
    return track.replace(gates=gates, path_points=pts, path_tangents=tan, path_s=s_path, path_gate_s=gate_s)
