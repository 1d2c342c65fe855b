"""The DOF dataset: its files, and loading them as laps or as training frames.

A dataset (written by :mod:`pixelmpc_jax.learn.collect`) is one directory::

    manifest.json          config, split, per-lap summary and sha256, versions
    lap_000.npz ...        one lap each, written atomically (temp file + os.replace):
        flow         (F, H, W, 2) float16  Farneback flow t -> t+1, pixels per frame, flow[y, x] = (du, dv)
        q, u         (F, 4) float32        orientation at t, control applied between t and t+1
        w_flown      (F, 3) float32        mean body rate flown between t and t+1 (rad/s; format 2)
        rates        (F + 1, 3) float32    true body rates at every rendered frame (rad/s; format 2)
        states       (F + 1, 10) float32   true state at every rendered frame
        target       (F + 1,) int32        target gate index at every rendered frame
        exact_flow   (F, H, W, 2) float16  exact flow from depth + poses (test laps only by default)
        exact_valid  (F, H, W) bool        where the exact flow is defined (in front, inside the image)
        gate_found   (F + 1,) bool         the detector found the target gate at that frame (later files)
        gate_centre  (F + 1, 2) float32    the detected gate's centre, normalised (later files)
        gate_corners (F + 1, 4, 2) float32 the detected opening's corners TL, TR, BR, BL, normalised (later files)

The command is not what the camera turns by: the plant's rate loop flies it with a slope of about 0.65 and
a lag of about 0.11 s, so a frame's flow paired with its tick's command shows a diluted, delayed response.
``w_flown[t]`` is the mean body rate over the frame interval, ``2 log(q_t^-1 q_{t+1}) / dt``: the rotation
the camera made between the two frames, which is the noise-free gyro preintegrated over the tick. The
MPC's robot model assumes the commanded rates are flown at once, so a pixel model trained on ``w_flown``
(``input="flown"``) answers the question the MPC asks of it.

As training data (:class:`FlowData`) every pixel of every frame is a row: pixel (i, j) has
``uv = ((i + 0.5) / W, (j + 0.5) / H)`` (:func:`pixel_uv`) and the flow at ``flow[f, j, i]``.

The manifest records each lap file's sha256; the loaders refuse a file whose bytes no longer match. Lap
files of format 1 (no ``w_flown``) still load: their flown rates are derived from the stored states, which
is the same computation.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH

DATASET_FORMAT = "pixelmpc_jax.flow_dataset"
DATASET_VERSION = 2
MANIFEST = "manifest.json"
LAP_KEYS = ("flow", "q", "u", "states", "target")  # format 1 and later; format 2 adds FLOWN_KEYS
FLOWN_KEYS = ("w_flown", "rates")
FLOWN_RATES = ("w_flown[t] = 2 log(q_t^-1 q_{t+1}) / dt: the mean body rate flown over the frame interval "
               "(the noise-free gyro, preintegrated over the tick)")
EXACT_KEYS = ("exact_flow", "exact_valid")
DETECTION_KEYS = ("gate_found", "gate_centre", "gate_corners")  # the detector's output per frame (optional)
# What the network's control input u (4,) is: "command", the paper's (the body rates and thrust commanded at
# the frame's tick), or "flown" (the body rates flown over the frame interval, with the commanded thrust;
# control_input). The MPC's robot model assumes the commanded rates are flown at once, so "flown"
# is what PixelMPC means by its control; the network is the same [10, 128, 128, 128, 2] either way.
INPUTS = ("command", "flown")


# --------------------------------------------------------------------------------------------------
# Frames as training data.
# --------------------------------------------------------------------------------------------------


class FlowData(NamedTuple):
    """Training or test frames. q: (F, 4); u: (F, 4); flow: (F, H, W, 2) pixels per frame."""

    q: Any
    u: Any
    flow: Any


def as_flow_data(data, width: int = PAPER_WIDTH, height: int = PAPER_HEIGHT) -> FlowData:
    """Coerce ``(q, u, flow)`` given as a FlowData, mapping or any object with those attributes, and
    check shapes early (outside jit), naming what was expected."""
    if isinstance(data, Mapping):
        q, u, flow = data["q"], data["u"], data["flow"]
    elif isinstance(data, tuple) and not hasattr(data, "q"):
        q, u, flow = data
    else:
        q, u, flow = data.q, data.u, data.flow
    q, u, flow = np.asarray(q), np.asarray(u), np.asarray(flow)
    n = q.shape[0] if q.ndim else -1
    if q.shape != (n, 4) or n < 1:
        raise ValueError(f"q must have shape (F, 4) with F >= 1, got {q.shape}")
    if u.shape != (n, 4):
        raise ValueError(f"u must have shape (F, 4) = ({n}, 4), got {u.shape}")
    if flow.shape != (n, height, width, 2):
        raise ValueError(f"flow must have shape (F, H, W, 2) = ({n}, {height}, {width}, 2), got {flow.shape}")
    if not np.issubdtype(flow.dtype, np.floating):
        raise ValueError(f"flow must be float16 or float32 pixels per frame, got {flow.dtype}")
    for name, arr in (("q", q), ("u", u)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains non-finite values in frames {np.nonzero(~np.isfinite(arr))[0][:10]}")
    return FlowData(q, u, flow)


def pixel_uv(i: jax.Array, j: jax.Array, width: int, height: int) -> jax.Array:
    """Pixel column ``i``, row ``j`` -> normalised centre ``((i + 0.5) / W, (j + 0.5) / H)``, (..., 2)."""
    return jnp.stack([(i + 0.5) / width, (j + 0.5) / height], axis=-1).astype(jnp.float32)


# --------------------------------------------------------------------------------------------------
# Laps and the network's control input.
# --------------------------------------------------------------------------------------------------


class Lap(NamedTuple):
    """One stored lap (host arrays; ``None`` for fields not loaded or not stored). F flow frames.

    Attributes:
        flow: (F, H, W, 2) float16 Farneback flow, pixels per frame.
        q, u: (F, 4) float32.
        states: (F + 1, 10) float32, true state at each rendered frame.
        target: (F + 1,) int32 target gate index.
        exact_flow: (F, H, W, 2) float16 or None; exact_valid: (F, H, W) bool or None.
        info: the lap's manifest entry (index, split, speed, seed, frames, end, ...); ``w_flown_source`` is
            "stored" or "states" (a format-1 file: derived from the states).
        w_flown: (F, 3) float32, the mean body rates flown over each frame interval (rad/s).
        detections: ``{name: array}`` of :data:`DETECTION_KEYS`, the detector's per-frame output where the file
            stores it (None for files collected before it was stored; derive it from the states then).
    """

    flow: np.ndarray | None
    q: np.ndarray
    u: np.ndarray
    states: np.ndarray
    target: np.ndarray
    exact_flow: np.ndarray | None
    exact_valid: np.ndarray | None
    info: dict
    w_flown: np.ndarray | None = None
    detections: dict | None = None


def flown_rates(states: np.ndarray, dt: float = timing.CONTROL_DT) -> np.ndarray:
    """Mean body rates (F, 3) rad/s flown between consecutive states (F + 1, 10): ``2 log(q_t^-1 q_{t+1}) / dt``.

    The body-frame rotation vector of the attitude change over the interval, divided by its length. The model
    integrates ``q_dot = q (x) [0, w] / 2`` with body rates ``w``, so for rates constant over the interval
    this is exactly them; for changing rates it is the rotation the camera actually made (the preintegrated
    gyro), which sets the rotational flow between the frames.
    """
    q = np.asarray(states, np.float64)[:, 3:7]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    a, b = q[:-1], q[1:]
    aw, ax, ay, az = a[:, 0], -a[:, 1], -a[:, 2], -a[:, 3]  # conjugate of q_t
    bw, bx, by, bz = b.T
    d = np.stack([aw * bw - ax * bx - ay * by - az * bz,
                  aw * bx + ax * bw + ay * bz - az * by,
                  aw * by - ax * bz + ay * bw + az * bx,
                  aw * bz + ax * by - ay * bx + az * bw], axis=1)
    d = d * np.where(d[:, :1] < 0, -1.0, 1.0)  # the shorter of the two rotations
    s = np.linalg.norm(d[:, 1:], axis=1)
    angle = 2.0 * np.arctan2(s, d[:, 0])
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return (d[:, 1:] * scale[:, None] / float(dt)).astype(np.float32)


def control_input(u: np.ndarray, w_flown: np.ndarray, input: str = "command") -> np.ndarray:
    """The DOF's 4-vector control input per frame (F, 4): the command ``u`` ("command", the paper's), or
    the rates flown over the frame with the commanded thrust ``[w_flown, u_thrust]`` ("flown")."""
    if input not in INPUTS:
        raise ValueError(f"input must be one of {INPUTS}, got {input!r}")
    u = np.asarray(u, np.float32)
    if input == "command":
        return u
    return np.concatenate([np.asarray(w_flown, np.float32), u[:, 3:4]], axis=1)


def lap_input(lap: Lap, input: str = "command") -> np.ndarray:
    """:func:`control_input` of a loaded lap."""
    return control_input(lap.u, lap.w_flown, input)


# --------------------------------------------------------------------------------------------------
# Files.
# --------------------------------------------------------------------------------------------------


def lap_filename(index: int) -> str:
    return f"lap_{index:03d}.npz"


def file_sha256(path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def intact_lap_sha256(path: Path, expected_sha256: str | None = None) -> str | None:
    """The sha256 of an intact lap file, or None when it is missing or damaged.

    Intact: the archive lists every required array and its bytes hash to ``expected_sha256`` (the manifest's);
    without a recorded checksum (a lap written just before an interruption, a dataset from before checksums)
    every member must pass the archive's CRC-32 check instead.
    """
    if not path.exists():
        return None
    try:
        with zipfile.ZipFile(path) as archive:
            if not set(LAP_KEYS) <= {Path(n).stem for n in archive.namelist()}:
                return None
            if expected_sha256 is None and archive.testzip() is not None:
                return None
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, zlib.error):
        return None
    digest = file_sha256(path)
    return digest if expected_sha256 in (None, digest) else None


def _meta(data) -> dict:
    """The ``meta_*`` scalars of an open lap archive, without the prefix."""
    return {k.removeprefix("meta_"): data[k].item() for k in data.files if k.startswith("meta_")}


def lap_meta(path: Path) -> dict:
    """The summary stored in a lap file (lap, split, speed, seed, frames, end, ...)."""
    with np.load(path) as data:
        return _meta(data)


def find_manifest(root: Path) -> dict | None:
    """The manifest in ``root``, or None when there is none; ``ValueError`` if it is unreadable or foreign."""
    path = root / MANIFEST
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: unreadable dataset manifest ({err}); delete it to re-collect") from err
    if not isinstance(manifest, dict) or manifest.get("format") != DATASET_FORMAT:
        raise ValueError(f"{path}: not a {DATASET_FORMAT} manifest")
    return manifest


def read_manifest(data_dir) -> dict:
    """The dataset's manifest; ``FileNotFoundError`` / ``ValueError`` naming what is wrong."""
    root = Path(data_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"no DOF dataset at {root}: the directory does not exist "
                                f"(collect one with `pixelmpc collect --out {root}` or learn.collect.collect)")
    manifest = find_manifest(root)
    if manifest is None:
        raise FileNotFoundError(f"no DOF dataset at {root}: {MANIFEST} is missing "
                                f"(collect one with `pixelmpc collect --out {root}` or learn.collect.collect)")
    return manifest


def summarise_manifest(manifest: dict, data_dir=None) -> str:
    """A few lines: laps, frames per split, size, and one line per lap."""
    laps = manifest["laps"]
    lines = [f"dataset {data_dir or ''}: {len(laps)}/{manifest['config']['laps']} laps, "
             f"{manifest['frames']['train']} train + {manifest['frames']['test']} test frames, "
             f"{manifest.get('bytes', 0) / 1e6:.0f} MB{'' if manifest['complete'] else ' (incomplete: run again)'}"]
    for e in laps:
        lines.append(f"  lap {e['lap']:>2} {e['split']:>5}  {e['speed']:5.1f} m/s  seed {e['seed']:>5}  "
                     f"{e['frames']:>5} frames  {e['flight_time_s']:5.1f} s  {e['gates_passed']:>2} gates  {e['end']}"
                     f"{'  excited' if e.get('excited') else ''}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# Loading.
# --------------------------------------------------------------------------------------------------


def _split_laps(manifest: dict, split: str, root: Path) -> list[dict]:
    if split not in ("train", "test", "all"):
        raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
    laps = [e for e in manifest["laps"] if split == "all" or e["split"] == split]
    if not laps:
        raise ValueError(f"{root}: no {split} laps in the dataset (split {manifest.get('split')}, "
                         f"{len(manifest['laps'])} lap(s) collected)")
    return laps


def load_lap(path, with_flow: bool = True, with_exact: bool = True, info: dict | None = None) -> Lap:
    """One lap file; ``ValueError`` naming the file if it is damaged (its sha256 differs from ``info``'s, the
    manifest entry's, or its arrays do not load)."""
    path = Path(path)
    expected = (info or {}).get("sha256")
    if expected is not None and path.exists() and file_sha256(path) != expected:
        raise ValueError(f"{path}: damaged lap file (its sha256 differs from the manifest's); run collect again "
                         f"to fly that lap again")
    try:
        with np.load(path) as data:
            missing = [k for k in LAP_KEYS if k not in data.files]
            if missing:
                raise ValueError(f"missing arrays {missing}")
            has_exact = all(k in data.files for k in EXACT_KEYS)
            stored = "w_flown" in data.files
            states = data["states"]
            w_flown = data["w_flown"] if stored else flown_rates(states, timing.CONTROL_DT)
            lap = Lap(
                flow=data["flow"] if with_flow else None,
                q=data["q"], u=data["u"], states=states, target=data["target"],
                exact_flow=data["exact_flow"] if (with_exact and has_exact) else None,
                exact_valid=data["exact_valid"] if (with_exact and has_exact) else None,
                info={**_meta(data), **(info or {}), "w_flown_source": "stored" if stored else "states"},
                w_flown=w_flown,
                detections=({k: data[k] for k in DETECTION_KEYS} if all(k in data.files for k in DETECTION_KEYS)
                            else None),
            )
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: lap file listed in the manifest is missing; run collect again to "
                                f"re-collect it") from None
    except (ValueError, OSError, zipfile.BadZipFile, EOFError, KeyError) as err:
        raise ValueError(f"{path}: damaged lap file ({err}); delete it and run collect again to re-collect "
                         f"that lap") from err
    frames = lap.q.shape[0]
    if (lap.u.shape != (frames, 4) or lap.states.shape != (frames + 1, 10) or lap.target.shape != (frames + 1,)
            or lap.w_flown.shape != (frames, 3) or (lap.flow is not None and lap.flow.shape[0] != frames)):
        raise ValueError(f"{path}: inconsistent lap arrays (q {lap.q.shape}, u {lap.u.shape}, states "
                         f"{lap.states.shape}, target {lap.target.shape}); delete it and collect again")
    return lap


def load_laps(data_dir, split: str = "test", with_flow: bool = True, with_exact: bool = True) -> list[Lap]:
    """The laps of ``split`` ("train", "test" or "all"), with states and targets for evaluation."""
    root = Path(data_dir)
    manifest = read_manifest(root)
    return [load_lap(root / e["file"], with_flow, with_exact, info=e) for e in _split_laps(manifest, split, root)]


def load_dataset(data_dir, split: str = "train", input: str = "command") -> FlowData:
    """The ``split`` frames as :class:`FlowData`: q (F, 4) f32, u (F, 4) f32, flow (F, H, W, 2) f16.

    ``u`` is the DOF's control input of the variant ``input`` (:func:`control_input`): the command, or the
    rates flown over the frame with the commanded thrust. Datasets of format 1 (no stored flown rates) load
    either way. Filled lap by lap into one preallocated array (no transient second copy of the flows).
    """
    if input not in INPUTS:
        raise ValueError(f"input must be one of {INPUTS}, got {input!r}")
    root = Path(data_dir)
    manifest = read_manifest(root)
    entries = _split_laps(manifest, split, root)
    total = int(sum(e["frames"] for e in entries))
    W, H = manifest["image_size_wh"]
    q = np.empty((total, 4), np.float32)
    u = np.empty((total, 4), np.float32)
    flow = np.empty((total, H, W, 2), np.float16)
    start = 0
    for entry in entries:
        lap = load_lap(root / entry["file"], with_flow=True, with_exact=False, info=entry)
        n = lap.q.shape[0]
        if n != entry["frames"] or lap.flow.shape[1:] != (H, W, 2):
            raise ValueError(f"{root / entry['file']}: {n} frames of {lap.flow.shape[1:]} but the manifest says "
                             f"{entry['frames']} of {(H, W, 2)}; delete the lap file and collect again")
        q[start:start + n], u[start:start + n], flow[start:start + n] = lap.q, lap_input(lap, input), lap.flow
        start += n
    return FlowData(q, u, flow)


def camera_tilt_deg(manifest: Mapping) -> float:
    """The upward tilt (deg) of the camera a dataset was collected through, as its manifest's config records it
    (``camera_tilt_deg``); a dataset collected before the tilt was recorded: 0, the paper's camera."""
    return float(manifest["config"].get("camera_tilt_deg", 0.0))


def dataset_camera(manifest: Mapping) -> camera_lib.Camera:
    """The camera a dataset's frames, flows and detections were seen through: the paper's, tilted up by
    :func:`camera_tilt_deg`. What trains or evaluates on the dataset sees through it, not the default camera."""
    return camera_lib.default_camera(tilt=math.radians(camera_tilt_deg(manifest)))


def load_test_laps(data_dir: Path, manifest: dict, with_flow: bool = True) -> tuple[list[Lap], Any]:
    """The dataset's test laps (with their Farneback and exact flow unless ``with_flow`` is False) and the
    :class:`~pixelmpc_jax.sim.env.World` they were flown in, seen through the dataset's camera
    (:func:`dataset_camera`; it must render the images' size)."""
    from pixelmpc_jax.sim.env import make_world

    laps = load_laps(data_dir, "test", with_flow=with_flow, with_exact=with_flow)
    world = make_world(camera=dataset_camera(manifest))
    W, H = manifest["image_size_wh"]
    if (world.camera.width, world.camera.height) != (W, H):
        raise ValueError(f"{data_dir}: images are {W}x{H}, the camera renders {world.camera.width}x"
                         f"{world.camera.height}")
    return laps, world


def data_record(data_dir: Path, manifest: dict) -> dict:
    """Where the evaluated laps came from: the dataset, its test laps, the baseline's train laps."""
    return {
        "dir": str(data_dir),
        "test_laps": [{k: e[k] for k in ("lap", "speed", "seed", "frames", "end")} for e in
                      manifest["laps"] if e["split"] == "test"],
        "train_laps_for_baseline": [e["lap"] for e in manifest["laps"] if e["split"] == "train"],
        "collect_config": manifest["config"],
        "camera_tilt_deg": camera_tilt_deg(manifest),  # the camera the laps were seen through, and evaluated with
    }
