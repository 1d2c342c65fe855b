"""Gate detectors: colour segmentation of rendered images (OpenCV) and projection of the true gate (JAX).

All return a :class:`Detection` in normalised image coordinates (``uv = px / (W, H)``, README "Conventions"). The
target pixel the controller tracks is ``Detection.centre``, the image of the gate's 3-D centre. From an
image it is the intersection of the diagonals of the four inner-opening corners: a perspective map keeps
lines and incidences, so the diagonals' crossing is exactly the image of the rectangle's centre.

From geometry there are two: :func:`detect_from_geometry`, the ideal projection (every corner and the centre,
in the image or not), and :func:`detect_in_view`, what a camera's detector reports of the same gate (the corners
inside the image, and with a corner out of view a centre from what is visible, as :func:`detect_from_image` takes
it: a YOLO box is clipped at the image border too).

With gates that look alike (one paint, ``render.GATE_PAINTS``), an image cannot say which gate it shows:
:func:`detect_candidates_from_image` reports the gate-like components in view as :class:`Candidates` (up to a fixed
K, padded, with a found mask), and the estimator side names the gate
(:mod:`pixelmpc_jax.perception.association`).
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax import devices
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import render as render_lib

_CORNER_ANGLES = np.radians([-135.0, -45.0, 45.0, 135.0])  # image-frame directions of TL, TR, BR, BL
# A vertex of the opening's 4-gon whose sides meet at more than this (degrees) is no corner: the outline runs straight
# through it. A sliver of opening cut by the image border gets such a vertex, since the 4-gon must have four.
_MAX_CORNER_ANGLE_DEG = 160.0


@struct.dataclass
class Detection:
    """One gate detection (single; leading axes when batched).

    Attributes:
        found: () bool, the gate is detected.
        centre: (2,) normalised uv of the gate centre's image.
        bbox: (4,) ``[u_min, v_min, u_max, v_max]`` normalised, the visible frame's box (clipped to the image).
        corners: (4, 2) normalised uv of the inner-opening corners, top-left, top-right, bottom-right,
            bottom-left as seen along the gate normal (zeros where not visible in an image detection).
        corners_visible: (4,) bool, the corner is in view (and, from an image, was found).
        gate_id: () int32, the gate's index in the track (-1 unknown).
    """

    found: jax.Array
    centre: jax.Array
    bbox: jax.Array
    corners: jax.Array
    corners_visible: jax.Array
    gate_id: jax.Array


@struct.dataclass
class Candidates:
    """The gate-like components an image shows, when the gates look alike: K slots, the largest first, padded.

    Attributes:
        found: (K,) bool, the slot holds a component.
        centre: (K, 2) normalised uv of each component's gate centre (as :class:`Detection`'s; 0.5 where empty).
        bbox: (K, 4) ``[u_min, v_min, u_max, v_max]`` normalised, each component's box (zeros where empty).
        corners: (K, 4, 2) normalised uv of each component's opening corners (zeros where not visible).
        corners_visible: (K, 4) bool.
        target: () int32, the gate the loop looks for (the one the association names a candidate for).
    """

    found: jax.Array
    centre: jax.Array
    bbox: jax.Array
    corners: jax.Array
    corners_visible: jax.Array
    target: jax.Array


def candidates_template(max_candidates: int) -> Candidates:
    """The shapes and dtypes of :class:`Candidates` with ``max_candidates`` slots (a host callback's result)."""
    k = int(max_candidates)
    return Candidates(
        found=jax.ShapeDtypeStruct((k,), jnp.bool_), centre=jax.ShapeDtypeStruct((k, 2), jnp.float32),
        bbox=jax.ShapeDtypeStruct((k, 4), jnp.float32), corners=jax.ShapeDtypeStruct((k, 4, 2), jnp.float32),
        corners_visible=jax.ShapeDtypeStruct((k, 4), jnp.bool_), target=jax.ShapeDtypeStruct((), jnp.int32))


def _not_found(gate_id: int) -> Detection:
    return Detection(
        found=np.bool_(False),
        centre=np.full(2, 0.5, np.float32),
        bbox=np.zeros(4, np.float32),
        corners=np.zeros((4, 2), np.float32),
        corners_visible=np.zeros(4, bool),
        gate_id=np.int32(gate_id),
    )


# --------------------------------------------------------------------------------------------------
# From geometry (JAX: jit, vmap).
# --------------------------------------------------------------------------------------------------


def _quad_overlaps_unit_square(quad: jax.Array) -> jax.Array:
    """() bool, the convex quadrilateral (4, 2) meets [0, 1]^2 (separating-axis test)."""
    square = jnp.asarray([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], quad.dtype)
    edges = jnp.roll(quad, -1, axis=0) - quad
    axes = jnp.concatenate([jnp.eye(2, dtype=quad.dtype), jnp.stack([-edges[:, 1], edges[:, 0]], -1)])
    pq, ps = quad @ axes.T, square @ axes.T  # (4, 6)
    separated = (pq.max(0) < ps.min(0)) | (ps.max(0) < pq.min(0))
    return ~jnp.any(separated)


def _sensor_noise(key: jax.Array, pixel_noise_px, dropout, uv: jax.Array, centre: jax.Array, camera):
    """The detector's noise: independent Gaussian noise of ``pixel_noise_px`` pixels (std, per axis) on the corners
    ``uv`` (4, 2) and the centre (2,), and whether the detection is kept (dropped with probability ``dropout``).
    -> (uv, centre, kept)."""
    key_corners, key_centre, key_dropout = jax.random.split(key, 3)
    sigma = jnp.asarray(pixel_noise_px, uv.dtype) / jnp.asarray([camera.width, camera.height], uv.dtype)
    uv = uv + sigma * jax.random.normal(key_corners, uv.shape, uv.dtype)
    centre = centre + sigma * jax.random.normal(key_centre, centre.shape, uv.dtype)
    return uv, centre, jax.random.uniform(key_dropout, (), uv.dtype) >= dropout


def detect_from_geometry(
    gate,
    x_robot: jax.Array,
    camera: camera_lib.Camera,
    key: jax.Array | None = None,
    pixel_noise_px: float | jax.Array = 0.0,
    dropout: float | jax.Array = 0.0,
    gate_id: int | jax.Array = -1,
) -> Detection:
    """The detection an ideal detector makes of ``gate`` (a single ``Gate``) from robot state ``x_robot``.

    Corners and centre are projected, in the image or not; with a ``key``, each gets independent Gaussian noise of
    ``pixel_noise_px`` pixels (std, per axis) and the whole detection is dropped with probability
    ``dropout``. ``found`` requires every outer frame corner in front of the camera and the projected
    frame to overlap the image (partly in view); occlusion is not modelled. Pure: jit- and vmap-able.
    """
    corners_w = gate.corners()  # (4, 3)
    outer_w = gate.outer_corners()
    uv, _, in_front = camera_lib.project(corners_w, x_robot, camera)  # (4, 2)
    uv_out, _, out_front = camera_lib.project(outer_w, x_robot, camera)
    centre, _, centre_front = camera_lib.project(gate.centre, x_robot, camera)
    found = jnp.all(out_front) & jnp.all(in_front) & centre_front & _quad_overlaps_unit_square(uv_out)
    if key is not None:
        uv, centre, kept = _sensor_noise(key, pixel_noise_px, dropout, uv, centre, camera)
        found = found & kept
    bbox = jnp.concatenate([jnp.clip(uv_out.min(0), 0.0, 1.0), jnp.clip(uv_out.max(0), 0.0, 1.0)])
    visible = in_front & camera_lib.in_image(uv) & found
    return Detection(
        found=found,
        centre=centre,
        bbox=bbox,
        corners=uv,
        corners_visible=visible,
        gate_id=jnp.asarray(gate_id, jnp.int32),
    )


NEAR_CUT_M = 0.01  # m: the frame's outline is cut this far in front of the camera before it is projected
MIN_SIDE_PX = 2.0  # px: the visible frame's box is at least this wide and high to be found (a few pixels of paint)
CORNER_MARGIN_PX = 2.0  # px: a corner is reported this far inside the image or more (as detect_from_image's)


def _clipped_box(polygon: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(box, overlaps)``: the box ``[u_min, v_min, u_max, v_max]`` (4,) of the convex polygon ``polygon`` (N, 2),
    its vertices in order (a vertex may repeat), cut to the image [0, 1]^2, and whether they overlap (the box is
    zeros where not).

    The cut is a convex polygon whose vertices are among the polygon's vertices inside the image, the image's corners
    inside the polygon, and the crossings of the polygon's edges with the image's borders: its box is theirs."""
    square = jnp.asarray([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], polygon.dtype)
    vertex_inside = jnp.all((polygon >= 0.0) & (polygon <= 1.0), axis=-1)  # (N,)
    start, edge = polygon, jnp.roll(polygon, -1, axis=0) - polygon  # (N, 2) each
    side = edge[None, :, 0] * (square[:, None, 1] - start[None, :, 1]) \
        - edge[None, :, 1] * (square[:, None, 0] - start[None, :, 0])  # (4 image corners, N edges)
    square_inside = jnp.all(side >= 0.0, axis=1) | jnp.all(side <= 0.0, axis=1)
    crossings, crossing_inside = [], []
    for axis in (0, 1):  # the borders u = 0, u = 1 (axis 0) and v = 0, v = 1 (axis 1)
        for border in (0.0, 1.0):
            run = edge[:, axis]
            safe = jnp.where(run != 0.0, run, 1.0)
            t = (border - start[:, axis]) / safe  # (N,) along each edge
            point = start + t[:, None] * edge  # (N, 2)
            other = point[:, 1 - axis]
            crossings.append(point.at[:, axis].set(border))
            crossing_inside.append((run != 0.0) & (t >= 0.0) & (t <= 1.0) & (other >= 0.0) & (other <= 1.0))
    points = jnp.concatenate([polygon, square, *crossings])  # (5 N + 4, 2)
    valid = jnp.concatenate([vertex_inside, square_inside, *crossing_inside])
    overlaps = jnp.any(valid)
    low = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
    high = jnp.max(jnp.where(valid[:, None], points, -jnp.inf), axis=0)
    return jnp.where(overlaps, jnp.concatenate([low, high]), 0.0), overlaps


def _in_front(outer: jax.Array, x_robot: jax.Array, camera: camera_lib.Camera) -> tuple[jax.Array, jax.Array]:
    """A planar convex quadrilateral ``outer`` (4, 3) (world) cut at :data:`NEAR_CUT_M` in front of the camera and
    projected: ``(polygon, any)``, the polygon (8, 2) normalised with its vertices in order (a vertex cut away
    repeats the last kept one) and whether any of it lies in front."""
    _, depth, _ = camera_lib.project(outer, x_robot, camera)
    following, depth_next = jnp.roll(outer, -1, axis=0), jnp.roll(depth, -1)
    front, front_next = depth > NEAR_CUT_M, depth_next > NEAR_CUT_M
    t = (NEAR_CUT_M - depth) / jnp.where(front != front_next, depth_next - depth, 1.0)
    cut = outer + t[:, None] * (following - outer)  # (4, 3) where each edge meets the cut
    points = jnp.stack([outer, cut], axis=1).reshape(8, 3)  # each corner, then its edge's cut
    kept = jnp.stack([front, front != front_next], axis=1).reshape(8)
    uv, _, _ = camera_lib.project(points, x_robot, camera)
    last_kept = jax.lax.cummax(jnp.where(kept, jnp.arange(8), -1))
    last_kept = jnp.where(last_kept >= 0, last_kept, jnp.max(last_kept))  # before the first kept: the cyclic last
    return uv[jnp.maximum(last_kept, 0)], jnp.any(kept)


def _frame_box(gate, x_robot: jax.Array, camera: camera_lib.Camera) -> tuple[jax.Array, jax.Array]:
    """``(box, seen)``: the box (4,) of the frame's visible part (the front and back faces of its four bars, each cut
    in front of the camera and to the image) and whether any of it is in view (the box is zeros where not). Through
    the opening, close by, only the bars in view count."""
    outer, inner = gate.outer_corners(), gate.corners()  # (4, 3) each, TL, TR, BR, BL
    bars = jnp.stack([outer, jnp.roll(outer, -1, axis=0), jnp.roll(inner, -1, axis=0), inner], axis=1)  # (4, 4, 3)
    half_depth = 0.5 * gate.depth * gate.normal
    faces = jnp.concatenate([bars - half_depth, bars + half_depth])  # (8, 4, 3)
    polygons, in_front = jax.vmap(_in_front, in_axes=(0, None, None))(faces, x_robot, camera)
    boxes, overlaps = jax.vmap(_clipped_box)(polygons)  # (8, 4), (8,)
    seen = in_front & overlaps
    low = jnp.min(jnp.where(seen[:, None], boxes[:, :2], jnp.inf), axis=0)
    high = jnp.max(jnp.where(seen[:, None], boxes[:, 2:], -jnp.inf), axis=0)
    return jnp.where(jnp.any(seen), jnp.concatenate([low, high]), 0.0), jnp.any(seen)


def stack_detections(target: Detection, following: Detection) -> Detection:
    """Two gates' detections of one tick, stacked on a new leading axis, the target's first (the estimator that
    takes two a tick: ``make_eskf(..., detections_per_tick=2)``); ``following`` cast to the target's dtypes."""
    return jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b.astype(a.dtype)]), target, following)


