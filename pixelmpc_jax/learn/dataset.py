"""Self-supervised DOF data, the first loop of the paper's Algorithm 1: fly, render, compute optical flow.

Nominal MPPI laps (the racing cost only, ground-truth state) are flown on the AlphaPilot course at target
speeds spread over 6-14 m/s across laps. Every 1/40 s tick of a lap is rendered (``render_batch``, one
compiled chunk size), Farneback flow (the paper's parameters) is computed between consecutive grey
frames, and each flow frame ``t`` is stored with the orientation ``q_t``, the control ``u_t`` applied
between ``t`` and ``t + 1``, the body rates actually flown between ``t`` and ``t + 1``, the full state and
the target gate.

The command is not what the camera turns by: the plant's rate loop flies it with a slope of about 0.65 and
a lag of about 0.11 s, so a frame's flow paired with its tick's command shows a diluted, delayed response.
``w_flown[t]`` is the mean body rate over the frame interval, ``2 log(q_t^-1 q_{t+1}) / dt``: the rotation
the camera made between the two frames, which is the noise-free gyro preintegrated over the tick (the
plant integrates the attitude with the true rates, the filter preintegrates the gyro the same way). The
MPC's robot model assumes the commanded rates are flown at once, so a pixel model trained on ``w_flown``
(``input="flown"``) answers the question the MPC asks of it.

With ``CollectConfig.excitation`` the TRAIN laps add held rate pulses and dither to the nominal MPPI's
body-rate command (:func:`excited_policy`, within the rate bounds), so the flown rates vary independently
of the attitude and the place on the course; the test laps stay nominal (the flight the DOF serves).

On disk, one directory::

    manifest.json          config, split, per-lap summary, versions (rewritten atomically after each lap)
    lap_000.npz ...        one lap each, written atomically (temp file + os.replace):
        flow         (F, H, W, 2) float16  Farneback flow t -> t+1, pixels per frame, flow[y, x] = (du, dv)
        q, u         (F, 4) float32        orientation at t, control applied between t and t+1
        w_flown      (F, 3) float32        mean body rate flown between t and t+1 (rad/s; format 2)
        rates        (F + 1, 3) float32    true body rates at every rendered frame (rad/s; format 2)
        states       (F + 1, 10) float32   true state at every rendered frame
        target       (F + 1,) int32        target gate index at every rendered frame
        exact_flow   (F, H, W, 2) float16  exact flow from depth + poses (test laps only by default)
        exact_valid  (F, H, W) bool        where the exact flow is defined (in front, inside the image)

The exact flow is stored for the test laps only (``CollectConfig.exact_flow = "test"``): training uses
the Farneback flow alone (the paper's self-supervision), the exact flow only serves evaluation, and
storing it for every lap would more than double the dataset for nothing. It is cheap to compute (one
reprojection of the rendered depth), so ``"all"`` is there for experiments that want it.

A lap file that exists is complete (atomic writes), so ``collect`` resumes: laps already on disk are
skipped, and Ctrl-C loses at most the lap in progress. The manifest records each lap file's sha256; a file
whose bytes no longer match (or, without a recorded checksum, whose archive fails its CRC check) is flown
again by ``collect`` and refused by the loaders. Lap files of format 1 (no ``w_flown``) still load:
their flown rates are derived from the stored states, which is the same computation.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import os
import shlex
import sys
import tempfile
import time
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import strict_json
from pixelmpc_jax.learn.train import INPUTS, FlowData
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.sim import controllers
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.world import render as render_lib
from pixelmpc_jax.world import track as track_lib

DATASET_FORMAT = "pixelmpc_jax.flow_dataset"
DATASET_VERSION = 2
MANIFEST = "manifest.json"
LAP_KEYS = ("flow", "q", "u", "states", "target")  # format 1 and later; format 2 adds FLOWN_KEYS
FLOWN_KEYS = ("w_flown", "rates")
FLOWN_RATES = ("w_flown[t] = 2 log(q_t^-1 q_{t+1}) / dt: the mean body rate flown over the frame interval "
               "(the noise-free gyro, preintegrated over the tick)")
EXACT_KEYS = ("exact_flow", "exact_valid")
# End causes after which the last logged state lies past the impact (its frame pair is dropped).
_COLLISION_CAUSES = (track_lib.CRASH_GATE, track_lib.CRASH_GROUND, track_lib.CRASH_WALL)


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    """What to collect. The default is laptop-sized (4 laps of at most 10 s, a few minutes on a CPU);
    :meth:`paper` is the paper's size (10 rounds of ~30 s, 6-14 m/s).

    Attributes:
        laps: number of laps flown.
        speed_min, speed_max: target speeds (m/s), spread linearly over the laps (one lap: their mean).
        seed: lap ``i`` uses PRNG key ``seed + i`` (plant noise and controller).
        test_every: without ``test_laps``, lap ``i`` is a test lap when ``i % test_every == test_every // 2``
            (the middle of each block: interior speeds), or the last lap if that selects none of >= 2 laps.
        test_laps: explicit test lap indices (overrides ``test_every``).
        max_lap_time_s: a lap is cut off (a timeout) after this much flight.
        supersample: renderer sub-samples per pixel side (1: none). 1 is the default: the texture is
            band-limited to the pixel grid anyway, and on the course Farneback's error against the exact
            flow is the same at 1 and 3 (0.53 vs 0.55 px, 30 frame pairs at 12 m/s), 5x cheaper.
        render_batch: poses per compiled ``render_batch`` call (the last chunk is padded: one compile).
        exact_flow: ``"test"`` (exact flow for test laps only) or ``"all"``.
        num_samples: MPPI samples of the nominal controller (``controllers.make_policy("mppi", ...)``).
        excitation: add held rate pulses and dither to the body-rate command of the TRAIN laps
            (:func:`excited_policy`); test laps stay nominal.
        excitation_pulse_rad_s: a pulse's amplitude is uniform in +- this, per axis (rad/s).
        excitation_hold_s: a pulse is held for a time uniform in [hold / 3, hold] (s).
        excitation_gap_s: mean time between the end of one pulse and the start of the next, per axis (s).
        excitation_dither_rad_s: std of the white dither added every tick, per axis (rad/s).
    """

    laps: int = 4
    speed_min: float = 6.0
    speed_max: float = 14.0
    seed: int = 0
    test_every: int = 5
    test_laps: tuple[int, ...] | None = None
    max_lap_time_s: float = 10.0
    supersample: int = 1
    render_batch: int = 32
    exact_flow: str = "test"
    num_samples: int = 512
    excitation: bool = False
    excitation_pulse_rad_s: float = 1.5
    excitation_hold_s: float = 0.3
    excitation_gap_s: float = 0.5
    excitation_dither_rad_s: float = 0.3

    def __post_init__(self):
        if int(self.laps) < 1:
            raise ValueError(f"CollectConfig.laps must be >= 1, got {self.laps}")
        if not (0 < self.speed_min <= self.speed_max):
            raise ValueError(f"CollectConfig needs 0 < speed_min <= speed_max, got {self.speed_min}, {self.speed_max}")
        if int(self.test_every) < 1:
            raise ValueError(f"CollectConfig.test_every must be >= 1, got {self.test_every}")
        if self.test_laps is not None:
            object.__setattr__(self, "test_laps", tuple(int(i) for i in self.test_laps))
            bad = [i for i in self.test_laps if not 0 <= i < self.laps]
            if bad:
                raise ValueError(f"CollectConfig.test_laps must be lap indices in [0, {self.laps}), got {bad}")
        if not self.max_lap_time_s > 0:
            raise ValueError(f"CollectConfig.max_lap_time_s must be > 0, got {self.max_lap_time_s}")
        if int(self.supersample) < 1 or int(self.supersample) % 2 == 0:
            raise ValueError(f"CollectConfig.supersample must be odd and >= 1, got {self.supersample}")
        if int(self.render_batch) < 1 or int(self.num_samples) < 1:
            raise ValueError("CollectConfig.render_batch and num_samples must be >= 1")
        if self.exact_flow not in ("test", "all"):
            raise ValueError(f"CollectConfig.exact_flow must be 'test' or 'all', got {self.exact_flow!r}")
        if not (self.excitation_pulse_rad_s >= 0 and self.excitation_dither_rad_s >= 0
                and self.excitation_hold_s >= 3 * episode_lib.CONTROL_DT and self.excitation_gap_s > 0):
            raise ValueError("CollectConfig excitation: pulse and dither amplitudes must be >= 0, the hold at "
                             f"least {3 * episode_lib.CONTROL_DT:g} s and the gap > 0")

    @classmethod
    def paper(cls, **overrides) -> CollectConfig:
        """The paper's data (Sec. V): 10 rounds of ~30 s of nominal MPPI flight, 6-14 m/s."""
        return cls(**{"laps": 10, "max_lap_time_s": 30.0, **overrides})

    def speeds(self) -> list[float]:
        """Target speed of every lap (m/s)."""
        if self.laps == 1:
            return [0.5 * (self.speed_min + self.speed_max)]
        return [float(s) for s in np.linspace(self.speed_min, self.speed_max, self.laps)]

    def seeds(self) -> list[int]:
        return [self.seed + i for i in range(self.laps)]

    def test_indices(self) -> list[int]:
        if self.test_laps is not None:
            return sorted(set(self.test_laps))
        chosen = [i for i in range(self.laps) if i % self.test_every == self.test_every // 2]
        if not chosen and self.laps >= 2:
            chosen = [self.laps - 1]
        return chosen

    def split_of(self, lap: int) -> str:
        return "test" if lap in self.test_indices() else "train"

    def to_json(self) -> dict:
        data = dataclasses.asdict(self)
        data["test_laps"] = None if self.test_laps is None else list(self.test_laps)
        return data

    def excited(self, lap: int) -> bool:
        """Lap ``lap`` is flown with excitation (train laps of an excited collection)."""
        return bool(self.excitation) and self.split_of(lap) == "train"

    def excitation_params(self) -> tuple[float, float, float, float]:
        return (float(self.excitation_pulse_rad_s), float(self.excitation_hold_s), float(self.excitation_gap_s),
                float(self.excitation_dither_rad_s))


def _same_config(recorded: dict | None, config: CollectConfig) -> bool:
    """A manifest's recorded config equals ``config``; fields added since it was written count at their
    defaults (a format-1 dataset, collected without excitation, still resumes and is reused)."""
    if recorded is None:
        return False
    defaults = {f.name: f.default for f in dataclasses.fields(CollectConfig)}
    return {**strict_json.json_safe(defaults), **recorded} == strict_json.json_safe(config.to_json())


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


def flown_rates(states: np.ndarray, dt: float = episode_lib.CONTROL_DT) -> np.ndarray:
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
# Collection.
# --------------------------------------------------------------------------------------------------


def lap_filename(index: int) -> str:
    return f"lap_{index:03d}.npz"


@functools.lru_cache(maxsize=4)
def _cached_runner(num_samples: int, max_time_s: float, excitation: tuple | None = None) -> episode_lib.Runner:
    """The nominal MPPI episode runner (current ``controllers.make_policy`` defaults), compiled once per size;
    with ``excitation`` (``CollectConfig.excitation_params()``) wrapped in :func:`excited_policy`."""
    policy = controllers.make_policy("mppi", num_samples=num_samples)
    if excitation is not None:
        policy = excited_policy(policy, *excitation, num_samples=num_samples)
    return episode_lib.make_runner(policy, episode_lib.EpisodeConfig(max_time_s=max_time_s))


class ExcitationState(NamedTuple):
    """Per-axis held pulse (3,) rad/s, ticks it has left (3,) int32, and the key."""

    pulse: jax.Array
    remaining: jax.Array
    key: jax.Array


def excited_policy(base: episode_lib.Policy, pulse_rad_s: float = 1.5, hold_s: float = 0.3, gap_s: float = 0.5,
                   dither_rad_s: float = 0.3, num_samples: int = 512) -> episode_lib.Policy:
    """``base`` with held rate pulses and dither added to its body-rate command (thrust untouched).

    Per axis and tick: an idle axis starts a pulse with probability ``dt / gap_s``, of amplitude uniform in
    ``+-pulse_rad_s``, held for a time uniform in ``[hold_s / 3, hold_s]``; white dither of std
    ``dither_rad_s`` is added on top. The result is clipped to the MPPI's rate bounds. The controller keeps
    acting on the true state, so it flies the perturbation out; the data see the rates move independently of
    the attitude and the place on the course.
    """
    dt = episode_lib.CONTROL_DT
    bounds = episode_lib.paper_mppi_config(num_samples=num_samples)
    lo, hi = jnp.asarray(bounds.u_min[:3], jnp.float32), jnp.asarray(bounds.u_max[:3], jnp.float32)
    hold_max = max(int(round(hold_s / dt)), 3)
    hold_min = max(hold_max // 3, 1)
    start_probability = min(dt / gap_s, 1.0)

    def init(key):
        key_base, key_exc = jax.random.split(key)
        return (base.init(key_base),
                ExcitationState(jnp.zeros(3, jnp.float32), jnp.zeros(3, jnp.int32), key_exc))

    def act(state, obs, world):
        base_state, exc = state
        u, base_state, prediction = base.act(base_state, obs, world)
        key, key_start, key_amp, key_hold, key_dither = jax.random.split(exc.key, 5)
        start = (exc.remaining <= 0) & (jax.random.uniform(key_start, (3,)) < start_probability)
        amplitude = jax.random.uniform(key_amp, (3,), minval=-pulse_rad_s, maxval=pulse_rad_s)
        hold = jax.random.randint(key_hold, (3,), hold_min, hold_max + 1)
        remaining = jnp.where(start, hold, jnp.maximum(exc.remaining - 1, 0))
        pulse = jnp.where(start, amplitude, jnp.where(remaining > 0, exc.pulse, 0.0))
        dither = dither_rad_s * jax.random.normal(key_dither, (3,))
        rates = jnp.clip(u[:3] + (pulse + dither).astype(u.dtype), lo.astype(u.dtype), hi.astype(u.dtype))
        u = jnp.concatenate([rates, u[3:]])
        return u, (base_state, ExcitationState(pulse.astype(jnp.float32), remaining.astype(jnp.int32), key)), \
            prediction

    return episode_lib.Policy(init=init, act=act, name=f"{base.name}+excitation")


def _versions() -> dict:
    import cv2
    import flax

    return {"jax": jax.__version__, "flax": flax.__version__, "numpy": np.__version__, "opencv": cv2.__version__}


def _controller_source() -> dict:
    """sha256 (first 16 hex) of the controller's source files: the nominal MPPI's defaults change with them."""
    import hashlib

    from pixelmpc_jax.control import costs

    return {Path(m.__file__).name: hashlib.sha256(Path(m.__file__).read_bytes()).hexdigest()[:16]
            for m in (episode_lib, costs, controllers)}


def _save_npz_atomic(path: Path, arrays: dict) -> None:
    """``np.savez_compressed`` through a temporary file in the same directory and ``os.replace``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def file_sha256(path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _verified_lap(path: Path, expected_sha256: str | None = None) -> str | None:
    """The sha256 of an intact lap file, or None when it is missing or damaged (then it is flown again).

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


def _lap_summary(path: Path) -> dict:
    with np.load(path) as data:
        return {k: data[k].item() for k in data.files if k.startswith("meta_")}


def fly_lap(world: episode_lib.World, seed: int, runner: episode_lib.Runner) -> tuple[np.ndarray, np.ndarray,
                                                                                    np.ndarray, dict]:
    """Fly one lap; returns states (F + 1, 10), controls (F, 4), targets (F + 1,) and a summary (its
    ``rates`` entry: the true body rates (F + 1, 3) at each state).

    After a collision the last state lies past the impact: that tick is dropped.
    """
    log = metrics_lib.unbatch(runner.single(world, jax.random.PRNGKey(seed)))[0]
    n = int(log.num_ticks)
    cause = int(log.end_cause)
    frames = n - 1 if (cause in _COLLISION_CAUSES and not bool(log.finished)) else n
    frames = max(frames, 0)
    summary = {
        "ticks_flown": n,
        "frames": frames,
        "flight_time_s": n * episode_lib.CONTROL_DT,
        "end": "finished" if bool(log.finished) else episode_lib.END_NAMES.get(cause, str(cause)),
        "gates_passed": int(log.gates_passed),
        "finished": bool(log.finished),
        "rates": np.asarray(log.body_rates[: frames + 1], np.float32),
    }
    return (np.asarray(log.states[: frames + 1], np.float32), np.asarray(log.controls[:frames], np.float32),
            np.asarray(log.target[: frames + 1], np.int32), summary)


def render_lap(world: episode_lib.World, states: np.ndarray, config: CollectConfig, with_depth: bool,
               bar=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Grey frames (F + 1, H, W) uint8 and, with ``with_depth``, depth (F + 1, H, W) float32 of ``states``.

    Poses go through ``render_batch`` in chunks of ``config.render_batch``; the last chunk is padded with
    its last pose so every call has one shape (compiled once).
    """
    chunk = int(config.render_batch)
    greys, depths = [], []
    for start in range(0, states.shape[0], chunk):
        xs = states[start:start + chunk]
        count = xs.shape[0]
        if count < chunk:
            xs = np.concatenate([xs, np.repeat(xs[-1:], chunk - count, axis=0)])
        frame = render_lib.render_batch(world.track, jnp.asarray(xs), world.camera,
                                        supersample=int(config.supersample), chunk=1)
        greys.append(np.asarray(frame.grey)[:count])
        if with_depth:
            depths.append(np.asarray(frame.depth)[:count])
        if bar is not None:
            bar.update(count)
    return np.concatenate(greys), (np.concatenate(depths) if with_depth else None)


_exact_flow_batch = jax.jit(jax.vmap(render_lib.exact_flow, in_axes=(0, 0, 0, None)))


def lap_arrays(world: episode_lib.World, states: np.ndarray, controls: np.ndarray, targets: np.ndarray,
               config: CollectConfig, with_exact: bool, bar=None, rates: np.ndarray | None = None) -> dict:
    """Render a flown lap and compute its flows: the arrays of one lap file (see the module docstring).
    ``rates``: the true body rates (F + 1, 3) at each state, stored when given."""
    frames = controls.shape[0]
    grey, depth = render_lap(world, states, config, with_exact, bar)
    H, W = grey.shape[1:]
    flow = np.empty((frames, H, W, 2), np.float16)
    for t in range(frames):
        flow[t] = flow_lib.farneback(grey[t], grey[t + 1], shape=None)
    arrays = {"flow": flow, "q": states[:frames, 3:7].copy(), "u": controls, "states": states, "target": targets,
              "w_flown": flown_rates(states, episode_lib.CONTROL_DT)}
    if rates is not None:
        arrays["rates"] = np.asarray(rates, np.float32)
    if with_exact:
        exact = np.empty((frames, H, W, 2), np.float16)
        valid = np.empty((frames, H, W), bool)
        chunk = int(config.render_batch)
        for start in range(0, frames, chunk):
            stop = min(start + chunk, frames)
            f, v = _exact_flow_batch(jnp.asarray(states[start:stop]), jnp.asarray(states[start + 1:stop + 1]),
                                     jnp.asarray(depth[start:stop]), world.camera)
            exact[start:stop], valid[start:stop] = np.asarray(f), np.asarray(v)
        arrays["exact_flow"], arrays["exact_valid"] = exact, valid
    return arrays


def _read_manifest(root: Path) -> dict | None:
    import json

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


def collect(out_dir, config: CollectConfig = CollectConfig(), progress: bool = True,
            policy: episode_lib.Policy | None = None) -> dict:
    """Collect (or resume collecting) a DOF dataset into ``out_dir``; returns the manifest.

    Args:
        out_dir: the dataset directory (created). A directory collected with another config is refused.
        config: what to collect.
        progress: tqdm progress bars (laps; frames of the lap in progress).
        policy: a controller overriding the nominal MPPI from ``controllers.make_policy`` (tests; its name is
            recorded in the manifest).

    Returns:
        The manifest (also in ``out_dir/manifest.json``); ``manifest["complete"]`` is False after a
        Ctrl-C, which keeps every finished lap (run again to resume), and ``manifest["interrupted"]`` (not
        stored) says whether this call was interrupted.
    """
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    previous = _read_manifest(root)
    policy_name = policy.name if policy is not None else "mppi"
    if previous is not None and (not _same_config(previous.get("config"), config)
                                 or previous.get("policy") != policy_name):
        raise ValueError(f"{root} holds a dataset collected with another config ({previous.get('config')}, policy "
                         f"{previous.get('policy')!r}); use a new directory or the same config to resume")
    if policy is not None:
        nominal = episode_lib.make_runner(policy, episode_lib.EpisodeConfig(max_time_s=config.max_lap_time_s))
        excitation = config.excitation_params()
        runners = {False: nominal,
                   True: episode_lib.make_runner(excited_policy(policy, *excitation,
                                                                num_samples=config.num_samples),
                                                 episode_lib.EpisodeConfig(max_time_s=config.max_lap_time_s))
                   if config.excitation else None}
    else:
        runners = {False: None, True: None}

    def runner_for(lap: int) -> episode_lib.Runner:
        excited = config.excited(lap)
        if runners[excited] is None:
            runners[excited] = _cached_runner(int(config.num_samples), float(config.max_lap_time_s),
                                              config.excitation_params() if excited else None)
        return runners[excited]
    base = episode_lib.make_world()
    speeds, seeds = config.speeds(), config.seeds()
    manifest = {
        "format": DATASET_FORMAT,
        "format_version": DATASET_VERSION,
        "config": config.to_json(),
        "policy": policy_name,
        "mppi_config": dataclasses.asdict(episode_lib.paper_mppi_config(num_samples=config.num_samples))
        if policy is None else None,
        "image_size_wh": [int(base.camera.width), int(base.camera.height)],
        "frame_dt_s": episode_lib.CONTROL_DT,
        "flown_rates": FLOWN_RATES,
        "excited_laps": [i for i in range(config.laps) if config.excited(i)],
        "farneback": {k: v for k, v in flow_lib.FARNEBACK_PARAMS.items()},
        "split": {"train": [i for i in range(config.laps) if config.split_of(i) == "train"],
                  "test": config.test_indices()},
        "laps": [],
        "frames": {"train": 0, "test": 0},
        "versions": _versions(),
        "controller_source_sha256": _controller_source() if policy is None else None,
        "command": shlex.join(sys.argv),
        "created": (previous or {}).get("created", datetime.datetime.now().isoformat(timespec="seconds")),
        "complete": False,
    }
    if previous is not None and previous.get("format_version", 1) != DATASET_VERSION:
        manifest["format_version"] = previous.get("format_version", 1)  # laps of mixed formats: the oldest
    manifest = strict_json.json_safe(manifest)
    recorded_sha256 = {e["lap"]: e.get("sha256") for e in (previous or {}).get("laps", [])}
    done: dict[int, dict] = {}
    bar = frames_bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.laps, desc="collect", unit="lap")
    t0 = time.perf_counter()
    interrupted = False
    try:
        for lap in range(config.laps):
            path = root / lap_filename(lap)
            split = config.split_of(lap)
            digest = _verified_lap(path, recorded_sha256.get(lap))
            if digest is not None:
                done[lap] = _lap_entry(lap, path, split, _lap_summary(path), digest)
                if bar is not None:
                    bar.update(1)
                continue
            if path.exists():
                print(f"{path}: damaged (its checksum does not match); flying lap {lap} again", file=sys.stderr)
            world = base.replace(target_speed=jnp.asarray(speeds[lap], jnp.float32))
            if bar is not None:
                bar.set_postfix(lap=lap, speed=f"{speeds[lap]:.1f}", stage="fly")
            states, controls, targets, summary = fly_lap(world, seeds[lap], runner_for(lap))
            rates = summary.pop("rates")
            if summary["frames"] < 1:
                raise RuntimeError(f"lap {lap} (seed {seeds[lap]}, {speeds[lap]:.1f} m/s) ended before a single "
                                   f"frame pair ({summary['end']}); nothing to store")
            if bar is not None:
                from tqdm.auto import tqdm

                bar.set_postfix(lap=lap, speed=f"{speeds[lap]:.1f}", stage="render+flow")
                frames_bar = tqdm(total=states.shape[0], desc=f"lap {lap} frames", unit="frame", leave=False)
            with_exact = config.exact_flow == "all" or split == "test"
            arrays = lap_arrays(world, states, controls, targets, config, with_exact, frames_bar, rates)
            if frames_bar is not None:
                frames_bar.close()
                frames_bar = None
            meta = {"lap": lap, "split": split, "speed": speeds[lap], "seed": seeds[lap],
                    "excited": config.excited(lap), **summary}
            arrays.update({f"meta_{k}": np.asarray(v) for k, v in meta.items()})
            _save_npz_atomic(path, arrays)
            done[lap] = _lap_entry(lap, path, split, _lap_summary(path), file_sha256(path))
            _write_manifest(root, manifest, done, config, complete=False)
            if bar is not None:
                bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        print(f"\ninterrupted: keeping the {len(done)} finished lap(s) in {root}; run again to resume")
    finally:
        if frames_bar is not None:
            frames_bar.close()
        if bar is not None:
            bar.close()
    manifest = _write_manifest(root, manifest, done, config, complete=not interrupted and len(done) == config.laps)
    manifest["wall_s_this_call"] = time.perf_counter() - t0
    manifest["interrupted"] = interrupted
    return manifest


def _lap_entry(lap: int, path: Path, split: str, meta: dict, sha256: str) -> dict:
    entry = {k.removeprefix("meta_"): v for k, v in meta.items()}
    entry.update({"lap": lap, "file": path.name, "split": split, "bytes": path.stat().st_size, "sha256": sha256})
    return entry


def _write_manifest(root: Path, manifest: dict, done: dict[int, dict], config: CollectConfig,
                    complete: bool) -> dict:
    manifest = dict(manifest)
    manifest["laps"] = [done[i] for i in sorted(done)]
    manifest["frames"] = {s: int(sum(e["frames"] for e in manifest["laps"] if e["split"] == s))
                          for s in ("train", "test")}
    manifest["bytes"] = int(sum(e["bytes"] for e in manifest["laps"]))
    manifest["complete"] = bool(complete)
    manifest["updated"] = datetime.datetime.now().isoformat(timespec="seconds")
    strict_json.write_json_atomic(root / MANIFEST, strict_json.json_safe(manifest))
    return manifest


# --------------------------------------------------------------------------------------------------
# Loading.
# --------------------------------------------------------------------------------------------------


def read_manifest(data_dir) -> dict:
    """The dataset's manifest; ``FileNotFoundError`` / ``ValueError`` naming what is wrong."""
    root = Path(data_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"no DOF dataset at {root}: the directory does not exist "
                                f"(collect one with `pixelmpc collect --out {root}` or learn.dataset.collect)")
    manifest = _read_manifest(root)
    if manifest is None:
        raise FileNotFoundError(f"no DOF dataset at {root}: {MANIFEST} is missing "
                                f"(collect one with `pixelmpc collect --out {root}` or learn.dataset.collect)")
    return manifest


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
            meta = {k.removeprefix("meta_"): data[k].item() for k in data.files if k.startswith("meta_")}
            has_exact = all(k in data.files for k in EXACT_KEYS)
            stored = "w_flown" in data.files
            states = data["states"]
            w_flown = data["w_flown"] if stored else flown_rates(states, episode_lib.CONTROL_DT)
            lap = Lap(
                flow=data["flow"] if with_flow else None,
                q=data["q"], u=data["u"], states=states, target=data["target"],
                exact_flow=data["exact_flow"] if (with_exact and has_exact) else None,
                exact_valid=data["exact_valid"] if (with_exact and has_exact) else None,
                info={**meta, **(info or {}), "w_flown_source": "stored" if stored else "states"},
                w_flown=w_flown,
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
    """The ``split`` frames as train.py's :class:`FlowData`: q (F, 4) f32, u (F, 4) f32, flow (F, H, W, 2) f16.

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


# --------------------------------------------------------------------------------------------------
# The `pixelmpc collect` entry point.
# --------------------------------------------------------------------------------------------------


def run_collect(out_dir, laps: int = 4, seed: int = 0, max_lap_time_s: float = 10.0, speed_min: float = 6.0,
                speed_max: float = 14.0, supersample: int = 1, test_laps: Sequence[int] | None = None,
                paper: bool = False, progress: bool = True, excitation: bool = False,
                excitation_pulse_rad_s: float = 1.5, excitation_dither_rad_s: float = 0.3) -> dict:
    """Collect a dataset and print a short summary. ``paper=True`` starts from :meth:`CollectConfig.paper`
    (10 laps of 30 s) and ignores ``laps`` and ``max_lap_time_s``. ``excitation``: held rate pulses and
    dither on the train laps (see :func:`excited_policy`)."""
    fields = dict(seed=seed, speed_min=speed_min, speed_max=speed_max, supersample=supersample,
                  test_laps=None if test_laps is None else tuple(test_laps), excitation=bool(excitation),
                  excitation_pulse_rad_s=float(excitation_pulse_rad_s),
                  excitation_dither_rad_s=float(excitation_dither_rad_s))
    config = (CollectConfig.paper(**fields) if paper
              else CollectConfig(laps=laps, max_lap_time_s=max_lap_time_s, **fields))
    manifest = collect(out_dir, config, progress=progress)
    print(summarise_manifest(manifest, out_dir))
    return manifest


def summarise_manifest(manifest: dict, data_dir=None) -> str:
    laps = manifest["laps"]
    lines = [f"dataset {data_dir or ''}: {len(laps)}/{manifest['config']['laps']} laps, "
             f"{manifest['frames']['train']} train + {manifest['frames']['test']} test frames, "
             f"{manifest.get('bytes', 0) / 1e6:.0f} MB{'' if manifest['complete'] else ' (incomplete: run again)'}"]
    for e in laps:
        lines.append(f"  lap {e['lap']:>2} {e['split']:>5}  {e['speed']:5.1f} m/s  seed {e['seed']:>5}  "
                     f"{e['frames']:>5} frames  {e['flight_time_s']:5.1f} s  {e['gates_passed']:>2} gates  {e['end']}"
                     f"{'  excited' if e.get('excited') else ''}")
    return "\n".join(lines)
