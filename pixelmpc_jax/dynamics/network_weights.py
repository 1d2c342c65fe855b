"""What the learned pixel models (:mod:`dof`, :mod:`vdof`) share about their weights: the dense layers' shapes a
weights tree implies, how many scalars are trained, and the weights file.

A weights file is one msgpack file (``flax.serialization``): the format name and version, the architecture and the
record of how the weights were made (both as JSON), and the parameters as state dicts of numpy arrays (raw bytes:
bit-exact round trips; no pickle, so loading an untrusted file cannot run code), written atomically. Each model
names its format, checks the architecture it reads against its own, and keeps its parameters' layout; the reading,
writing and shape checks are here, once. So is the weights' fingerprint (:func:`dof_weights_hash`), by which a race
names the weights it flies, and its cache for the weights shipped in the package (:func:`packaged_weights_hash`),
and the camera the weights serve, as their record states it (:func:`trained_camera_tilt_deg`), by which a race picks
the packaged weights trained for its camera (:func:`variant_for_camera`).
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from pixelmpc_jax import strict_json

# The record's entry (deg) of the upward tilt of the camera the weights were trained for (the dataset's)
CAMERA_TILT_KEY = "camera_tilt_deg"


def dense_kernel_shapes(weights, network: str) -> list[tuple[int, ...]]:
    """The kernel shapes of a flax MLP's ``Dense_0 .. Dense_n`` layers in order (read from shapes, not values);
    ``ValueError`` naming ``network`` for a tree that is not one."""
    try:
        names = sorted(weights, key=lambda n: int(str(n).split("_")[-1]))
        kernels = [tuple(np.shape(weights[n]["kernel"])) for n in names]
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"weights are not a {network} params tree: {err!r}") from err
    if not kernels or any(len(k) != 2 for k in kernels):
        raise ValueError(f"weights are not a {network} params tree: kernel shapes {kernels}")
    return kernels


def num_trainable_params(params) -> int:
    """Number of trainable scalars of a model's parameters (``params.weights``; the normalisation constants beside
    them are not trained)."""
    return int(sum(np.size(leaf) for leaf in jax.tree_util.tree_leaves(params.weights)))


def to_numpy_tree(tree):
    """State dict with arrays as numpy (msgpack stores them as raw bytes); strings stay strings."""

    def leaf(x):
        return x if isinstance(x, str | bytes) else np.asarray(x)

    return jax.tree_util.tree_map(leaf, serialization.to_state_dict(tree))


def write_file(path, file_format: str, version: int, architecture: Mapping, config: Mapping, trees: Mapping) -> None:
    """One msgpack file, written atomically (``strict_json.write_atomic``): the ``file_format``, its ``version``,
    the ``architecture`` and ``config`` (JSON-serialisable dicts) as JSON, and ``trees`` (state dicts of numpy
    arrays, :func:`to_numpy_tree`) as they are."""
    try:
        config_json = strict_json.dumps(dict(config), sort_keys=True)
    except (TypeError, ValueError) as err:
        raise TypeError(f"config must be a JSON-serialisable dict: {err}") from err
    payload = {"format": file_format, "format_version": version,
               "architecture": strict_json.dumps(dict(architecture), sort_keys=True), "config": config_json,
               **trees}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = serialization.msgpack_serialize(payload)
    strict_json.write_atomic(path, lambda f: f.write(data))


def read_file(path: Path, file_format: str, version: int, model: str) -> dict:
    """The payload of a file :func:`write_file` wrote in ``file_format`` and ``version``; ``ValueError`` (one line,
    naming the ``model``'s checkpoint) for a corrupted, truncated or foreign file or another version."""
    data = path.read_bytes()
    try:
        payload = serialization.msgpack_restore(data)
    except Exception as err:  # msgpack raises several unrelated types on bad bytes
        detail = " ".join(str(err).split()) if len(str(err)) <= 100 else type(err).__name__  # (some quote the bytes)
        raise ValueError(f"{path}: not a readable {model} checkpoint (corrupted or truncated, {len(data)} bytes): "
                         f"{detail}") from err
    if not isinstance(payload, dict) or payload.get("format") != file_format:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(f"{path}: not a {model} checkpoint: format expected {file_format!r}, found {found!r}")
    if payload.get("format_version") != version:
        raise ValueError(f"{path}: format_version expected {version}, found {payload.get('format_version')!r}")
    return payload


def read_header(path: Path, payload: Mapping, params_key: str, model: str) -> tuple[dict, dict, object, dict]:
    """A checkpoint payload's (:func:`read_file`) architecture record, configuration, parameters' tree (under
    ``params_key``) and extra record; a ValueError ``{path}: {model} checkpoint header is damaged`` where one is
    missing or unreadable."""
    try:
        return (json.loads(payload["architecture"]), json.loads(payload["config"]), payload[params_key],
                payload.get("extra", {}) or {})
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: {model} checkpoint header is damaged: {err!r}") from err


def architecture_differences(expected: Mapping, found: Mapping) -> list[str]:
    """``key: expected ..., found ...`` for every entry of two architecture records that differs."""
    return [f"{k}: expected {expected.get(k, '<missing>')!r}, found {found.get(k, '<missing>')!r}"
            for k in sorted(set(expected) | set(found)) if expected.get(k, "<missing>") != found.get(k, "<missing>")]


def restore_params(path: Path, template, state, model: str):
    """``template``'s pytree with the arrays of the state dict ``state``, as JAX arrays; ``ValueError`` naming what
    differs when the state does not fit the template or a leaf is not float32 of the template's shape.

    Only the template's structure, shapes and dtypes are read: pass ``jax.eval_shape`` of the initialiser, which
    traces it without compiling or running it (a flax ``init`` compiled to build a template took 2 s on a CPU)."""
    try:
        params = serialization.from_state_dict(template, state)
    except Exception as err:
        raise ValueError(f"{path}: {model} parameters do not match the architecture: {err!r}") from err
    bad = [f"{jax.tree_util.keystr(p)}: expected float32{np.shape(t)}, found {np.asarray(f).dtype}{np.shape(f)}"
           for (p, t), f in zip(jax.tree_util.tree_leaves_with_path(template), jax.tree_util.tree_leaves(params),
                                strict=True)
           if np.shape(t) != np.shape(f) or np.asarray(f).dtype != np.float32]
    if bad:
        raise ValueError(f"{path}: architecture mismatch: " + "; ".join(bad))
    return jax.tree_util.tree_map(jnp.asarray, params)


def trained_camera_tilt_deg(record: Mapping) -> float:
    """The upward tilt (deg) of the camera weights were trained for, as their record states it; 0, the paper's
    untilted camera, for a record without it (every record written before the tilt was recorded)."""
    return float(record.get(CAMERA_TILT_KEY, 0.0))


def variant_for_camera(variants: Mapping[str, Path], camera_tilt_deg: float) -> str | None:
    """The first of the packaged weights ``variants`` (``{name: weights file}``, the model's default first) whose
    record states the camera tilt ``camera_tilt_deg`` (:func:`trained_camera_tilt_deg`, to 1e-9 deg); None where none
    was trained for that camera."""
    for name, path in variants.items():
        if abs(packaged_camera_tilt_deg(path) - float(camera_tilt_deg)) <= 1e-9:
            return name
    return None


def packaged_camera_tilt_deg(path: Path) -> float:
    """:func:`trained_camera_tilt_deg` of the record shipped beside the weights at ``path``, read again only when the
    record changes (its mtime or size)."""
    beside = Path(path).with_suffix(".json")
    stat = beside.stat() if beside.exists() else None
    return _record_tilt(str(path), stat and (stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=32)
def _record_tilt(path: str, version) -> float:
    return trained_camera_tilt_deg(weights_record(Path(path)))


def packaged_path(variants: Mapping[str, Path], variant: str, model: str, missing: str) -> Path:
    """The file of the packaged weights ``variant`` of ``variants`` (``{name: weights file}``) of the pixel model
    ``model``; a ValueError naming the variants for an unknown one, a FileNotFoundError ending with ``missing`` (what
    to do) where the package lacks the file."""
    if variant not in variants:
        raise ValueError(f"unknown packaged {model} weights {variant!r}; choose one of {', '.join(variants)}")
    path = variants[variant]
    if not path.exists():
        raise FileNotFoundError(f"{path}: the package ships no {model} weights; {missing}")
    return path


def weights_record(path: Path) -> dict:
    """The readable record shipped beside a weights file (its ``.json``), or ``{}`` where there is none."""
    beside = Path(path).with_suffix(".json")
    return json.loads(beside.read_text()) if beside.exists() else {}


def dof_weights_hash(params) -> str:
    """A short fingerprint of a pixel model's weights (the DOF's or vdof's): the first 16 hex digits of the sha256 of
    every leaf's dtype, shape and bytes (in ``jax.tree_util.tree_leaves`` order)."""
    digest = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(params):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def packaged_weights_hash(path: Path, load: Callable, *args) -> str:
    """:func:`dof_weights_hash` of weights shipped in the package at ``path``, as ``load(*args)`` reads them;
    computed again only when the file changes (its mtime or size)."""
    stat = path.stat() if path.exists() else None
    return _packaged_hash(load, args, str(path), stat and (stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=8)
def _packaged_hash(load: Callable, args: tuple, path: str, version) -> str:
    """The packaged weights' fingerprint, cached by the loader, the file's ``path`` and ``version`` (mtime, size)."""
    return dof_weights_hash(load(*args))
