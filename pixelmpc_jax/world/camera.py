"""The onboard pinhole camera: intrinsics, mount, projection.

Conventions (README, "Conventions"): the camera sits at the body origin with its optical axis along body +x
(optionally tilted up by a fixed angle); image u grows to the right, v downwards, origin top-left.
Image coordinates are continuous: pixel (i, j) covers [i, i+1) x [j, j+1) and its centre is
(i + 0.5, j + 0.5). Normalised coordinates are ``uv = (u_px / W, v_px / H)``; the image centre is
(0.5, 0.5).

Camera frame (OpenCV): x right, y down, z forward. In the body frame (x forward, y left, z up) with no
tilt: camera x = -body y, camera y = -body z, camera z = body x.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax.dynamics import quadrotor

PAPER_WIDTH = 204
PAPER_HEIGHT = 153
_NEAR = 1e-3


@struct.dataclass
class Camera:
    """Pinhole intrinsics (pixels, at ``width`` x ``height``) and the mount's upward tilt (rad).

    ``width`` and ``height`` are static (they set array shapes); the rest are pytree leaves.
    """

    fx: float | jax.Array
    fy: float | jax.Array
    cx: float | jax.Array
    cy: float | jax.Array
    tilt: float | jax.Array = 0.0
    width: int = struct.field(pytree_node=False, default=PAPER_WIDTH)
    height: int = struct.field(pytree_node=False, default=PAPER_HEIGHT)

    @property
    def K(self) -> jax.Array:
        """(3, 3) intrinsic matrix in pixels."""
        return jnp.asarray([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def scaled_camera(
    K_full, full_wh=(1024, 768), wh=(PAPER_WIDTH, PAPER_HEIGHT), tilt: float = 0.0
) -> Camera:
    """Scale a full-resolution K to ``wh`` (fx, cx by W'/W; fy, cy by H'/H)."""
    sx = wh[0] / full_wh[0]
    sy = wh[1] / full_wh[1]
    return Camera(
        fx=float(K_full[0][0]) * sx,
        fy=float(K_full[1][1]) * sy,
        cx=float(K_full[0][2]) * sx,
        cy=float(K_full[1][2]) * sy,
        tilt=float(tilt),
        width=int(wh[0]),
        height=int(wh[1]),
    )


def default_camera(tilt: float = 0.0, wh=(PAPER_WIDTH, PAPER_HEIGHT)) -> Camera:
    """The AlphaPilot camera (packaged course file) scaled to the paper's 204 x 153 images."""
    data = json.loads((Path(__file__).resolve().parent.parent / "data" / "alphapilot_course.json").read_text())
    cam = data["camera"]
    return scaled_camera(cam["K"], tuple(cam["image_size_wh"]), wh, tilt)


def body_to_camera(camera: Camera) -> jax.Array:
    """(3, 3) matrix taking body-frame vectors to camera-frame vectors (x right, y down, z forward)."""
    t = jnp.asarray(camera.tilt, dtype=jnp.float32)
    c, s = jnp.cos(t), jnp.sin(t)
    zero, one = jnp.zeros_like(t), jnp.ones_like(t)
    right = jnp.stack([zero, -one, zero])  # camera x in body
    down = jnp.stack([s, zero, -c])  # camera y in body
    forward = jnp.stack([c, zero, s])  # camera z in body
    return jnp.stack([right, down, forward])


def world_to_camera(x_robot: jax.Array, camera: Camera) -> tuple[jax.Array, jax.Array]:
    """Rotation (3, 3) and camera position (3,) such that ``p_cam = R @ (p_world - position)``."""
    q = quadrotor.normalize_quat(x_robot[quadrotor.QUAT])
    R_wb = quadrotor.rotation_matrix(q)  # body -> world
    R = body_to_camera(camera).astype(R_wb.dtype) @ R_wb.T
    return R, x_robot[quadrotor.POS]


