"""Deep Optical Flow (DOF) dynamics: the paper's pixel model, Section III, Eqs. (10)-(12).

A feed-forward network [10, 128, 128, 128, 2] (ReLU on the hidden layers, 10% dropout after each hidden
layer in training only, linear output) maps the robot orientation ``q`` (4,), the normalised pixel
``uv`` (2,) and the control ``u`` (4,) to the polar optical flow ``(l, theta)`` of that pixel, and
PolarToEuler (Eq. 11) turns it into the pixel velocity ``uv_dot = (l cos theta, l sin theta)``, in
normalised image units per second (the image is [0, 1] x [0, 1]).

The input normalisation (per-feature mean and std) and the output scale (``(l, theta) = out * std +
mean``) live beside the weights in :class:`DOFParams`, so a parameter pytree, and a checkpoint of it,
is self-contained. Every model function is written for one sample and batched by ``jax.vmap``; the
per-sample path has no value-dependent Python branching, so ``vmap`` turns the dense layers into
matmuls (the MPPI inner loop: 512 samples x 40 steps per tick).

Checkpoints are single msgpack files (:mod:`network_weights`, shared with vdof), the format the package
ships its weights in (``data/*.msgpack``): arrays are stored as raw bytes (bit-exact round trips), no pickle
is involved (loading an untrusted file cannot run code), and the header (architecture, normalisation,
training config) sits in the same file.
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

from pixelmpc_jax.dynamics import network_weights

INPUT_NAMES = ("qw", "qx", "qy", "qz", "u", "v", "wx", "wy", "wz", "thrust")
OUTPUT_NAMES = ("l", "theta")
INPUT_DIM = len(INPUT_NAMES)
OUTPUT_DIM = len(OUTPUT_NAMES)
HIDDEN_SIZES = (128, 128, 128)
LAYER_SIZES = (INPUT_DIM, *HIDDEN_SIZES, OUTPUT_DIM)
ACTIVATION = "relu"
OUTPUT_ACTIVATION = "linear"
DROPOUT_RATE = 0.1

CHECKPOINT_FORMAT = "pixelmpc_jax.dof"
CHECKPOINT_VERSION = 1


def architecture() -> dict:
    """The architecture this module implements, as recorded in (and checked against) checkpoints."""
    return {
        "layer_sizes": list(LAYER_SIZES),
        "activation": ACTIVATION,
        "output_activation": OUTPUT_ACTIVATION,
        "dropout_rate": DROPOUT_RATE,
        "inputs": list(INPUT_NAMES),
        "outputs": list(OUTPUT_NAMES),
    }


class DOFNetwork(nn.Module):
    """The MLP on normalised features: (..., 10) -> (..., 2), normalised (l, theta)."""

    hidden_sizes: tuple[int, ...] = HIDDEN_SIZES
    output_dim: int = OUTPUT_DIM
    dropout_rate: float = DROPOUT_RATE

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        for width in self.hidden_sizes:
            x = nn.relu(nn.Dense(width)(x))
            x = nn.Dropout(self.dropout_rate, deterministic=deterministic)(x)
        return nn.Dense(self.output_dim)(x)


_NETWORK = DOFNetwork()


@struct.dataclass
class DOFParams:
    """Weights and the constants that go with them; a pytree (new weights never recompile).

    Attributes:
        weights: the flax ``params`` collection of :class:`DOFNetwork` (the only trainable part).
        input_mean, input_std: (10,) feature normalisation, ``(x - mean) / std``, order ``INPUT_NAMES``.
        output_mean, output_std: (2,) output scale, ``(l, theta) = out * std + mean``.
    """

    weights: Any
    input_mean: jax.Array
    input_std: jax.Array
    output_mean: jax.Array
    output_std: jax.Array


def _constant(value, default, size: int, name: str) -> jax.Array:
    arr = np.asarray(default if value is None else value, dtype=np.float32)
    if arr.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    if name.endswith("std") and not np.all(arr > 0):
        raise ValueError(f"{name} must be > 0, got {arr}")
    return jnp.asarray(arr)


def init_dof_params(
    key: jax.Array,
    input_mean=None,
    input_std=None,
    output_mean=None,
    output_std=None,
) -> DOFParams:
    """Fresh weights (flax default initialisers) with the given normalisation constants.

    Missing constants default to identity scaling (mean 0, std 1).
    """
    weights = _NETWORK.init({"params": key}, jnp.zeros((INPUT_DIM,), jnp.float32))["params"]
    return DOFParams(
        weights=weights,
        input_mean=_constant(input_mean, np.zeros(INPUT_DIM), INPUT_DIM, "input_mean"),
        input_std=_constant(input_std, np.ones(INPUT_DIM), INPUT_DIM, "input_std"),
        output_mean=_constant(output_mean, np.zeros(OUTPUT_DIM), OUTPUT_DIM, "output_mean"),
        output_std=_constant(output_std, np.ones(OUTPUT_DIM), OUTPUT_DIM, "output_std"),
    )


def dof_features(q: jax.Array, uv: jax.Array, u: jax.Array) -> jax.Array:
    """Network input ``[q, uv, u]``: (..., 4), (..., 2), (..., 4) -> (..., 10), same leading shape."""
    q, uv, u = jnp.asarray(q), jnp.asarray(uv), jnp.asarray(u)
    for name, arr, size in (("q", q, 4), ("uv", uv, 2), ("u", u, 4)):
        if arr.ndim == 0 or arr.shape[-1] != size:
            raise ValueError(f"{name} must have trailing dimension {size}, got shape {arr.shape}")
    if not q.shape[:-1] == uv.shape[:-1] == u.shape[:-1]:
        raise ValueError(f"q, uv, u must share leading dimensions, got {q.shape}, {uv.shape}, {u.shape}")
    return jnp.concatenate([q, uv, u], axis=-1)


def _along_last(vec: jax.Array, ndim: int) -> jax.Array:
    """Reshape a (k,) constant to broadcast against (..., k) without implicit rank promotion."""
    return jnp.reshape(vec, (1,) * (ndim - 1) + (-1,))


def dof_forward(
    dof_params: DOFParams, features: jax.Array, *, dropout_key: jax.Array | None = None
) -> jax.Array:
    """The network on raw features: (..., 10) -> (..., 2) = (l, theta), any leading shape.

    With ``dropout_key`` the 10% dropout is active (training; every row gets its own mask), without
    it the function is deterministic. Computes in the weights' dtype (float32).
    """
    if features.shape[-1] != INPUT_DIM:
        raise ValueError(f"features must have trailing dimension {INPUT_DIM}, got {features.shape}")
    dtype = dof_params.input_mean.dtype
    x = features.astype(dtype)
    nd = x.ndim
    x = (x - _along_last(dof_params.input_mean, nd)) / _along_last(dof_params.input_std, nd)
    variables = {"params": dof_params.weights}
    if dropout_key is None:
        out = _NETWORK.apply(variables, x, deterministic=True)
    else:
        # The non-partitionable threefry draws the same-quality bits 5-8x faster on CPU (the masks are
        # the largest random draw of a training step); scoped here, the global setting is untouched.
        with jax.threefry_partitionable(False):
            out = _NETWORK.apply(variables, x, deterministic=False, rngs={"dropout": dropout_key})
    return out * _along_last(dof_params.output_std, nd) + _along_last(dof_params.output_mean, nd)


def dof_apply(
    dof_params: DOFParams,
    q: jax.Array,
    uv: jax.Array,
    u: jax.Array,
    *,
    dropout_key: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """DOF(q, uv, u) -> (l, theta) for one sample (Eq. 12 before PolarToEuler).

    Args:
        q: (4,) orientation ``[qw, qx, qy, qz]``, body to world.
        uv: (2,) normalised pixel in [0, 1]^2.
        u: (4,) control ``[wx, wy, wz, thrust]``.
        dropout_key: training only; ``None`` gives the deterministic network.

    Returns:
        l: () flow magnitude, normalised image units per second; theta: () its angle (rad).
    """
    out = dof_forward(dof_params, dof_features(q, uv, u), dropout_key=dropout_key)
    return out[..., 0], out[..., 1]


def polar_to_euler(l: jax.Array, theta: jax.Array) -> jax.Array:
    """PolarToEuler, Eq. (11): ``(l cos theta, l sin theta)``, stacked on a new last axis."""
    return jnp.stack([l * jnp.cos(theta), l * jnp.sin(theta)], axis=-1)


def pixel_velocity(dof_params: DOFParams, q: jax.Array, uv: jax.Array, u: jax.Array) -> jax.Array:
    """The DOF pixel dynamics, Eq. (12): ``uv_dot = PolarToEuler(DOF(q, uv, u))``.

    One sample: q (4,), uv (2,), u (4,) -> uv_dot (2,) in normalised image units per second, in
    ``uv``'s floating dtype. Deterministic (no dropout).
    """
    uv = jnp.asarray(uv)
    chex.assert_rank([q, uv, u], 1)  # one sample; vmap it for a batch
    l, theta = dof_apply(dof_params, q, uv, u)
    uv_dot = polar_to_euler(l, theta)
    return uv_dot.astype(uv.dtype) if jnp.issubdtype(uv.dtype, jnp.floating) else uv_dot


# --------------------------------------------------------------------------------------------------
# Checkpoints.
# --------------------------------------------------------------------------------------------------


class DOFCheckpoint(NamedTuple):
    """Everything in a checkpoint file: the parameters, the config it was made with, and ``extra``
    (state-dict pytrees a trainer stored to resume, e.g. optimizer state and step; ``{}`` if none)."""

    dof_params: DOFParams
    config: dict
    extra: dict


def _architecture_of(dof_params: DOFParams) -> dict:
    """The architecture the weights' shapes imply (so a mismatched file is caught however written)."""
    kernels = network_weights.dense_kernel_shapes(dof_params.weights, "DOFNetwork")
    arch = architecture()
    arch["layer_sizes"] = [int(kernels[0][0])] + [int(k[1]) for k in kernels]
    return arch


