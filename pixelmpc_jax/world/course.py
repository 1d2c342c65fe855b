"""Building a race course (:class:`~pixelmpc_jax.world.track.Track`): from a course file (the packaged
AlphaPilot course by default), the straight course of the paper's straight-lane test, a course from its gates'
centres (:func:`course_from_gates`), and a course with its gates perturbed within their bounds; the courses known
by name (:data:`COURSES`) and the course a name or a file gives (:func:`make_course`); and generating a seeded
course file (:func:`generate_course`).

A built course gets its hall (``HALL_MARGIN`` around every gate frame, the start and the desired path; the
ceiling at ``max(HALL_CEILING, highest point + 3 m)``) and its desired path with the number of path points P
fixed from the nominal length; a perturbed course keeps both (see :mod:`pixelmpc_jax.world.track`).

Building a course is a job on the host (a file read and checked, P from the path's length); the path's two pure
halves run there as compiled programs through :func:`pixelmpc_jax.devices.compiled`, never a jit of the world's own
(:func:`move_gates` likewise, for a perturbed lap's course built on the host). :func:`perturb_course` is pure: it is
traced inside its caller's jit.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import devices
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.strict_json import write_json_atomic
from pixelmpc_jax.world.track import (
    GATE_BORDER,
    HALL_CEILING,
    HALL_MARGIN,
    PATH_RUNOUT,
    Gate,
    Track,
    dense_path,
    gate_outer_corners,
    make_gate,
    offset_gates,
    path_point_count,
    resample_path,
    with_gates,
    yaw_rotation,
)

COURSE_FILE = Path(__file__).resolve().parent.parent / "data" / "alphapilot_course.json"

_TOP_LEVEL_FIELDS = {"about", "race", "gates", "camera", "vehicle"}
_RACE_FIELDS = {"gate_order", "init_pose", "timeout_s", "gate_frame_width_m", "perturbation_bounds_note"}
_POSE_FIELDS = {"position", "quaternion_xyzw", "note"}
_GATE_FIELDS = {"corners", "perturbation_bound"}

GATE_WIDTH = 1.8  # m, inner opening of the AlphaPilot gates
GATE_HEIGHT = 1.85  # m


def _hall(gates: Gate, start_position, path_points, ceiling_min: float = HALL_CEILING):
    pts = np.concatenate(
        [
            np.asarray(gate_outer_corners(gates)).reshape(-1, 3),  # eager: the same bits as jitted
            np.asarray(start_position)[None],
            np.asarray(path_points),
        ]
    )
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    hall_min = np.array([lo[0] - HALL_MARGIN, lo[1] - HALL_MARGIN, 0.0])
    hall_max = np.array([hi[0] + HALL_MARGIN, hi[1] + HALL_MARGIN, max(ceiling_min, hi[2] + 3.0)])
    return jnp.asarray(hall_min, jnp.float32), jnp.asarray(hall_max, jnp.float32)


def _host_path(start_position: jax.Array, gates: Gate, num_points: int | None = None):
    """:func:`~pixelmpc_jax.world.track.build_path` on the host, P = ``num_points`` or, with None, fixed from the
    path's length (points about ``PATH_SPACING`` apart: a new course's path, whose P its perturbed versions keep; not
    jit-able, P depends on the geometry). Its two halves run as compiled programs
    (:func:`pixelmpc_jax.devices.compiled`), one each, as every course has been built: op by op they round otherwise,
    and one program of both rounds otherwise again."""
    points, derivs, s_dense, gate_s = devices.compiled(dense_path)(start_position, gates.centre, gates.normal)
    if num_points is None:
        num_points = path_point_count(float(s_dense[-1]))
    resample = devices.compiled(resample_path, "num_points")
    pts, tan, s = resample(points, derivs, s_dense, num_points=num_points)
    return pts, tan, s, gate_s


def _assemble(names, gates: Gate, start, bounds) -> Track:
    """A Track with its path (P from the nominal length) and hall."""
    start = jnp.asarray(start, jnp.float32)
    pts, tan, s, gate_s = _host_path(start[:3], gates)
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
    width: float = GATE_WIDTH,
    gate_height: float = GATE_HEIGHT,
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


def course_from_gates(centres, start=(0.0, 0.0, 3.0), width: float = GATE_WIDTH, height: float = GATE_HEIGHT,
                      border: float = GATE_BORDER) -> Track:
    """A course of upright gates at ``centres`` (G, 3), flown in that order from ``start`` (3,), at rest and heading
    for the first gate; each gate faces the direction of travel, level (from the gate before it, the start for the
    first, towards the gate after it; the last from the gate before it), of the AlphaPilot gates' size by default.

    Raises:
        ValueError: centres not (G, 3) finite numbers, a start not 3, a gate frame below the floor, two points
            of the course on top of each other.
    """
    centres = np.asarray(centres, np.float64)
    if centres.ndim != 2 or centres.shape[0] < 1 or centres.shape[1] != 3 or not np.all(np.isfinite(centres)):
        raise ValueError(f"centres: expected (G, 3) finite gate centres in metres, got shape {centres.shape}")
    position = _vector(start, 3, "start")
    if not (width > 0 and height > 0 and border >= 0):
        raise ValueError(f"course_from_gates: need width, height > 0 and border >= 0; got {width}, {height}, {border}")
    if np.any(centres[:, 2] - 0.5 * height - border < 0):
        raise ValueError(f"a gate's frame is below the floor: centre heights {centres[:, 2].tolist()}, frames "
                         f"{0.5 * height + border:g} m below them")
    points = np.concatenate([position[None], centres])
    travel = np.concatenate([centres[1:] - points[:-2], centres[-1:] - points[-2:-1]])[:, :2]  # (G, 2) level
    length = np.linalg.norm(travel, axis=1)
    if np.any(length < 1e-3):
        raise ValueError("two points of the course (the start or gates) are at one place seen from above")
    normals = np.concatenate([travel / length[:, None], np.zeros((len(centres), 1))], axis=1)
    rotation = np.stack([normals, np.cross([0.0, 0.0, 1.0], normals), np.broadcast_to([0.0, 0.0, 1.0],
                                                                                       normals.shape)], axis=-1)
    gates = make_gate(centres, rotation, width, height, border)
    first = centres[0] - position
    start_state = quadrotor.hover_state(tuple(position), yaw=float(np.arctan2(first[1], first[0])))
    names = tuple(f"Gate{k + 1}" for k in range(len(centres)))
    return _assemble(names, gates, start_state, np.zeros((len(centres), 3)))


class NamedCourse(NamedTuple):
    """A course known by name: what a report calls it, and what builds it."""

    title: str
    build: Callable[[], Track]


# The courses known by name; any other course is a course file (load_course).
COURSES = {"alphapilot": NamedCourse("the AlphaPilot course", load_course),
           "straight": NamedCourse("the straight lane", straight_course)}


def make_course(course: str = "alphapilot") -> Track:
    """The course ``course`` names: one of :data:`COURSES` ("alphapilot", the paper's race; "straight", five gates
    20 m apart in a row, the paper's straight-lane test), or the path of a course file (:func:`load_course`)."""
    if course in COURSES:
        return COURSES[course].build()
    if Path(course).is_file():
        return load_course(course)
    raise ValueError(f"unknown course {course!r}; choose one of {', '.join(COURSES)} or a course file")


def course_title(course: str) -> str:
    """What a report calls ``course``: a named course's title, a course file by its path."""
    return COURSES[course].title if course in COURSES else course


def perturb_course(track: Track, key: jax.Array, bounds=None) -> Track:
    """The track with its gates moved (:func:`perturb_gates`), its path rebuilt with the same number of samples and
    its hall kept.

    Pure and deterministic for a key; jit- and vmap-able (over keys): it compiles nothing itself, the caller's jit
    traces it. On the host, ``move_gates(track, perturb_gates(track, key))`` builds the same course with the path's
    halves compiled as a loaded course's are (:func:`move_gates`), within float rounding of this one.
    """
    return with_gates(track, perturb_gates(track, key, bounds))


def move_gates(track: Track, gates: Gate) -> Track:
    """The track with ``gates`` (the same G, moved within its hall), its path rebuilt on the host with the same number
    of samples (the path's halves compiled, as :func:`load_course` builds one) and its hall kept. Not jit-able; a
    perturbed lap's course (``move_gates(track, perturb_gates(track, key))``, the gates moved op by op) has the bits
    every perturbed race has flown."""
    pts, tan, s_path, gate_s = _host_path(track.start[:3], gates, track.num_path_points)
    return track.replace(gates=gates, path_points=pts, path_tangents=tan, path_s=s_path, path_gate_s=gate_s)


def perturb_gates(track: Track, key: jax.Array, bounds=None) -> Gate:
    """The track's gates, each moved by ``[dx, dy, dyaw]`` drawn uniformly in ``[-b, b]`` (m, m, deg).

    ``bounds``: (G, 3) or (3,), default ``track.perturbation_bounds`` (the AlphaPilot per-gate bounds).
    The gate keeps its size and direction of travel; the yaw turns it about world z through its centre. Pure and
    deterministic for a key; jit- and vmap-able (over keys).
    """
    b = track.perturbation_bounds if bounds is None else jnp.asarray(bounds, jnp.float32)
    b = jnp.broadcast_to(jnp.abs(b), (track.num_gates, 3))
    draw = jax.random.uniform(key, (track.num_gates, 3), jnp.float32, minval=-1.0, maxval=1.0) * b
    centre = track.gates.centre + jnp.concatenate([draw[:, :2], jnp.zeros((track.num_gates, 1))], axis=-1)
    return track.gates.replace(centre=centre, rotation=yaw_rotation(jnp.deg2rad(draw[:, 2])) @ track.gates.rotation)


# The error of a surveyed map, per gate (1 sigma): where a gate stands against where a tape-measured map of the hall
# puts it, [x, y, z (m), yaw (rad)]: a tape over tens of metres is good to about 0.1 m, a gate's height to 0.05 m, its
# heading to a degree. A lap on the surveyed course draws its gates from it (:func:`survey_gates`).
SURVEY_SIGMA = (0.1, 0.1, 0.05, math.radians(1.0))


def survey_gates(track: Track, key: jax.Array) -> Gate:
    """The track's gates as they stand against a surveyed map: each moved by an offset drawn from a normal
    distribution of :data:`SURVEY_SIGMA`. Pure and deterministic for a key."""
    offset = jax.random.normal(key, (track.num_gates, 4), jnp.float32) * jnp.asarray(SURVEY_SIGMA, jnp.float32)
    return offset_gates(track.gates, offset)


def gate_prior_std(track: Track, perturbed: bool) -> jax.Array:
    """(G, 4) what a drone given ``track`` as its map knows of where each gate stands, as the standard deviations of
    its offset ``[dx, dy, dz (m), dyaw (rad)]``: the survey's error (:data:`SURVEY_SIGMA`) and, with ``perturbed``,
    each gate moved anywhere within its published bounds (``track.perturbation_bounds``, uniform: ``b / sqrt(3)``)."""
    survey = jnp.broadcast_to(jnp.asarray(SURVEY_SIGMA, jnp.float32), (track.num_gates, 4))
    if not perturbed:
        return survey
    b = jnp.abs(jnp.asarray(track.perturbation_bounds, jnp.float32))
    moved = jnp.stack([b[:, 0], b[:, 1], jnp.zeros_like(b[:, 0]), jnp.deg2rad(b[:, 2])], axis=-1) / math.sqrt(3.0)
    return jnp.sqrt(survey**2 + moved**2)


# --------------------------------------------------------------------------------------------------
# A seeded course generator.
# --------------------------------------------------------------------------------------------------

GENERATOR_VERSION = 1
GATE_CENTRE_Z = (3.0, 7.0)  # m, gate centre height
LEG_LENGTH = (10.0, 22.0)  # m, between consecutive gate centres
START_DISTANCE = (15.0, 20.0)  # m, level from the start to the first gate
MAX_TURN_DEG = 70.0  # heading change between consecutive legs (the start -> first gate leg included)
MIN_SEPARATION = 6.0  # m, horizontal, between any two gate centres, and between the start and any gate
LEG_CLEARANCE = 4.0  # m, horizontal, from a leg (or the run-out) to any gate that is not one of its ends
FOOTPRINT = 70.0  # m, side of the square holding the start, the gate frames and the desired path
PATH_SWING = 2.0  # m, room left on each side of the footprint for the path's swing out of its straight legs
PERTURBATION_BOUND = (1.0, 1.0, 5.0)  # per gate: x, y (m), yaw (deg), as the AlphaPilot bounds
_CANDIDATES_PER_GATE = 64
_MAX_ATTEMPTS = 1000
_DECIMALS = 4  # rounding of the written coordinates (0.1 mm)


def _heading(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw), math.sin(yaw)])


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distances of points (N, 2) to the segment a-b ((2,) each)."""
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=-1)


def _runout_route(start: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(G + 2, 2) horizontal route: the start, the gate centres, the run-out end along the last leg."""
    route = np.concatenate([start[None], centres])[:, :2]
    last_leg = route[-1] - route[-2]
    return np.concatenate([route, (route[-1] + PATH_RUNOUT * last_leg / np.linalg.norm(last_leg))[None]])


