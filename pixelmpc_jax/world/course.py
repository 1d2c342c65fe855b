"""Building a race course (:class:`~pixelmpc_jax.world.track.Track`): from a course file (the packaged
AlphaPilot course by default), the straight course of the paper's straight-lane test, and a course with its
gates perturbed within their bounds.

A built course gets its hall (``HALL_MARGIN`` around every gate frame, the start and the desired path; the
ceiling at ``max(HALL_CEILING, highest point + 3 m)``) and its desired path with the number of path points P
fixed from the nominal length; a perturbed course keeps both (see :mod:`pixelmpc_jax.world.track`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world.track import (
    GATE_BORDER,
    HALL_CEILING,
    HALL_MARGIN,
    Gate,
    Track,
    build_nominal_path,
    build_path,
    gate_outer_corners,
    make_gate,
)

COURSE_FILE = Path(__file__).resolve().parent.parent / "data" / "alphapilot_course.json"

_TOP_LEVEL_FIELDS = {"about", "race", "gates", "camera", "vehicle"}
_RACE_FIELDS = {"gate_order", "init_pose", "timeout_s", "gate_frame_width_m", "perturbation_bounds_note"}
_POSE_FIELDS = {"position", "quaternion_xyzw", "note"}
_GATE_FIELDS = {"corners", "perturbation_bound"}


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
    pts, tan, s, gate_s = build_nominal_path(start[:3], gates)
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