def detect_in_view(gate, x_robot: jax.Array, camera: camera_lib.Camera, key: jax.Array | None = None,
                   pixel_noise_px: float | jax.Array = 0.0, dropout: float | jax.Array = 0.0,
                   gate_id: int | jax.Array = -1) -> Detection:
    """What a camera's detector reports of ``gate`` from ``x_robot``: the projection cut at the image border, as
    :func:`detect_from_image` sees the rendered gate (noise and dropout as :func:`detect_from_geometry`'s).

    - found: the frame's visible part (its bars in front of the camera, cut to the image) spans at least
      :data:`MIN_SIDE_PX` both ways, a frame passed close by included;
    - corners: those in front of the camera and :data:`CORNER_MARGIN_PX` or more inside the image; a corner out of
      view is zeros and not visible;
    - centre: with every corner in view the gate centre's image; else a diagonal's two ends in view -> its midpoint;
      else the centre of the box of the frame's visible part (as a YOLO box is cut at the border);
    - bbox: the box of the frame's visible part;
    - not found: centre (0.5, 0.5), no corners, no box (nothing of the gate reaches the report).

    Where the whole gate is in view, its corners that margin inside, the report is the ideal projection's but for the
    box, which holds the frame's depth. Pure: jit- and vmap-able.
    """
    uv, _, in_front = camera_lib.project(gate.corners(), x_robot, camera)  # (4, 2)
    centre, _, _ = camera_lib.project(gate.centre, x_robot, camera)
    box, seen = _frame_box(gate, x_robot, camera)
    scale = jnp.asarray([camera.width, camera.height], uv.dtype)
    found = seen & jnp.all((box[2:] - box[:2]) * scale >= MIN_SIDE_PX)
    if key is not None:
        uv, centre, kept = _sensor_noise(key, pixel_noise_px, dropout, uv, centre, camera)
        found = found & kept
    pixels = uv * scale
    inside = jnp.all((pixels >= CORNER_MARGIN_PX) & (pixels <= scale - CORNER_MARGIN_PX), axis=-1)
    visible = in_front & inside & found
    corners = jnp.where(visible[:, None], uv, 0.0)
    centre = jnp.where(jnp.all(visible), centre,
                       jnp.where(visible[0] & visible[2], 0.5 * (corners[0] + corners[2]),
                                 jnp.where(visible[1] & visible[3], 0.5 * (corners[1] + corners[3]),
                                           0.5 * (box[:2] + box[2:]))))
    return Detection(
        found=found,
        centre=jnp.where(found, centre, 0.5).astype(uv.dtype),
        bbox=jnp.where(found, box, 0.0).astype(uv.dtype),
        corners=corners,
        corners_visible=visible,
        gate_id=jnp.asarray(gate_id, jnp.int32),
    )


