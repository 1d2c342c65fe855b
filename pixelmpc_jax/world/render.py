"""A ray-caster for the race hall: RGB, grey, depth and gate-id images, and the exact optical flow.

The scene is the track's closed hall (an axis-aligned box: floor, four walls, ceiling, seen from the
inside) and its gates. A gate's frame is the ring between the inner opening (``width`` x ``height``)
and the outer rectangle (``border`` wider on every side), a slab ``depth`` thick along the gate normal.
Every ray is intersected with the hall box (exit distance) and with every gate (outer box minus the
through-hole); the nearest hit wins.

Surfaces carry procedural value-noise textures in their own surface coordinates (world metres for the
hall, gate-local metres for the frames): nine octaves from 4 m down to 1.6 cm wavelength, each octave
faded out once its wavelength falls below ~3 pixel footprints at the hit (so the texture is
band-limited before sampling), then the image is supersampled ``s x s`` and box-filtered. That keeps the
images rich at every scale Farneback's pyramid looks at and keeps brightness constant between frames.
By default gate ``g`` has its own hue (``gate_colour``) so a colour detector can tell gates apart; with the
"alike" paint (:data:`GATE_PAINTS`, :func:`gate_palette`) every gate wears one paint, :data:`ALIKE_HUE`, as racing
gates do, and telling them apart is the estimator's job. The hall is nearly grey.

Everything is a pure function of one pose, vmapped over (sub)pixels; ``render_batch`` maps it over a
batch of poses. The gate loop is a ``lax.scan`` (memory O(rays), not O(rays x gates)).

Nothing here compiles itself: inside a closed loop the episode's jit traces :func:`render` (the image detector), and
a caller that renders at the top level compiles through :func:`pixelmpc_jax.devices.compiled`, one compiled function
per static argument set (``devices.compiled(render_batch, ("supersample", "chunk"))``, ``devices.compiled(render,
("supersample",))``, ``devices.compiled(exact_flow)``): called op by op it would run a frame far slower.
"""

from __future__ import annotations

import colorsys
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import camera as camera_lib