def _footprint(route: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal box (lo (2,), hi (2,)) of route points (N, 2) and the frames of gates at centres (G, 3)."""
    half = 0.5 * GATE_WIDTH + GATE_BORDER  # a frame's corners lie within this of its centre, horizontally
    lo = np.minimum(route.min(axis=0), centres[:, :2].min(axis=0) - half)
    hi = np.maximum(route.max(axis=0), centres[:, :2].max(axis=0) + half)
    return lo, hi


def _layout_fits(start: np.ndarray, centres: np.ndarray, final: bool) -> bool:
    """Whether start (3,) and gate centres (k, 3) keep MIN_SEPARATION, LEG_CLEARANCE and FOOTPRINT (less
    the PATH_SWING on each side), all horizontal; with ``final`` the run-out past the last gate (along its
    last leg) is checked too."""
    knots = np.concatenate([start[None], centres])[:, :2]  # (k + 1, 2): the start, then the gates
    gap = np.linalg.norm(knots[:, None] - knots[None], axis=-1)[np.triu_indices(len(knots), 1)]
    if gap.min() < MIN_SEPARATION:
        return False
    route = _runout_route(start, centres) if final else knots
    for i in range(len(route) - 1):
        others = [j for j in range(1, len(knots)) if j not in (i, i + 1)]
        if others and _segment_distance(knots[others], route[i], route[i + 1]).min() < LEG_CLEARANCE:
            return False
    lo, hi = _footprint(route, centres)
    return bool((hi - lo).max() <= FOOTPRINT - 2 * PATH_SWING)


def _sample_layout(rng: np.random.Generator, num_gates: int) -> tuple[np.ndarray, np.ndarray] | None:
    """One try at a layout: start (3,) and gate centres (G, 3), or None where a gate found no place.

    The first gate is at the origin, the start level with it ``START_DISTANCE`` behind along a random
    heading; each next gate is a leg of ``LEG_LENGTH`` (3-D) on, turned by at most ``MAX_TURN_DEG``, at a
    height in ``GATE_CENTRE_Z``; a gate tries ``_CANDIDATES_PER_GATE`` places that keep
    :func:`_layout_fits`.
    """
    yaw = rng.uniform(-math.pi, math.pi)
    z = rng.uniform(*GATE_CENTRE_Z)
    centres = np.array([[0.0, 0.0, z]])
    start = np.array([*(-rng.uniform(*START_DISTANCE) * _heading(yaw)), z])
    for k in range(1, num_gates):
        for _ in range(_CANDIDATES_PER_GATE):
            turn = math.radians(rng.uniform(-MAX_TURN_DEG, MAX_TURN_DEG))
            length, z = rng.uniform(*LEG_LENGTH), rng.uniform(*GATE_CENTRE_Z)
            level = math.sqrt(length**2 - (z - centres[-1, 2]) ** 2)  # |dz| <= 4 m < the shortest leg
            candidate = np.array([*(centres[-1, :2] + level * _heading(yaw + turn)), z])
            placed = np.concatenate([centres, candidate[None]])
            if _layout_fits(start, placed, final=k == num_gates - 1):
                centres, yaw = placed, yaw + turn
                break
        else:
            return None
    if num_gates == 1 and not _layout_fits(start, centres, final=True):
        return None
    return start, centres


def _gate_yaws(start: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(G,) yaw of each gate's normal: the bisector of its legs in and out (the last gate: its leg in)."""
    route = np.concatenate([start[None], centres])[:, :2]
    legs = np.diff(route, axis=0)
    legs /= np.linalg.norm(legs, axis=-1, keepdims=True)  # (G, 2) unit leg into each gate
    facing = legs + np.concatenate([legs[1:], legs[-1:]])  # in + out; never zero (turns <= MAX_TURN_DEG)
    return np.arctan2(facing[:, 1], facing[:, 0])


def _gate_corners(centre: np.ndarray, yaw: float) -> np.ndarray:
    """(4, 3) inner corners of a vertical AlphaPilot-size gate facing ``yaw``: top-left, top-right,
    bottom-right, bottom-left seen along the normal (the order of ``Gate.corners``)."""
    lateral = np.array([-math.sin(yaw), math.cos(yaw), 0.0])  # up x normal: left of the direction of travel
    up = np.array([0.0, 0.0, 1.0])
    signs = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])  # (lateral, up)
    return centre + signs[:, :1] * 0.5 * GATE_WIDTH * lateral + signs[:, 1:] * 0.5 * GATE_HEIGHT * up