# --------------------------------------------------------------------------------------------------
# From an image (numpy + OpenCV, not jit).
# --------------------------------------------------------------------------------------------------


def gate_mask(
    rgb: np.ndarray, gate_id: int, hue_tol_deg: float = 10.0, min_saturation: int = 110, min_value: int = 40
) -> np.ndarray:
    """(H, W) uint8 {0, 255}: pixels within +-``hue_tol_deg`` of gate ``gate_id``'s hue
    (``render.gate_hue``; paints are 30 deg apart), saturated and bright enough (OpenCV uint8 HSV)."""
    return paint_mask(rgb, render_lib.gate_hue(gate_id), hue_tol_deg, min_saturation, min_value)


def paint_mask(
    rgb: np.ndarray, hue: float, hue_tol_deg: float = 10.0, min_saturation: int = 110, min_value: int = 40
) -> np.ndarray:
    """(H, W) uint8 {0, 255}: pixels within +-``hue_tol_deg`` of the paint's ``hue`` (in [0, 1)), saturated and
    bright enough (OpenCV uint8 HSV)."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)  # H in [0, 180)
    hue = hue * 180.0
    dh = np.abs(hsv[..., 0].astype(np.float32) - hue)
    dh = np.minimum(dh, 180.0 - dh)
    mask = (dh <= hue_tol_deg / 2.0) & (hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)
    return mask.astype(np.uint8) * 255


def _camera_image(rgb_or_frame, camera: camera_lib.Camera | None) -> tuple[np.ndarray, int, int]:
    """An RGB image or a ``render.Frame``'s checked as the ``camera``'s (default: the paper's): the image, W, H."""
    camera = camera or camera_lib.default_camera()
    image = rgb_or_frame.rgb if isinstance(rgb_or_frame, render_lib.Frame) else rgb_or_frame
    return _check_rgb(image, (camera.height, camera.width)), camera.width, camera.height


def _check_rgb(image, shape: tuple[int, int]) -> np.ndarray:
    rgb = np.asarray(image)
    expected = f"uint8 RGB image of shape {(*shape, 3)}"
    if rgb.dtype != np.uint8:
        raise ValueError(f"the detector expects a {expected}; got dtype {rgb.dtype}")
    if rgb.shape != (*shape, 3):
        raise ValueError(f"the detector expects a {expected}; got shape {rgb.shape}")
    return np.ascontiguousarray(rgb)


def _label_corners(points: np.ndarray, reference: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Assign corner slots (0 TL, 1 TR, 2 BR, 3 BL) by direction from ``reference``; one point per slot."""
    best: dict[int, tuple[float, np.ndarray]] = {}
    for p in points:
        angle = np.arctan2(p[1] - reference[1], p[0] - reference[0])
        diff = np.abs((angle - _CORNER_ANGLES + np.pi) % (2 * np.pi) - np.pi)
        slot = int(np.argmin(diff))
        if diff[slot] < np.radians(60) and (slot not in best or diff[slot] < best[slot][0]):
            best[slot] = (float(diff[slot]), p)
    return [(slot, best[slot][1]) for slot in sorted(best)]


def _refine_quad(contour: np.ndarray, quad: np.ndarray, outward: float = 0.5) -> np.ndarray:
    """Corners (4, 2) from straight lines fitted to the contour points of each side of ``quad`` (4, 2).

    The contour runs through the centres of the opening's boundary pixels, half a pixel inside the edge,
    so every line is moved ``outward`` pixels away from the quad's centroid. Falls back to ``quad``
    where a side has too few points.
    """
    centroid = quad.mean(0)
    lines = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        ab = b - a
        length = float(np.hypot(*ab))
        if length < 3.0:
            return quad
        t = (contour - a) @ ab / length**2
        dist = np.abs((contour - a) @ np.array([-ab[1], ab[0]])) / length
        margin = min(1.5 / length, 0.2)
        near = (t > margin) & (t < 1 - margin) & (dist < 1.5)
        if near.sum() < 3:
            return quad
        vx, vy, x0, y0 = cv2.fitLine(contour[near].astype(np.float32), cv2.DIST_L2, 0, 0.01, 0.01).ravel()
        n = np.array([-vy, vx])
        point = np.array([x0, y0])
        if (point - centroid) @ n < 0:
            n = -n
        lines.append((point + outward * n, np.array([vx, vy])))
    corners = []
    for k in range(4):
        (p1, d1), (p2, d2) = lines[k - 1], lines[k]
        A = np.stack([d1, -d2], axis=1)
        if abs(np.linalg.det(A)) < 1e-6:
            return quad
        s = np.linalg.solve(A, p2 - p1)
        corners.append(p1 + s[0] * d1)
    corners = np.asarray(corners)
    if np.max(np.abs(corners - quad)) > 3.0:  # a bad fit; keep the polygon's vertices
        return quad
    return corners


def _diagonal_intersection(corners: np.ndarray) -> np.ndarray | None:
    """Crossing of TL-BR and TR-BL, (2,), or None if they are parallel."""
    tl, tr, br, bl = corners
    d1, d2 = br - tl, bl - tr
    A = np.stack([d1, -d2], axis=1)
    if abs(np.linalg.det(A)) < 1e-9:
        return None
    s = np.linalg.solve(A, tr - tl)
    return tl + s[0] * d1


def detect_from_image(
    rgb_or_frame,
    gate_id: int,
    camera: camera_lib.Camera | None = None,
    min_pixels: int = 6,
    hue_tol_deg: float = 10.0,
) -> Detection:
    """Find gate ``gate_id`` in a rendered RGB image by its paint colour.

    Segments the gate's hue, keeps the largest frame component, and takes the opening as the largest
    hole of the frame (or, when the opening runs off the image, the part of the frame's convex hull not
    covered by the frame). Opening corners come from lines fitted to its sides; a corner counts as
    visible if the outline turns there (by 20 degrees or more), it lies 2 px or more inside the image and the frame
    surrounds it on the outside.

    Centre: all 4 corners -> the diagonals' intersection (the exact image of the gate centre); a
    diagonal's two ends only -> its midpoint; otherwise the centre of the frame's box.

    Args:
        rgb_or_frame: (H, W, 3) uint8 RGB, or a ``render.Frame`` (its ``rgb``).
        gate_id: the gate's index in the track (its paint colour).
        camera: sets the expected (H, W); default the paper's 204 x 153 camera.

    Raises:
        ValueError: the image is not uint8 (H, W, 3) of the camera's size.
    """
    rgb, W, H = _camera_image(rgb_or_frame, camera)
    mask = gate_mask(rgb, gate_id, hue_tol_deg)
    if int(np.count_nonzero(mask)) < min_pixels:
        return _not_found(gate_id)
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    hierarchy = hierarchy[0]
    main, frame = _gate_frame(mask, contours, hierarchy)
    ys, xs = np.nonzero(frame)
    if len(xs) < min_pixels:
        return _not_found(gate_id)
    bbox_px = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)
    opening = _opening(mask, contours, hierarchy, main)
    corners, visible = _opening_corners(opening, mask, W, H)
    centre = _gate_centre(corners, visible, bbox_px)
    scale = np.array([W, H], np.float64)
    return Detection(
        found=np.bool_(True),
        centre=(centre / scale).astype(np.float32),
        bbox=(bbox_px / np.tile(scale, 2)).astype(np.float32),
        corners=np.where(visible[:, None], corners / scale, 0.0).astype(np.float32),
        corners_visible=visible,
        gate_id=np.int32(gate_id),
    )


def detect_candidates_from_image(
    rgb_or_frame,
    target: int,
    max_candidates: int,
    camera: camera_lib.Camera | None = None,
    hue: float = render_lib.ALIKE_HUE,
    min_pixels: int = 6,
    hue_tol_deg: float = 10.0,
) -> Candidates:
    """Every gate-like component of one paint (``hue``, the gates painted alike) in a rendered RGB image, as
    :class:`Candidates`: each 8-connected component of the paint with ``min_pixels`` or more, the largest
    ``max_candidates`` of them, largest first; each reported as :func:`detect_from_image` reports its gate (its box,
    its opening's corners, the centre from them). Which gate each shows is not known here; ``target`` (the gate the
    loop looks for) is passed on for the association.

    Raises:
        ValueError: the image is not uint8 (H, W, 3) of the camera's size.
    """
    rgb, W, H = _camera_image(rgb_or_frame, camera)
    k = int(max_candidates)
    found, centre = np.zeros(k, bool), np.full((k, 2), 0.5, np.float32)
    bbox, corners = np.zeros((k, 4), np.float32), np.zeros((k, 4, 2), np.float32)
    visible = np.zeros((k, 4), bool)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(paint_mask(rgb, hue, hue_tol_deg), connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = [1 + int(i) for i in np.argsort(-areas, kind="stable") if areas[i] >= min_pixels][:k]
    scale = np.array([W, H], np.float64)
    for slot, label in enumerate(order):
        component = (labels == label).astype(np.uint8) * 255
        box_px, slot_corners, slot_visible, slot_centre = _component_report(component, W, H)
        found[slot], centre[slot] = True, slot_centre / scale
        bbox[slot] = box_px / np.tile(scale, 2)
        corners[slot] = np.where(slot_visible[:, None], slot_corners / scale, 0.0)
        visible[slot] = slot_visible
    return Candidates(found=found, centre=centre, bbox=bbox, corners=corners, corners_visible=visible,
                      target=np.int32(target))


def _component_report(component: np.ndarray, width: int, height: int):
    """One painted component (H, W) uint8 {0, 255} as a gate: its box (4,) in pixels, its opening's corners (4, 2)
    in pixels, their visibility (4,) and the gate centre's image (2,) in pixels (:func:`detect_from_image`'s)."""
    contours, hierarchy = cv2.findContours(component, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    hierarchy = hierarchy[0]
    outers = [i for i in range(len(contours)) if hierarchy[i][3] < 0]
    main = max(outers, key=lambda i: cv2.contourArea(contours[i]) + len(contours[i]))
    ys, xs = np.nonzero(component)
    bbox_px = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)
    opening = _opening(component, contours, hierarchy, main)
    corners, visible = _opening_corners(opening, component, width, height)
    return bbox_px, corners, visible, _gate_centre(corners, visible, bbox_px)


def _gate_frame(mask: np.ndarray, contours, hierarchy: np.ndarray) -> tuple[int, np.ndarray]:
    """The main (largest) outer component's contour index, and the frame (H, W) uint8: the mask's pixels of
    every sizeable outer component (occlusion can split the frame), for the box."""
    outers = [i for i in range(len(contours)) if hierarchy[i][3] < 0]
    areas = [cv2.contourArea(contours[i]) + len(contours[i]) for i in outers]
    main = outers[int(np.argmax(areas))]
    keep = np.zeros_like(mask)
    for i in outers:
        if cv2.contourArea(contours[i]) + len(contours[i]) >= 0.1 * max(areas):
            cv2.drawContours(keep, contours, i, 255, thickness=cv2.FILLED)
    return main, cv2.bitwise_and(keep, mask)


def _opening(mask: np.ndarray, contours, hierarchy: np.ndarray, main: int) -> np.ndarray:
    """The gate's opening (H, W) uint8: the main component's largest hole, else its convex hull minus the frame."""
    holes = [i for i in range(len(contours)) if hierarchy[i][3] == main]
    opening = np.zeros_like(mask)
    if holes:
        hole = max(holes, key=lambda i: cv2.contourArea(contours[i]))
        cv2.drawContours(opening, contours, hole, 255, thickness=cv2.FILLED)
    else:
        hull = cv2.convexHull(contours[main])
        cv2.drawContours(opening, [hull], 0, 255, thickness=cv2.FILLED)
    return cv2.bitwise_and(opening, cv2.bitwise_not(mask))


def _opening_corners(opening: np.ndarray, mask: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Corners (4, 2) in pixels (TL, TR, BR, BL; zeros where not found) and their visibility (4,) bool, from
    lines fitted to the sides of the opening's largest region."""
    corners = np.zeros((4, 2))
    visible = np.zeros(4, bool)
    open_contours, _ = cv2.findContours(opening, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if open_contours:
        contour_int = max(open_contours, key=cv2.contourArea)
        # approxPolyN needs a hull of 4 or more vertices (a triangular opening has 3: no corners then)
        if cv2.contourArea(contour_int) >= 4 and len(cv2.convexHull(contour_int)) >= 4:
            contour = contour_int.reshape(-1, 2).astype(np.float64) + 0.5  # pixel centres
            quad = cv2.approxPolyN(contour_int, 4, ensure_convex=True).reshape(-1, 2).astype(np.float64) + 0.5
            if len(quad) == 4:
                quad = _refine_quad(contour, _cyclic_from_top_left(quad))
                reference = contour.mean(0)
                turning = quad[_interior_angles_deg(quad) <= _MAX_CORNER_ANGLE_DEG]
                for slot, point in _label_corners(turning, reference):
                    if _is_true_corner(point, reference, mask, width, height):
                        corners[slot], visible[slot] = point, True
    return corners, visible


def _interior_angles_deg(quad: np.ndarray) -> np.ndarray:
    """The angle (4,) in degrees between the two sides that meet at each vertex of ``quad`` (4, 2): 180 where the
    outline runs straight through it."""
    before, after = np.roll(quad, 1, axis=0) - quad, np.roll(quad, -1, axis=0) - quad
    cosine = np.sum(before * after, axis=1) / np.maximum(
        np.linalg.norm(before, axis=1) * np.linalg.norm(after, axis=1), 1e-9)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def _gate_centre(corners: np.ndarray, visible: np.ndarray, bbox_px: np.ndarray) -> np.ndarray:
    """The gate centre's image (2,) in pixels: all 4 corners -> the diagonals' intersection; a diagonal's two
    ends only -> its midpoint; otherwise (or parallel diagonals) the centre of the frame's box."""
    if visible.all():
        centre = _diagonal_intersection(corners)
    elif visible[0] and visible[2]:
        centre = 0.5 * (corners[0] + corners[2])
    elif visible[1] and visible[3]:
        centre = 0.5 * (corners[1] + corners[3])
    else:
        centre = None
    if centre is None:
        centre = 0.5 * (bbox_px[:2] + bbox_px[2:])
    return centre


def _cyclic_from_top_left(quad: np.ndarray) -> np.ndarray:
    """The 4 vertices in clockwise image order (u right, v down) starting nearest the top-left direction."""
    c = quad.mean(0)
    angle = np.arctan2(quad[:, 1] - c[1], quad[:, 0] - c[0])
    quad = quad[np.argsort(angle)]  # increasing angle = clockwise on screen
    angle = np.sort(angle)
    start = int(np.argmin(np.abs((angle - _CORNER_ANGLES[0] + np.pi) % (2 * np.pi) - np.pi)))
    return np.roll(quad, -start, axis=0)


def _is_true_corner(point, reference, mask, width, height, margin: float = 2.0, probe: float = 2.5) -> bool:
    """The corner is inside the image by ``margin`` px and frame paint lies just outside it."""
    x, y = point
    if not (margin <= x <= width - margin and margin <= y <= height - margin):
        return False
    outward = point - reference
    outward = outward / max(np.hypot(*outward), 1e-9)
    px, py = (point + probe * outward).astype(int)
    if not (0 <= px < width and 0 <= py < height):
        return False
    return bool(mask[py, px])


# --------------------------------------------------------------------------------------------------
# The geometric detector against the image detector.
# --------------------------------------------------------------------------------------------------


def image_agreement(track, states, targets, camera: camera_lib.Camera | None = None) -> dict:
    """:func:`detect_in_view` against :func:`detect_from_image` on the frames rendered at ``states`` (S, 10) as the
    loop renders them (one sample per pixel), each looking for gate ``targets[s]``.

    Returns per frame: ``found_geometry`` and ``found_image`` (S,) bool, ``partial`` (S,) bool (the geometric report
    misses a corner: the gate partly out of view) and ``centre_error_px`` (S,), the distance between the two centres
    in pixels (NaN unless both found)."""
    camera = camera or camera_lib.default_camera()
    states = jnp.asarray(states, jnp.float32)
    targets = np.asarray(targets, np.int32)
    gates = jax.tree_util.tree_map(lambda leaf: leaf[targets], track.gates)
    geometric = jax.device_get(jax.vmap(detect_in_view, in_axes=(0, 0, None))(gates, states, camera))
    render_batch = devices.compiled(render_lib.render_batch, ("supersample", "chunk"))
    frames = np.asarray(render_batch(track, states, camera, supersample=1).rgb)
    seen = [detect_from_image(frame, int(gate), camera) for frame, gate in zip(frames, targets)]
    found_image = np.asarray([bool(det.found) for det in seen])
    scale = np.asarray([camera.width, camera.height])
    centres = np.stack([np.asarray(det.centre) for det in seen])
    both = np.asarray(geometric.found) & found_image
    error = np.linalg.norm((centres - np.asarray(geometric.centre)) * scale, axis=1)
    return {"found_geometry": np.asarray(geometric.found), "found_image": found_image,
            "partial": np.asarray(geometric.found) & ~np.all(geometric.corners_visible, axis=1),
            "centre_error_px": np.where(both, error, np.nan)}