def save_checkpoint(path, dof_params: DOFParams, config: Mapping, *, extra: Mapping | None = None) -> None:
    """Write ``dof_params`` and ``config`` to one weights file (:func:`network_weights.write_file`), atomically.

    The file records the format and version, the architecture (layer sizes, activation, dropout; read
    from the weights' shapes), the normalisation constants (inside the params), and ``config`` (a
    JSON-serialisable dict: the training config and command). ``extra`` holds pytrees a trainer needs
    to resume (optimizer state, step, key data); they are stored as flax state dicts of numpy arrays.
    """
    network_weights.write_file(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, _architecture_of(dof_params), config, {
        "dof_params": network_weights.to_numpy_tree(dof_params),
        "extra": {str(k): network_weights.to_numpy_tree(v) for k, v in (extra or {}).items()},
    })


def read_checkpoint(path) -> DOFCheckpoint:
    """Read and validate a checkpoint file; raises ``ValueError`` for a corrupt, truncated, foreign or
    mismatched-architecture file, naming what differs (expected vs found)."""
    path = Path(path)
    payload = network_weights.read_file(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, "DOF")
    found_arch, config, state, extra = network_weights.read_header(path, payload, "dof_params", "DOF")
    differences = network_weights.architecture_differences(architecture(), found_arch)
    if differences:
        raise ValueError(f"{path}: architecture mismatch: " + "; ".join(differences))
    dof_params = network_weights.restore_params(path, jax.eval_shape(init_dof_params, jax.random.key(0)), state, "DOF")
    return DOFCheckpoint(dof_params=dof_params, config=config, extra=extra)