def generate_course(seed: int, num_gates: int = 8) -> dict:
    """A random race course in the course-file format of ``alphapilot_course.json``, deterministic in
    ``seed`` (numpy ``default_rng``).

    AlphaPilot-size vertical gates (1.8 x 1.85 m opening, 0.3 m frame) facing the direction of travel, centres
    3-7 m high, legs of 10-22 m turning at most 70 deg, gates at least 6 m apart and legs at least 4 m from
    the gates they do not join, the start level with the first gate 15-20 m before it and facing it, all
    within a 70 m square centred on the origin (see the bounds above; a try that breaks them is redrawn). The
    ``camera`` and ``vehicle`` blocks are the AlphaPilot file's. Load it with :func:`load_course` after
    :func:`write_course`.
    """
    if num_gates < 1:
        raise ValueError(f"generate_course: need num_gates >= 1, got {num_gates}")
    rng = np.random.default_rng(seed)
    for _ in range(_MAX_ATTEMPTS):
        layout = _sample_layout(rng, num_gates)
        if layout is not None:
            break
    else:
        raise RuntimeError(f"generate_course: no layout of {num_gates} gates found in {_MAX_ATTEMPTS} tries")
    start, centres = layout
    yaws = _gate_yaws(start, centres)
    corners = np.stack([_gate_corners(c, y) for c, y in zip(centres, yaws, strict=True)])  # (G, 4, 3)
    lo, hi = _footprint(_runout_route(start, centres), centres)
    shift = np.array([*(-0.5 * (lo + hi)), 0.0])  # the footprint centred on the origin
    return _course_file(seed, start + shift, corners + shift)