_INF = 1e9
_RAY_TILE = 4096  # rays shaded per vectorised tile (cache-sized on a CPU)
_TINY = 1e-9
# Octave wavelengths, metres (coarse to fine) and their relative amplitudes.
_WAVELENGTHS = tuple(4.0 * 0.5**k for k in range(9))
_AMPLITUDES = tuple(0.8**k for k in range(9))
# Fade an octave from 0 at FADE_LO pixel footprints per wavelength to 1 at FADE_HI.
_FADE_LO, _FADE_HI = 1.5, 3.0
_TEXTURE_GAIN = 2.2
# A fixed directional light (world frame) for flat Lambert shading; static, so brightness is constant.
_LIGHT = np.asarray([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
# Hall faces, indexed 2 * axis + (ray direction > 0): -x wall, +x wall, -y wall, +y wall, floor, ceiling.
_HALL_BASE = np.asarray(
    [
        [0.62, 0.60, 0.57],
        [0.58, 0.60, 0.62],
        [0.60, 0.58, 0.60],
        [0.57, 0.61, 0.58],
        [0.55, 0.53, 0.50],
        [0.66, 0.66, 0.66],
    ]
)
GATE_SATURATION = 0.85
NUM_GATE_HUES = 12  # 30 deg apart; gate g and g + 12 share a paint
# How the gates are painted: "hues", each gate its own hue (gate_hue); "alike", every gate the one paint ALIKE_HUE.
GATE_PAINTS = ("hues", "alike")
ALIKE_HUE = 1.0 / NUM_GATE_HUES  # orange (30 deg), one of the 12 hues, far from the nearly grey hall


def gate_hue(gate_id: int) -> float:
    """Hue in [0, 1) of gate ``gate_id``'s paint: one of 12 hues 30 deg apart, consecutive gates 150 deg
    apart (``5 g mod 12`` steps of 30 deg), so gates seen together are easy to tell apart."""
    return float(((5 * int(gate_id)) % NUM_GATE_HUES) / NUM_GATE_HUES)


def gate_colour(gate_id: int) -> np.ndarray:
    """(3,) RGB in [0, 1] of gate ``gate_id``'s paint at full brightness."""
    return np.asarray(colorsys.hsv_to_rgb(gate_hue(gate_id), GATE_SATURATION, 1.0))


def gate_palette(num_gates: int, paint: str = "hues") -> np.ndarray:
    """(G, 3) RGB in [0, 1], each gate's paint: its own hue (``paint="hues"``, :func:`gate_colour`) or, with
    ``paint="alike"``, :data:`ALIKE_HUE` for every gate (:data:`GATE_PAINTS`)."""
    if paint not in GATE_PAINTS:
        raise ValueError(f"paint must be one of {', '.join(GATE_PAINTS)}, got {paint!r}")
    if not num_gates:
        return np.zeros((0, 3))
    if paint == "alike":
        return np.tile(np.asarray(colorsys.hsv_to_rgb(ALIKE_HUE, GATE_SATURATION, 1.0)), (num_gates, 1))
    return np.stack([gate_colour(g) for g in range(num_gates)])


@struct.dataclass
class Frame:
    """One rendered image at ``camera.width`` x ``camera.height`` (H, W), or a batch with leading axes.

    Attributes:
        rgb: (H, W, 3) uint8.
        grey: (H, W) uint8, ``0.299 R + 0.587 G + 0.114 B`` of the anti-aliased colour.
        depth: (H, W) float32, metres along the optical axis (camera z) at the pixel centre.
        gate_id: (H, W) int32, index of the gate seen at the pixel centre, -1 for the hall.
    """

    rgb: jax.Array
    grey: jax.Array
    depth: jax.Array
    gate_id: jax.Array


# --------------------------------------------------------------------------------------------------
# Procedural texture.
# --------------------------------------------------------------------------------------------------


def _hash_uniform(ix: jax.Array, iy: jax.Array, seed: jax.Array) -> jax.Array:
    """Uniform [0, 1) from integer lattice coordinates and a seed (a 32-bit integer mix, deterministic)."""
    u32 = jnp.uint32
    h = (
        jax.lax.bitcast_convert_type(ix.astype(jnp.int32), u32) * u32(0x8DA6B343)
        ^ jax.lax.bitcast_convert_type(iy.astype(jnp.int32), u32) * u32(0xD8163841)
        ^ (seed.astype(u32) + u32(1)) * u32(0xCB1AB31F)
    )
    h = h ^ (h >> 16)
    h = h * u32(0x7FEB352D)
    h = h ^ (h >> 15)
    h = h * u32(0x846CA68B)
    h = h ^ (h >> 16)
    return (h >> 8).astype(jnp.float32) * (1.0 / 16777216.0)


def _value_noise(a: jax.Array, b: jax.Array, seed: jax.Array) -> jax.Array:
    """Smooth (C1, quintic-faded) value noise on the unit lattice, in [0, 1]."""
    fa, fb = jnp.floor(a), jnp.floor(b)
    ta, tb = a - fa, b - fb
    wa = ta * ta * ta * (ta * (ta * 6.0 - 15.0) + 10.0)
    wb = tb * tb * tb * (tb * (tb * 6.0 - 15.0) + 10.0)
    ia, ib = fa.astype(jnp.int32), fb.astype(jnp.int32)
    n00 = _hash_uniform(ia, ib, seed)
    n10 = _hash_uniform(ia + 1, ib, seed)
    n01 = _hash_uniform(ia, ib + 1, seed)
    n11 = _hash_uniform(ia + 1, ib + 1, seed)
    return (n00 * (1 - wa) + n10 * wa) * (1 - wb) + (n01 * (1 - wa) + n11 * wa) * wb


def surface_texture(a: jax.Array, b: jax.Array, footprint: jax.Array, material: jax.Array) -> jax.Array:
    """Band-limited multi-octave texture in [0, 1] at surface coordinates ``(a, b)`` (metres).

    Octave k (wavelength ``lambda_k``) is faded towards its mean 0.5 as ``lambda_k / footprint`` drops
    from 3 to 1.5 pixels, so nothing finer than the pixel grid is ever sampled. Each octave's lattice is
    rotated and offset differently (no axis-aligned artefacts), and each material has its own seed.
    """
    total = 0.0
    for k, (lam, amp) in enumerate(zip(_WAVELENGTHS, _AMPLITUDES, strict=True)):
        angle = 0.7 + 1.3 * k
        c, s = np.cos(angle), np.sin(angle)
        ra = (c * a - s * b) / lam + 17.31 * k
        rb = (s * a + c * b) / lam - 9.17 * k
        n = _value_noise(ra, rb, material * 16 + k)
        x = (lam / footprint - _FADE_LO) / (_FADE_HI - _FADE_LO)
        x = jnp.clip(x, 0.0, 1.0)
        fade = x * x * (3.0 - 2.0 * x)
        total = total + amp * fade * (n - 0.5)
    total = total / sum(_AMPLITUDES)
    return jnp.clip(0.5 + _TEXTURE_GAIN * total, 0.0, 1.0)


# --------------------------------------------------------------------------------------------------
# Geometry.
# --------------------------------------------------------------------------------------------------


def _safe_dir(d: jax.Array) -> jax.Array:
    """Direction components bounded away from zero, sign kept (so 1/d is finite)."""
    return jnp.where(d >= 0, jnp.maximum(d, _TINY), jnp.minimum(d, -_TINY))


def _gate_arrays(gates, dtype=jnp.float32):
    """Per-gate centre (G, 3), rotation (G, 3, 3), outer half-extents (G, 3), inner half-extents (G, 2)."""
    centre = jnp.asarray(gates.centre, dtype).reshape(-1, 3)
    num = centre.shape[0]
    rotation = jnp.broadcast_to(jnp.asarray(gates.rotation, dtype), (num, 3, 3))

    def per_gate(v):
        return jnp.broadcast_to(jnp.asarray(v, dtype), (num,))

    width, height = per_gate(gates.width), per_gate(gates.height)
    border, depth = per_gate(gates.border), per_gate(gates.depth)
    half_out = jnp.stack([0.5 * depth, 0.5 * width + border, 0.5 * height + border], axis=-1)
    half_in = jnp.stack([0.5 * width, 0.5 * height], axis=-1)
    return centre, rotation, half_out, half_in


def _hit_hall(origin, d, hall_min, hall_max):
    """Exit of a ray from inside the hall box. Returns t, face (0..5, 2*axis + (d > 0))."""
    ds = _safe_dir(d)
    bound = jnp.where(ds > 0, hall_max, hall_min)
    t_axes = (bound - origin) / ds  # (3,)
    axis = jnp.argmin(t_axes)
    t = t_axes[axis]
    face = 2 * axis + (ds[axis] > 0).astype(jnp.int32)
    return t, face


def _hit_gate(origin_local, d_local, half_out, half_in):
    """First hit of a ray with one gate frame (outer box minus through-hole), gate-local frame.

    Returns:
        t: distance along the ray (same parameter as the world ray), ``_INF`` if missed.
        axis: local axis of the face normal hit (0 normal, 1 lateral, 2 up).
    """
    ds = _safe_dir(d_local)
    t1 = (-half_out - origin_local) / ds
    t2 = (half_out - origin_local) / ds
    t_lo, t_hi = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
    enter_axis = jnp.argmax(t_lo)
    t_enter, t_exit = t_lo[enter_axis], jnp.min(t_hi)
    box_hit = (t_enter < t_exit) & (t_exit > 0)
    t_start = jnp.maximum(t_enter, 0.0)
    p = origin_local + t_start * ds
    in_hole = (jnp.abs(p[1]) < half_in[0]) & (jnp.abs(p[2]) < half_in[1])
    # Inside the hole the ray leaves the hole's prism through one of its four inner walls.
    bound = jnp.where(ds[1:] > 0, half_in, -half_in)
    t_walls = (bound - origin_local[1:]) / ds[1:]
    wall = jnp.argmin(t_walls)
    t_wall = t_walls[wall]
    wall_hit = in_hole & (t_wall < t_exit)
    t = jnp.where(in_hole, t_wall, t_start)
    axis = jnp.where(in_hole, wall + 1, enter_axis)
    hit = box_hit & (~in_hole | wall_hit)
    return jnp.where(hit, t, _INF), axis


def _shade(normal_world: jax.Array) -> jax.Array:
    return 0.6 + 0.4 * jnp.abs(normal_world @ jnp.asarray(_LIGHT, normal_world.dtype))


def _cast(origin, d, hall_min, hall_max, gate_origin_local, gate_rotation, half_out, half_in, palette, f):
    """Shade one ray (world direction ``d``, any length; t is measured in units of ``d``).

    Returns (rgb (3,) in [0, 1], t, gate index or -1).
    """
    t_hall, face = _hit_hall(origin, d, hall_min, hall_max)

    def gate_step(best, gate):
        o_l, rot, h_out, h_in = gate
        d_l = rot.T @ d
        t, axis = _hit_gate(o_l, d_l, h_out, h_in)
        t_best, g_best, axis_best, index = best
        closer = t < t_best
        best = (
            jnp.where(closer, t, t_best),
            jnp.where(closer, index, g_best),
            jnp.where(closer, axis, axis_best),
            index + 1,
        )
        return best, None

    init = (jnp.asarray(_INF, d.dtype), jnp.int32(-1), jnp.int32(0), jnp.int32(0))
    if gate_rotation.shape[0] > 0:
        (t_gate, g, g_axis, _), _ = jax.lax.scan(gate_step, init, (gate_origin_local, gate_rotation, half_out, half_in))
    else:
        t_gate, g, g_axis = init[0], init[1], init[2]
    on_gate = t_gate < t_hall
    t = jnp.where(on_gate, t_gate, t_hall)
    gate_index = jnp.where(on_gate, g, -1)

    # Surface frame of the hit: world axes for the hall, the gate's axes for a frame.
    g_safe = jnp.maximum(g, 0)
    if gate_rotation.shape[0] > 0:
        rot = jnp.where(on_gate, gate_rotation[g_safe], jnp.eye(3, dtype=d.dtype))
        o_l = jnp.where(on_gate, gate_origin_local[g_safe], origin)
        base = jnp.where(on_gate, palette[g_safe], jnp.asarray(_HALL_BASE, d.dtype)[face])
    else:
        rot, o_l = jnp.eye(3, dtype=d.dtype), origin
        base = jnp.asarray(_HALL_BASE, d.dtype)[face]
    axis = jnp.where(on_gate, g_axis, face // 2)
    d_l = rot.T @ d
    p_l = o_l + t * d_l
    a = jnp.take(p_l, (axis + 1) % 3)
    b = jnp.take(p_l, (axis + 2) % 3)
    material = jnp.where(on_gate, 6 + g_safe, face)
    normal_world = rot[:, axis] * -jnp.sign(jnp.take(d_l, axis))
    d_norm = jnp.sqrt(jnp.sum(d * d))
    cos_incidence = jnp.abs(jnp.take(d_l, axis)) / d_norm
    footprint = t * d_norm / f / jnp.maximum(cos_incidence, 0.15)
    tex = surface_texture(a, b, footprint, material)
    brightness = jnp.where(on_gate, 0.45 + 0.55 * tex, 0.15 + 0.85 * tex)
    rgb = base * brightness * _shade(normal_world)
    return jnp.clip(rgb, 0.0, 1.0), t, gate_index


# --------------------------------------------------------------------------------------------------
# Public API.
# --------------------------------------------------------------------------------------------------


def render(track, x_robot: jax.Array, camera: camera_lib.Camera, supersample: int = 3,
           palette: jax.Array | None = None) -> Frame:
    """Render one frame of ``track`` from robot state ``x_robot`` (10,).

    Args:
        track: a ``Track`` (uses ``gates``, ``hall_min``, ``hall_max``).
        x_robot: (10,) robot state; only position and attitude are used.
        camera: intrinsics and mount; the image is ``camera.height`` x ``camera.width``.
        supersample: odd sub-samples per pixel side (3 -> 3 x 3 box-filtered; 1 -> none; static under jit). Depth and
            gate id are those of the centre sub-sample, i.e. of the ray through the pixel centre.
        palette: (G, 3) RGB in [0, 1], each gate's paint (:func:`gate_palette`); None: each gate its own hue.

    Returns:
        Frame with rgb (H, W, 3) uint8, grey (H, W) uint8, depth (H, W) float32 m, gate_id (H, W) int32.
    """
    s = int(supersample)
    if s < 1 or s % 2 == 0:
        raise ValueError(f"supersample must be an odd positive integer (1, 3, 5, ...), got {supersample}")
    dtype = jnp.float32
    H, W = camera.height, camera.width
    R, origin = camera_lib.world_to_camera(jnp.asarray(x_robot, dtype), camera)
    origin = origin.astype(dtype)
    rays_cam = camera_lib.pixel_rays_camera(camera, s).astype(dtype)  # (H*s, W*s, 3)
    rays_world = rays_cam.reshape(-1, 3) @ R.astype(dtype)  # rows R^T d

    centre, rotation, half_out, half_in = _gate_arrays(track.gates, dtype)
    gate_origin_local = jnp.einsum("gji,gj->gi", rotation, origin[None, :] - centre)  # (G, 3)
    palette = jnp.asarray(gate_palette(centre.shape[0]) if palette is None else palette, dtype)
    hall_min = jnp.asarray(track.hall_min, dtype)
    hall_max = jnp.asarray(track.hall_max, dtype)
    f = jnp.sqrt(jnp.asarray(camera.fx, dtype) * jnp.asarray(camera.fy, dtype))

    cast = partial(
        _cast,
        origin,
        hall_min=hall_min,
        hall_max=hall_max,
        gate_origin_local=gate_origin_local,
        gate_rotation=rotation,
        half_out=half_out,
        half_in=half_in,
        palette=palette,
        f=f,
    )
    # Shade in cache-sized tiles: vmap within a tile, a loop over tiles (memory O(tile), not O(rays)).
    num_rays = rays_world.shape[0]
    tile = min(_RAY_TILE, num_rays)
    padded = -(-num_rays // tile) * tile
    rays_world = jnp.pad(rays_world, ((0, padded - num_rays), (0, 0)), constant_values=1.0)
    rgb, t, gate_index = jax.lax.map(cast, rays_world, batch_size=tile)
    rgb, t, gate_index = rgb[:num_rays], t[:num_rays], gate_index[:num_rays]
    rgb = rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3))
    c = s // 2
    depth = t.reshape(H, s, W, s)[:, c, :, c]  # rays have unit camera z, so t is the depth
    gate_id = gate_index.reshape(H, s, W, s)[:, c, :, c].astype(jnp.int32)
    rgb255 = rgb * 255.0
    grey = rgb255 @ jnp.asarray([0.299, 0.587, 0.114], dtype)
    return Frame(
        rgb=jnp.clip(jnp.round(rgb255), 0, 255).astype(jnp.uint8),
        grey=jnp.clip(jnp.round(grey), 0, 255).astype(jnp.uint8),
        depth=depth,
        gate_id=gate_id,
    )


def render_batch(
    track, x_robots: jax.Array, camera: camera_lib.Camera, supersample: int = 3, chunk: int | None = 4,
    palette: jax.Array | None = None
) -> Frame:
    """Render a batch of poses ``x_robots`` (B, 10) -> Frame with a leading B axis (``palette``: :func:`render`'s).

    ``chunk`` poses are vmapped at a time (``lax.map``'s batch size; each frame is already vectorised
    over ray tiles, so 1 is fastest on a CPU; larger chunks suit an accelerator); ``None`` vmaps all.
    """
    x_robots = jnp.asarray(x_robots)
    if x_robots.ndim != 2 or x_robots.shape[-1] != 10:
        raise ValueError(f"x_robots must have shape (B, 10), got {x_robots.shape}")

    def one(x):
        return render(track, x, camera, supersample=supersample, palette=palette)

    if chunk is None:
        return jax.vmap(one)(x_robots)
    if int(chunk) <= 1:
        return jax.lax.map(one, x_robots)
    return jax.lax.map(one, x_robots, batch_size=min(int(chunk), x_robots.shape[0]))


def exact_flow(x_t: jax.Array, x_t1: jax.Array, depth_t: jax.Array, camera: camera_lib.Camera):
    """True optical flow of the static scene from pose ``x_t`` to pose ``x_t1``.

    Each pixel centre is back-projected with its depth at ``x_t`` and re-projected at ``x_t1``.
    Farneback's convention: ``flow[y, x] = (dx, dy)`` with ``prev(y, x) ~ next(y + dy, x + dx)``.

    Args:
        x_t, x_t1: (10,) robot states of the two frames.
        depth_t: (H, W) depth along the optical axis at ``x_t`` (``Frame.depth``), m.
        camera: intrinsics and mount.

    Returns:
        flow: (H, W, 2) float32, pixels (zero where not valid).
        valid: (H, W) bool, the point is in front of the camera and inside the image at ``x_t1``.
    """
    depth_t = jnp.asarray(depth_t, jnp.float32)
    H, W = depth_t.shape
    uu, vv = jnp.meshgrid(jnp.arange(W, dtype=jnp.float32) + 0.5, jnp.arange(H, dtype=jnp.float32) + 0.5)
    px0 = jnp.stack([uu, vv], axis=-1)  # (H, W, 2)
    points = camera_lib.backproject(px0, depth_t, jnp.asarray(x_t, jnp.float32), camera)
    uv1, _, in_front = camera_lib.project(points, jnp.asarray(x_t1, jnp.float32), camera)
    px1 = uv1 * jnp.asarray([W, H], jnp.float32)
    valid = in_front & camera_lib.in_image(uv1) & jnp.isfinite(depth_t) & (depth_t > 0)
    flow = jnp.where(valid[..., None], px1 - px0, 0.0)
    return flow.astype(jnp.float32), valid


# --------------------------------------------------------------------------------------------------
# Poses for rendered pairs (tests, figures, benchmarks, data collection).
# --------------------------------------------------------------------------------------------------


def pose_before_gate(
    gate,
    distance: float,
    lateral: float = 0.0,
    height: float = 0.0,
    yaw_offset: float = 0.0,
    roll: float = 0.0,
    pitch: float = 0.0,
) -> jax.Array:
    """(10,) state at rest ``distance`` m before a single ``gate`` along its normal, offset ``lateral``
    m along its lateral axis (left) and ``height`` m up, heading along the normal plus ``yaw_offset``,
    with ``roll`` and ``pitch`` (rad, Z-Y-X Euler)."""
    normal, lateral_axis = jnp.asarray(gate.normal, jnp.float32), jnp.asarray(gate.lateral, jnp.float32)
    position = (
        jnp.asarray(gate.centre, jnp.float32)
        - distance * normal
        + lateral * lateral_axis
        + jnp.asarray([0.0, 0.0, height], jnp.float32)
    )
    yaw = jnp.arctan2(normal[1], normal[0]) + yaw_offset
    q = quadrotor.quat_from_euler(jnp.float32(roll), jnp.float32(pitch), yaw)
    return jnp.concatenate([position, q, jnp.zeros(3, jnp.float32)])


def advance_pose(x_robot: jax.Array, dt: float, speed: float = 0.0, body_rates=(0.0, 0.0, 0.0)) -> jax.Array:
    """The pose ``dt`` s later flying ``speed`` m/s along body x with constant body ``rates`` (rad/s).

    Translation first (along the initial heading), then the exact rotation ``q * exp(w dt / 2)``.
    """
    x = jnp.asarray(x_robot, jnp.float32)
    q = quadrotor.normalize_quat(x[quadrotor.QUAT])
    rates = jnp.asarray(body_rates, jnp.float32)
    position = x[quadrotor.POS] + quadrotor.rotation_matrix(q)[:, 0] * speed * dt
    q_next = quadrotor.normalize_quat(quadrotor.quat_multiply(q, quadrotor.quat_exp(rates, dt)))
    return x.at[quadrotor.POS].set(position).at[quadrotor.QUAT].set(q_next)