def load_checkpoint(path) -> tuple[DOFParams, dict]:
    """``(dof_params, config)`` from a file written by :func:`save_checkpoint`; predictions of the
    restored parameters are bit-identical to the saved ones."""
    checkpoint = read_checkpoint(path)
    return checkpoint.dof_params, checkpoint.config


def checkpoint_variant(config: Mapping) -> dict:
    """How a checkpoint's network was trained, from its config: ``{"input", "loss"}``.

    ``input`` is what the network's control input means: "command" (the paper's: the body rates commanded at
    the frame's tick) or "flown" (the body rates flown over the frame interval; see learn/dataset.py);
    ``loss`` "polar" or "endpoint". Files written before the variants were recorded are the paper's
    (command input) with the loss their training config names (polar by default).
    """
    variant = dict(config.get("variant") or {})
    train_config = config.get("train_config") or {}
    return {"input": variant.get("input", train_config.get("input", "command")),
            "loss": variant.get("loss", train_config.get("loss", "polar"))}


PACKAGED_WEIGHTS = Path(__file__).resolve().parent.parent / "data" / "dof_weights.msgpack"
PACKAGED_VARIANTS = {
    # the paper's formulation: the network's control input is the commanded body rate (the default)
    "paper": PACKAGED_WEIGHTS,
    # the flown-rate variant: trained on the body rates flown over each frame (the MPC's own meaning of u)
    "flown": PACKAGED_WEIGHTS.with_name("dof_weights_flown.msgpack"),
    # the flown-rate variant trained with rows turned by an extra camera rotation (train --rotation-augment 1)
    "turned": PACKAGED_WEIGHTS.with_name("dof_weights_turned.msgpack"),
    # the paper's formulation trained through the racing camera, tilted up 30 degrees (its record's camera_tilt_deg):
    # what a race on that camera flies by default
    "paper_tilt30": PACKAGED_WEIGHTS.with_name("dof_weights_tilt30.msgpack"),
}


def load_packaged_dof(variant: str = "paper") -> DOFParams:
    """DOF weights shipped inside the package: ``variant`` "paper" (``data/dof_weights.msgpack``, the paper's
    command input; the default), "flown" (``data/dof_weights_flown.msgpack``), "turned"
    (``data/dof_weights_turned.msgpack``) or "paper_tilt30" (``data/dof_weights_tilt30.msgpack``, the paper's trained
    for the camera tilted up 30 degrees); each has a ``.json`` beside it saying how it was made and for which camera."""
    return load_checkpoint(network_weights.packaged_path(
        PACKAGED_VARIANTS, variant, "DOF", "reinstall it, or train your own with `pixelmpc train` and pass them "
        "explicitly"))[0]


def packaged_dof_hash(variant: str = "paper") -> str:
    """The fingerprint (:func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`) of the DOF weights
    ``variant`` shipped inside the package (computed again only when the weights file changes)."""
    return network_weights.packaged_weights_hash(PACKAGED_VARIANTS[variant], load_packaged_dof, variant)
