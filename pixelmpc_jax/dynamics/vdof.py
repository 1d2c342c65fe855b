"""Velocity-and-depth DOF ("vdof"): a learned pixel model shaped like the interaction matrix.

The paper's DOF (:mod:`pixelmpc_jax.dynamics.dof`) maps ``(q, uv, u)`` to the target pixel's flow; it has
neither the camera's velocity nor the target's depth, which set the translational part of the flow. The
paper's conclusion names the fix: the target's depth and the robot's velocity as inputs, and propagating the
target's box. Here the pixel state is ``p = [u, v, s]`` (3,): the target's normalised pixel and a depth cue a
monocular drone has, the detected gate's apparent size ``s`` (:func:`box_size`, about ``k / Z`` for a gate at
depth ``Z``). Image motion of a point is ``uv_dot = (1/Z) A(uv) v_cam + B(uv) w_cam`` (visual servoing's
interaction matrix), and ``Z_dot / Z`` is linear in ``v / Z`` and ``w`` too, so the model is

    uv_dot = s A(uv) v_b + B(uv) w,        s_dot = s (s a(uv) . v_b + b(uv) . w),

``v_b = R(q)^T v`` the body-frame velocity, ``w = u[:3]`` the body rates, and ``g(uv) -> (A (2, 3), B (2, 3),
a (3,), b (3,))`` a small MLP of the pixel alone (:func:`interaction`). The learned scale of ``s`` absorbs the
gate's size and the focal length: the model never sees the gate's 3-D position or the camera intrinsics.
At zero velocity and zero rate the pixel state does not move, by construction. One scale fits gates of one
size; the AlphaPilot openings are 1.8 m and 3.0 m wide, so weights may be trained with ``s`` divided by the
target opening's ``sqrt(width * height)`` (a course fact, not a position): :func:`box_cue_of` reads which from
a checkpoint's record, and :func:`initial_pixel_state` takes the divisor as ``gate_size``.

Every quantity enters normalised (``VDOFParams``'s constants, set from the training rows); the box size is
saturated at ``box_max`` (the largest seen in training) before it multiplies, so a rollout that drives ``s``
up (the drone flying at the gate, ``s_dot ~ s^2``) grows it at most linearly and stays finite.

Checkpoints are single msgpack files (:mod:`network_weights`, as :mod:`dof`'s): format name and version,
the architecture (checked on load against the weights' shapes), the normalisation constants and the
training record, written atomically.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax.dynamics import network_weights, quadrotor

PIXEL_STATE_NAMES = ("u", "v", "s")
PIXEL_STATE_DIM = 3
HIDDEN_SIZES = (32, 32)  # [64, 64] and [128, 128] fit the train rows better and the held-out laps worse
ACTIVATION = "tanh"
# g(uv) -> [A (2x3, row-major), B (2x3), a (3,), b (3,)]
OUTPUT_NAMES = ("A", "B", "a", "b")
OUTPUT_DIM = 6 + 6 + 3 + 3
STRUCTURE = "uv_dot = s A(uv) v_b + B(uv) w; s_dot = s (s a(uv).v_b + b(uv).w)"

CHECKPOINT_FORMAT = "pixelmpc_jax.vdof"
CHECKPOINT_VERSION = 1


def box_size(corners: jax.Array) -> jax.Array:
    """The depth cue ``s``: sqrt of the area of the corner quadrilateral (shoelace), normalised image units.

    corners: (4, 2) normalised uv in order around the quadrilateral (TL, TR, BR, BL) -> (). For a gate facing
    the camera ``s`` is proportional to inverse depth. Zero for a degenerate quadrilateral, with a finite
    gradient there.
    """
    corners = jnp.asarray(corners)
    chex.assert_shape(corners, (4, 2))
    following = jnp.roll(corners, -1, axis=0)
    cross = corners[:, 0] * following[:, 1] - following[:, 0] * corners[:, 1]
    area = 0.5 * jnp.abs(jnp.sum(cross))
    ok = area > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, area, 1.0)), 0.0)


class InteractionNetwork(nn.Module):
    """The MLP g: (..., 2) normalised pixel -> (..., 18) = [A, B, a, b], normalised units; tanh hidden layers."""

    hidden_sizes: tuple[int, ...] = HIDDEN_SIZES

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden_sizes:
            x = jnp.tanh(nn.Dense(width)(x))
        return nn.Dense(OUTPUT_DIM)(x)


@struct.dataclass
class VDOFParams:
    """Weights and the constants that go with them; a pytree (new weights never recompile).

    Attributes:
        weights: the flax ``params`` of :class:`InteractionNetwork` (the only trainable part).
        uv_mean, uv_std: (2,) pixel normalisation, ``(uv - mean) / std``.
        velocity_scale: (3,) m/s, body-frame velocity scale.
        rate_scale: (3,) rad/s, body-rate scale.
        box_scale: () the box size's scale.
        box_max: () the box size saturates here before it multiplies (the largest in training).
        p_dot_scale: (3,) output scale of ``[u_dot, v_dot, s_dot]`` per second.
    """

    weights: Any
    uv_mean: jax.Array
    uv_std: jax.Array
    velocity_scale: jax.Array
    rate_scale: jax.Array
    box_scale: jax.Array
    box_max: jax.Array
    p_dot_scale: jax.Array


CONSTANTS = {  # name: (shape, default, must be positive)
    "uv_mean": ((2,), (0.5, 0.5), False),
    "uv_std": ((2,), (0.29, 0.29), True),
    "velocity_scale": ((3,), (1.0, 1.0, 1.0), True),
    "rate_scale": ((3,), (1.0, 1.0, 1.0), True),
    "box_scale": ((), 0.1, True),
    "box_max": ((), 1.0, True),
    "p_dot_scale": ((3,), (1.0, 1.0, 1.0), True),
}


def _constant(name: str, value) -> jax.Array:
    shape, default, positive = CONSTANTS[name]
    arr = np.asarray(default if value is None else value, dtype=np.float32)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or (positive and not np.all(arr > 0)):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}, got {arr}")
    return jnp.asarray(arr)


def init_vdof_params(key: jax.Array, hidden_sizes: tuple[int, ...] = HIDDEN_SIZES, **constants) -> VDOFParams:
    """Fresh weights (flax default initialisers) and the normalisation ``constants`` (names of
    :data:`CONSTANTS`; missing ones take their defaults)."""
    unknown = sorted(set(constants) - set(CONSTANTS))
    if unknown:
        raise ValueError(f"unknown VDOFParams constants {unknown}; expected some of {sorted(CONSTANTS)}")
    network = InteractionNetwork(tuple(int(h) for h in hidden_sizes))
    weights = network.init({"params": key}, jnp.zeros((2,), jnp.float32))["params"]
    return VDOFParams(weights=weights, **{name: _constant(name, constants.get(name)) for name in CONSTANTS})


def hidden_sizes_of(weights) -> tuple[int, ...]:
    """The hidden widths the weights' kernel shapes imply (static: read from shapes, not values)."""
    kernels = network_weights.dense_kernel_shapes(weights, "InteractionNetwork")
    if kernels[0][0] != 2 or kernels[-1][1] != OUTPUT_DIM:
        raise ValueError(f"weights are not an InteractionNetwork params tree: kernel shapes {kernels}")
    return tuple(int(k[1]) for k in kernels[:-1])