def _course_file(seed: int, start: np.ndarray, corners: np.ndarray) -> dict:
    """The course-file dict of a generated layout: start (3,), gate corners (G, 4, 3)."""
    alphapilot = json.loads(COURSE_FILE.read_text())
    names = [f"Gate{k + 1}" for k in range(len(corners))]
    to_first = corners[0].mean(axis=0) - start
    start_yaw = math.atan2(to_first[1], to_first[0])
    quaternion_xyzw = [0.0, 0.0, math.sin(0.5 * start_yaw), math.cos(0.5 * start_yaw)]
    rounded = lambda a: np.round(np.asarray(a, np.float64), _DECIMALS).tolist()  # noqa: E731
    return {
        "about": (
            f"Generated by pixelmpc_jax.world.course.generate_course (generator version {GENERATOR_VERSION}, "
            f"seed {seed}): {len(names)} AlphaPilot-size gates. World frame is ENU (z up), metres; gate corners "
            "are top-left, top-right, bottom-right, bottom-left seen along the direction of travel. The camera "
            "and vehicle blocks are those of the AlphaPilot course file."
        ),
        "race": {
            "gate_order": names,
            "init_pose": {
                "position": rounded(start),
                "quaternion_xyzw": quaternion_xyzw,
                "note": f"yaw {math.degrees(start_yaw):+.1f} deg, hovering, facing {names[0]}",
            },
            "timeout_s": alphapilot["race"]["timeout_s"],
            "gate_frame_width_m": GATE_BORDER,
            "perturbation_bounds_note": alphapilot["race"]["perturbation_bounds_note"],
        },
        "gates": {
            name: {"corners": rounded(c), "perturbation_bound": list(PERTURBATION_BOUND)}
            for name, c in zip(names, corners, strict=True)
        },
        "camera": copy.deepcopy(alphapilot["camera"]),
        "vehicle": copy.deepcopy(alphapilot["vehicle"]),
    }


def write_course(course: dict, path: str | Path) -> None:
    """Write a course dict (as :func:`generate_course` makes) to ``path`` as strict JSON, atomically."""
    write_json_atomic(path, course)
