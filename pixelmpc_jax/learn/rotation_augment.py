"""Rotation augmentation of flow training rows: the same frame pair, as if the camera had turned a little more.

A camera rotation moves every pixel by the infinite homography ``K M K^-1``, whatever the depth of the
point behind it. So a training row ``(q, w, pixel p, label flow f)`` of the flown-rate DOF (its control
input ``w`` is the rate flown over the frame interval) can be turned into an equally true row for the rate
``w'`` of the same motion followed by an extra body rotation ``exp(delta dt)``: the point seen at ``p`` lands
at ``p + f`` in the second frame, and at ``H(p + f)`` had the camera turned ``delta dt`` more, so the label is
``f' = H(p + f) - p``, exactly, with the translation's share of ``f`` (unknown depth and velocity) left as it
was. The new rate is ``w' = 2 log(exp(w dt / 2) exp(delta dt / 2)) / dt`` (= ``w + delta`` when the two are
parallel).

Why: on flown data the rates are correlated with the translational flow (the drone yaws in turns, pitches
as it speeds up), so a network fitted to ``E[flow | q, uv, w]`` learns a response to ``w`` that mixes the
rotation with what usually comes with it, 0.77 of the true rotational flow for yaw on the shipped flown
weights. Rows with ``delta`` drawn independently of everything break that correlation: the response the
network learns to ``w`` tends to the camera's true rotational flow, which is what PixelMPC asks of it (its
sampled controls differ from each other in the rates, not in the velocity). The camera intrinsics are
known (the paper's calibrated camera), and the labels stay Farneback's: the training is still self-supervised.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import camera as camera_lib


def rate_of_rotation(d: jax.Array, dt: float) -> jax.Array:
    """The body rate (3,) whose rotation over ``dt`` is the unit quaternion ``d`` (4,): ``2 log(d) / dt``,
    the shorter rotation; finite at the identity."""
    d = d * jnp.where(d[0] < 0, -1.0, 1.0)
    s = jnp.linalg.norm(d[1:])
    angle = 2.0 * jnp.arctan2(s, d[0])
    scale = jnp.where(s > 1e-9, angle / jnp.maximum(s, 1e-12), 2.0)
    return d[1:] * scale / dt


def rotation_homography(rotation_body: jax.Array, camera: camera_lib.Camera) -> jax.Array:
    """(3, 3) pixel homography ``K B R^T B^T K^-1`` of a camera whose body turned by ``rotation_body`` (3, 3):
    a pixel ``p`` (homogeneous) seen before the extra turn is seen at ``H p`` after it."""
    K = camera.K.astype(jnp.float32)
    B = camera_lib.body_to_camera(camera)
    return K @ (B @ rotation_body.T @ B.T) @ jnp.linalg.inv(K)


def augment_row(w: jax.Array, pixel_px: jax.Array, flow_px: jax.Array, delta: jax.Array,
                camera: camera_lib.Camera, dt: float) -> tuple[jax.Array, jax.Array]:
    """One row, turned by the extra body rate ``delta`` (3,) rad/s over ``dt``.

    Args:
        w: (3,) rate flown over the frame interval, rad/s (the flown-rate DOF's input).
        pixel_px: (2,) the pixel in the first frame, pixels; flow_px: (2,) its label flow, pixels per frame.

    Returns:
        ``(w', flow')``: the rate of the turned motion (3,) and the label flow (2,) of the same pixel under it.
    """
    extra = quadrotor.quat_exp(delta, dt)
    w_new = rate_of_rotation(quadrotor.quat_multiply(quadrotor.quat_exp(w, dt), extra), dt)
    H = rotation_homography(quadrotor.rotation_matrix(extra), camera)
    h = H @ jnp.concatenate([pixel_px + flow_px, jnp.ones((1,), flow_px.dtype)])
    return w_new, h[:2] / h[2] - pixel_px


def augment_batch(key: jax.Array, w: jax.Array, pixel_px: jax.Array, flow_px: jax.Array, sigma: float,
                  fraction: float, camera: camera_lib.Camera, dt: float) -> tuple[jax.Array, jax.Array]:
    """A batch of rows, each turned with probability ``fraction`` by ``delta ~ N(0, sigma^2 I)`` rad/s.

    Args:
        w: (B, 3); pixel_px, flow_px: (B, 2).

    Returns:
        ``(w', flow')``, (B, 3) and (B, 2); rows not drawn keep their values exactly.
    """
    key_delta, key_pick = jax.random.split(key)
    B = w.shape[0]
    picked = jax.random.uniform(key_pick, (B, 1)) < fraction
    delta = jnp.where(picked, sigma * jax.random.normal(key_delta, (B, 3), w.dtype), 0.0)
    w_new, flow_new = jax.vmap(augment_row, in_axes=(0, 0, 0, 0, None, None))(w, pixel_px, flow_px, delta,
                                                                                camera, dt)
    return jnp.where(picked, w_new, w), jnp.where(picked, flow_new, flow_px)


def turn_training_rows(key: jax.Array, u: jax.Array, i: jax.Array, j: jax.Array, flow_px: jax.Array,
                       config) -> tuple[jax.Array, jax.Array]:
    """Training rows (control input ``u`` (B, 4) = flown rates and thrust, pixel column ``i`` and row ``j``
    (B,), label flow (B, 2) px/frame) turned as ``config`` (a ``dof_spec.DOFConfig``: ``rotation_augment``,
    ``rotation_augment_fraction``, ``width``, ``height``, ``dt``, ``camera_tilt_deg``) says, for the dataset's camera:
    the default one at that size, tilted up as the data's was."""
    camera = camera_lib.default_camera(tilt=math.radians(config.camera_tilt_deg), wh=(config.width, config.height))
    pixel_px = jnp.stack([i + 0.5, j + 0.5], axis=-1).astype(jnp.float32)
    w, flow_px = augment_batch(key, u[:, :3], pixel_px, flow_px, config.rotation_augment,
                               config.rotation_augment_fraction, camera, config.dt)
    return jnp.concatenate([w, u[:, 3:]], axis=1), flow_px