def project(points_world: jax.Array, x_robot: jax.Array, camera: Camera):
    """Project world points into the image.

    Args:
        points_world: (..., 3) points, world frame.
        x_robot: (10,) robot state (only position and attitude are used; q is renormalised).
        camera: intrinsics and mount.

    Returns:
        uv: (..., 2) normalised image coordinates (finite even for points behind the camera).
        depth: (...,) distance along the optical axis (camera z), m; negative behind the camera.
        in_front: (...,) bool, depth above a small near plane.
    """
    R, position = world_to_camera(x_robot, camera)
    p_cam = (points_world - position) @ R.T  # (..., 3)
    depth = p_cam[..., 2]
    in_front = depth > _NEAR
    z = jnp.where(in_front, depth, 1.0)
    u_px = camera.fx * p_cam[..., 0] / z + camera.cx
    v_px = camera.fy * p_cam[..., 1] / z + camera.cy
    uv = jnp.stack([u_px / camera.width, v_px / camera.height], axis=-1)
    return uv, depth, in_front


def in_image(uv: jax.Array) -> jax.Array:
    """(...,) bool: normalised coordinates inside [0, 1] x [0, 1]."""
    return jnp.all((uv >= 0.0) & (uv <= 1.0), axis=-1)


def pixel_rays_camera(camera: Camera, supersample: int = 1) -> jax.Array:
    """Unit-z ray directions in the camera frame through every (sub)pixel centre.

    Returns:
        (H * s, W * s, 3) directions ``[(u - cx)/fx, (v - cy)/fy, 1]`` for sub-pixel centres, s the
        supersampling factor (row-major: v then u).
    """
    s = int(supersample)
    u = (jnp.arange(camera.width * s) + 0.5) / s
    v = (jnp.arange(camera.height * s) + 0.5) / s
    uu, vv = jnp.meshgrid(u, v)  # (H*s, W*s)
    x = (uu - camera.cx) / camera.fx
    y = (vv - camera.cy) / camera.fy
    return jnp.stack([x, y, jnp.ones_like(x)], axis=-1)


def backproject(uv_px: jax.Array, depth: jax.Array, x_robot: jax.Array, camera: Camera) -> jax.Array:
    """World points (..., 3) from pixel coordinates (..., 2) in pixels and depth along the optical axis."""
    R, position = world_to_camera(x_robot, camera)
    x = (uv_px[..., 0] - camera.cx) / camera.fx * depth
    y = (uv_px[..., 1] - camera.cy) / camera.fy * depth
    p_cam = jnp.stack([x, y, depth], axis=-1)
    return p_cam @ R + position


# --------------------------------------------------------------------------------------------------
# Gate visibility (the paper's visibility counts: the fraction of a gate seen by the camera).
# --------------------------------------------------------------------------------------------------


def gate_outline_points(gate, n_per_side: int = 16) -> jax.Array:
    """Points evenly spaced on the outline of a gate's inner opening.

    Args:
        gate: a ``world.track.Gate``, single or batched (leading axes ``...``).
        n_per_side: points per side; each side starts at its corner (top-left, top-right, bottom-right,
            bottom-left as seen along the normal) and stops before the next.

    Returns:
        (..., 4 * n_per_side, 3) world points.
    """
    corners = gate.corners()  # (..., 4, 3)
    following = jnp.roll(corners, -1, axis=-2)
    frac = jnp.arange(n_per_side, dtype=corners.dtype) / n_per_side
    frac = frac.reshape((1,) * (corners.ndim - 1) + (n_per_side, 1))  # (..., 1, n, 1)
    points = corners[..., :, None, :] + frac * (following - corners)[..., :, None, :]  # (..., 4, n, 3)
    return points.reshape(*points.shape[:-3], 4 * n_per_side, 3)


def gate_visibility(gate, x_robot: jax.Array, camera: Camera, n_per_side: int = 16) -> jax.Array:
    """Fraction in [0, 1] of a gate's opening outline that projects into the image, in front of the camera.

    Occlusion is not modelled. A single gate gives (); a batch of gates (...,).
    """
    points = gate_outline_points(gate, n_per_side)
    uv, _, in_front = project(points, x_robot, camera)
    seen = in_front & in_image(uv)
    return jnp.mean(seen.astype(jnp.float32), axis=-1)
