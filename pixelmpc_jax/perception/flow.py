"""Dense optical flow (OpenCV Farneback with the paper's parameters) and the DOF's polar flow units.

Pixel flow follows Farneback's convention: ``flow[y, x] = (dx, dy)`` pixels per frame with
``prev(y, x) ~ next(y + dy, x + dx)``. The DOF (README, "Conventions") predicts ``(l, theta)``: ``l`` the flow
magnitude in normalised image units per second and ``theta`` its angle, ``u_dot = l cos(theta)``,
``v_dot = l sin(theta)``, with ``u_dot = dx / W / dt`` and ``v_dot = dy / H / dt`` (frames at the control rate,
``timing.CONTROL_DT``).
"""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH

# The paper's Farneback parameters (Sec. IV-A), exactly.
FARNEBACK_PARAMS = dict(pyr_scale=0.5, levels=10, winsize=51, iterations=15, poly_n=5, poly_sigma=1.1, flags=0)


def _check_grey(name: str, image, shape: tuple[int, int] | None) -> np.ndarray:
    image = np.asarray(image)
    expected = f"uint8 (H, W){'' if shape is None else f' = {shape}'}"
    if image.ndim != 2:
        raise ValueError(f"{name} must be a single-channel {expected} image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must be a {expected} image, got dtype {image.dtype}")
    if shape is not None and image.shape != tuple(shape):
        raise ValueError(f"{name} must be a {expected} image, got shape {image.shape}")
    return np.ascontiguousarray(image)


def farneback(grey0, grey1, shape: tuple[int, int] | None = (PAPER_HEIGHT, PAPER_WIDTH)) -> np.ndarray:
    """Farneback flow from ``grey0`` to ``grey1`` with the paper's parameters.

    Args:
        grey0, grey1: (H, W) uint8 grey images (``Frame.grey``), the same size.
        shape: the required (H, W); default the paper's (153, 204). ``None`` accepts any equal sizes.

    Returns:
        (H, W, 2) float32 flow in pixels per frame, ``flow[y, x] = (dx, dy)``.

    Raises:
        ValueError: an image is not uint8, not 2-D, or not of the expected (H, W).
    """
    g0 = _check_grey("grey0", grey0, shape)
    g1 = _check_grey("grey1", grey1, g0.shape if shape is None else shape)
    p = FARNEBACK_PARAMS
    flow = cv2.calcOpticalFlowFarneback(
        g0,
        g1,
        None,
        p["pyr_scale"],
        p["levels"],
        p["winsize"],
        p["iterations"],
        p["poly_n"],
        p["poly_sigma"],
        p["flags"],
    )
    return flow.astype(np.float32)


def flow_to_polar(flow_px, width: int = PAPER_WIDTH, height: int = PAPER_HEIGHT, dt: float = timing.CONTROL_DT):
    """Pixel flow per frame (..., 2) -> DOF units ``(l, theta)``, each (...,).

    ``u_dot = dx / W / dt``, ``v_dot = dy / H / dt``; ``l = |(u_dot, v_dot)|`` (normalised units per
    second), ``theta = atan2(v_dot, u_dot)`` in (-pi, pi]. Works on numpy and JAX arrays, under jit; a
    half-precision flow (DOF training keeps it in float16) is computed in float32.
    """
    xp = np if isinstance(flow_px, np.ndarray) else jnp
    flow_px = xp.asarray(flow_px)
    flow_px = flow_px.astype(xp.promote_types(flow_px.dtype, xp.float32))
    u_dot = flow_px[..., 0] / (width * dt)
    v_dot = flow_px[..., 1] / (height * dt)
    return xp.hypot(u_dot, v_dot), xp.arctan2(v_dot, u_dot)


def polar_to_flow(l, theta, width: int = PAPER_WIDTH, height: int = PAPER_HEIGHT, dt: float = timing.CONTROL_DT):
    """DOF units ``(l, theta)`` (...,) -> pixel flow per frame (..., 2), the inverse of ``flow_to_polar``."""
    xp = np if isinstance(l, np.ndarray) and isinstance(theta, np.ndarray) else jnp
    dx = l * xp.cos(theta) * (width * dt)
    dy = l * xp.sin(theta) * (height * dt)
    return xp.stack([dx, dy], axis=-1)


def endpoint_error(flow_a, flow_b) -> np.ndarray:
    """(H, W) per-pixel endpoint error ``|flow_a - flow_b|`` in pixels."""
    diff = np.asarray(flow_a, np.float64) - np.asarray(flow_b, np.float64)
    return np.hypot(diff[..., 0], diff[..., 1])


def average_endpoint_error(flow_a, flow_b, mask=None) -> float:
    """Mean endpoint error in pixels over ``mask`` (H, W) bool (all pixels if None).

    Raises:
        ValueError: mismatched shapes, or an empty mask.
    """
    a, b = np.asarray(flow_a), np.asarray(flow_b)
    if a.shape != b.shape or a.shape[-1:] != (2,):
        raise ValueError(f"flows must both be (..., 2) of one shape, got {a.shape} and {b.shape}")
    epe = endpoint_error(a, b)
    if mask is None:
        return float(epe.mean())
    mask = np.asarray(mask, bool)
    if mask.shape != epe.shape:
        raise ValueError(f"mask must have shape {epe.shape}, got {mask.shape}")
    if not mask.any():
        raise ValueError("mask selects no pixels")
    return float(epe[mask].mean())


def border_mask(height: int, width: int, border: int) -> np.ndarray:
    """(H, W) bool, True except in a ``border``-pixel frame around the image."""
    mask = np.zeros((height, width), bool)
    mask[border : height - border, border : width - border] = True
    return mask


def flow_to_rgb(flow_px, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a flow field (H, W, 2): hue = direction, value = magnitude / ``max_magnitude``.

    Hue follows the image-frame angle ``atan2(dy, dx)`` (0 = right = red, 90 deg = down); full
    saturation; value saturates at ``max_magnitude`` (default the field's 99th percentile).

    Returns:
        (H, W, 3) uint8 RGB.
    """
    flow = np.asarray(flow_px, np.float32)
    mag = np.hypot(flow[..., 0], flow[..., 1])
    if max_magnitude is None:
        max_magnitude = float(np.percentile(mag, 99)) if mag.size else 1.0
    max_magnitude = max(float(max_magnitude), 1e-6)
    angle = np.degrees(np.arctan2(flow[..., 1], flow[..., 0])) % 360.0
    hsv = np.stack([angle / 2.0, np.full_like(mag, 255.0), np.clip(mag / max_magnitude, 0.0, 1.0) * 255.0], axis=-1)
    return cv2.cvtColor(np.round(hsv).astype(np.uint8), cv2.COLOR_HSV2RGB)


def colour_wheel(size: int = 101) -> np.ndarray:
    """(size, size, 3) uint8 RGB legend for ``flow_to_rgb``: the flow at each pixel is its offset from
    the centre, scaled so the rim has magnitude 1 (``max_magnitude = 1``); black outside the disc."""
    r = (np.arange(size) + 0.5 - size / 2) / (size / 2)
    dx, dy = np.meshgrid(r, r)
    rgb = flow_to_rgb(np.stack([dx, dy], axis=-1), max_magnitude=1.0)
    rgb[np.hypot(dx, dy) > 1.0] = 0
    return rgb