def interaction(params: VDOFParams, uv: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """g(uv) for one pixel (2,): ``A`` (2, 3), ``B`` (2, 3), ``a`` (3,), ``b`` (3,), in normalised units."""
    network = InteractionNetwork(hidden_sizes_of(params.weights))
    out = network.apply({"params": params.weights}, (uv - params.uv_mean) / params.uv_std)  # (18,)
    return out[0:6].reshape(2, 3), out[6:12].reshape(2, 3), out[12:15], out[15:18]


def body_velocity(x: jax.Array) -> jax.Array:
    """``v_b = R(q)^T v``: the robot's velocity (3,) in the body frame, from the state x (10,)."""
    q = quadrotor.normalize_quat(x[quadrotor.QUAT])
    return quadrotor.rotation_matrix(q).T @ x[quadrotor.VEL]


def _check_shapes(x, p, u) -> None:
    for name, arr, size in (("x", x, quadrotor.STATE_DIM), ("p", p, PIXEL_STATE_DIM), ("u", u, quadrotor.CONTROL_DIM)):
        if jnp.shape(arr) != (size,):
            raise ValueError(f"vdof: {name} must have shape ({size},) (one sample; vmap for a batch), "
                             f"got {jnp.shape(arr)}")


def pixel_state_velocity(params: VDOFParams, x: jax.Array, p: jax.Array, u: jax.Array) -> jax.Array:
    """The vdof pixel dynamics for one sample: ``p_dot = [uv_dot, s_dot]`` (3,), per second, in ``p``'s dtype.

    uv_dot = s A(uv) v_b + B(uv) w;  s_dot = s (s a(uv) . v_b + b(uv) . w).

    Args:
        params: the network and its constants.
        x: (10,) robot state (its attitude and velocity are used).
        p: (3,) pixel state ``[u, v, s]``: the target's normalised pixel and its box size (:func:`box_size`).
        u: (4,) control ``[wx, wy, wz, thrust]``; the rates are those flown (thrust is not used).
    """
    _check_shapes(x, p, u)
    p = jnp.asarray(p)
    dtype = params.uv_mean.dtype
    s = jnp.clip(p[2].astype(dtype), 0.0, params.box_max) / params.box_scale
    v_b = body_velocity(jnp.asarray(x).astype(dtype)) / params.velocity_scale
    w = jnp.asarray(u)[:3].astype(dtype) / params.rate_scale
    A, B, a, b = interaction(params, p[:2].astype(dtype))
    uv_dot = s * (A @ v_b) + B @ w
    s_dot = s * (s * jnp.dot(a, v_b) + jnp.dot(b, w))
    p_dot = jnp.concatenate([uv_dot, s_dot[None]]) * params.p_dot_scale
    return p_dot.astype(p.dtype) if jnp.issubdtype(p.dtype, jnp.floating) else p_dot


def initial_pixel_state(centre: jax.Array, corners: jax.Array, gate_size: float | jax.Array = 1.0) -> jax.Array:
    """The pixel state ``[u, v, s]`` (3,) of one detection: its centre (2,) and :func:`box_size` of its corners
    (4, 2) divided by ``gate_size`` (1 for the apparent size; the opening's ``sqrt(width * height)`` in metres
    for weights trained with ``box_cue="per_gate_size"``, see ``learn.vdof_spec``)."""
    centre = jnp.asarray(centre)
    return jnp.concatenate([centre, (box_size(corners) / gate_size)[None].astype(centre.dtype)])


# --------------------------------------------------------------------------------------------------
# Checkpoints.
# --------------------------------------------------------------------------------------------------


def architecture(hidden_sizes: tuple[int, ...] = HIDDEN_SIZES) -> dict:
    """The architecture recorded in (and checked against) checkpoints; only the hidden widths may vary."""
    return {"hidden_sizes": [int(h) for h in hidden_sizes], "activation": ACTIVATION, "inputs": ["u", "v"],
            "outputs": list(OUTPUT_NAMES), "output_dim": OUTPUT_DIM, "structure": STRUCTURE,
            "pixel_state": list(PIXEL_STATE_NAMES)}


class VDOFCheckpoint(NamedTuple):
    """Everything in a vdof weights file: the parameters, the record of how they were made, and ``extra``
    (state-dict pytrees a trainer stored to resume: optimizer state, step, key; ``{}`` if none)."""

    params: VDOFParams
    config: dict
    extra: dict


def save_vdof(path, params: VDOFParams, config: Mapping, *, extra: Mapping | None = None) -> None:
    """Write ``params`` and ``config`` (a JSON-serialisable record: how they were made) to one weights file
    (:func:`network_weights.write_file`), atomically; ``extra``: pytrees a trainer needs to resume."""
    trees = {"params": network_weights.to_numpy_tree(params)}
    if extra:
        trees["extra"] = {str(k): network_weights.to_numpy_tree(v) for k, v in extra.items()}
    architecture_record = architecture(hidden_sizes_of(params.weights))
    network_weights.write_file(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, architecture_record, config, trees)


def read_vdof_checkpoint(path) -> VDOFCheckpoint:
    """Read and validate a file written by :func:`save_vdof`, bit-exact; ``ValueError`` (one line, naming what is
    wrong) for a corrupted, truncated, foreign or mismatched file."""
    path = Path(path)
    payload = network_weights.read_file(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, "vdof")
    found, config, state, extra = network_weights.read_header(path, payload, "params", "vdof")
    try:
        hidden = tuple(int(h) for h in found["hidden_sizes"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: vdof checkpoint header is damaged: {err!r}") from err
    diffs = network_weights.architecture_differences(architecture(hidden), found)
    if diffs:
        raise ValueError(f"{path}: architecture mismatch: " + "; ".join(diffs))
    template = jax.eval_shape(lambda key: init_vdof_params(key, hidden), jax.random.key(0))
    params = network_weights.restore_params(path, template, state, "vdof")
    return VDOFCheckpoint(params, config, extra)


def load_vdof(path) -> tuple[VDOFParams, dict]:
    """``(params, config)`` from a file written by :func:`save_vdof` (:func:`read_vdof_checkpoint`)."""
    checkpoint = read_vdof_checkpoint(path)
    return checkpoint.params, checkpoint.config


def box_cue_of(config: Mapping) -> str:
    """What the checkpoint's ``s`` means, from its record: "apparent" (:func:`box_size` of the detected corners) or
    "per_gate_size" (that over the target opening's ``sqrt(width * height)`` in metres: pass it as
    :func:`initial_pixel_state`'s ``gate_size``). Records without the field are "apparent"."""
    return str((config.get("model_config") or config.get("train_config") or {}).get("box_cue", "apparent"))


PACKAGED_VDOF = Path(__file__).resolve().parent.parent / "data" / "vdof_weights.msgpack"
PACKAGED_VARIANTS = {
    # trained for the paper's untilted camera (the default)
    "vdof": PACKAGED_VDOF,
    # trained through the racing camera, tilted up 30 degrees (its record's camera_tilt_deg): what a race on that
    # camera flies by default
    "vdof_tilt30": PACKAGED_VDOF.with_name("vdof_weights_tilt30.msgpack"),
}


def load_packaged_vdof(variant: str = "vdof") -> VDOFParams:
    """vdof weights shipped inside the package: ``variant`` "vdof" (``data/vdof_weights.msgpack``, trained for the
    untilted camera; the default) or "vdof_tilt30" (``data/vdof_weights_tilt30.msgpack``, for the camera tilted up
    30 degrees); each has a ``.json`` beside it saying how it was made and for which camera."""
    return load_vdof(network_weights.packaged_path(PACKAGED_VARIANTS, variant, "vdof",
                                                   "train them with `pixelmpc train --model vdof --ship`"))[0]


def packaged_vdof_hash(variant: str = "vdof") -> str:
    """The fingerprint (:func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`) of the vdof weights
    ``variant`` shipped inside the package (computed again only when the weights file changes)."""
    return network_weights.packaged_weights_hash(PACKAGED_VARIANTS[variant], load_packaged_vdof, variant)
