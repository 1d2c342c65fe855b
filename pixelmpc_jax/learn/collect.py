"""Self-supervised DOF data, the first loop of the paper's Algorithm 1: fly, render, compute optical flow.

Nominal MPPI laps (the racing cost only, ground-truth state) are flown on the AlphaPilot course at target
speeds spread over 6-14 m/s across laps (``speed_min``, ``speed_max``: up to the racing pace, 16 m/s), seen through
the paper's camera or one tilted up on its mount (``camera_tilt_deg``: the racing camera; the manifest's ``config``
records it, and whatever trains or evaluates on the dataset sees through it, ``dataset.dataset_camera``).
Every 1/40 s tick of a lap is rendered (``render_batch``, one compiled chunk size), Farneback flow (the paper's
parameters) is computed between consecutive grey frames, and each flow frame ``t`` is stored with the orientation
``q_t``, the control ``u_t`` applied between ``t`` and ``t + 1``, the body rates actually flown between ``t`` and
``t + 1``, the full state and the target gate (the files: :mod:`pixelmpc_jax.learn.dataset`).

With ``CollectConfig.excitation`` the TRAIN laps add held rate pulses and dither to the nominal MPPI's
body-rate command (:func:`excited_policy`, within the rate bounds), so the flown rates vary independently
of the attitude and the place on the course; the test laps stay nominal (the flight the DOF serves).

The exact flow is stored for the test laps only (``CollectConfig.exact_flow = "test"``): training uses
the Farneback flow alone (the paper's self-supervision), the exact flow only serves evaluation, and
storing it for every lap would more than double the dataset for nothing. It is cheap to compute (one
reprojection of the rendered depth), so ``"all"`` is there for experiments that want it.

A lap file that exists is complete (atomic writes), so ``collect`` resumes: laps already on disk are
skipped, and Ctrl-C loses at most the lap in progress. A file whose bytes no longer match the manifest's
sha256 (or, without a recorded checksum, whose archive fails its CRC check) is flown again.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import devices, platform_info, strict_json, timing
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.settings import CAMERA_TILT_RANGE, Range, check, setting
from pixelmpc_jax.sim import controllers, policies
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import render as render_lib
from pixelmpc_jax.world import track as track_lib

# End causes after which the last logged state lies past the impact (its frame pair is dropped).
_COLLISION_CAUSES = (track_lib.CRASH_GATE, track_lib.CRASH_GROUND, track_lib.CRASH_WALL)
# m/s, a collected lap's target speed: up to past the racing pace (14-16 m/s), below the vehicle's top speed (~19 m/s)
COLLECT_SPEED_RANGE = Range(0.0, 18.0, lo_open=True, unit="m/s")


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    """What to collect. The default is laptop-sized (4 laps of at most 10 s, a few minutes on a CPU);
    :meth:`paper` is the paper's size (10 rounds of ~30 s, 6-14 m/s).

    Attributes:
        laps: number of laps flown.
        speed_min, speed_max: target speeds (m/s), spread linearly over the laps (one lap: their mean), in
            :data:`COLLECT_SPEED_RANGE`.
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
        camera_tilt_deg: the camera's upward tilt on its mount (deg, in ``settings.CAMERA_TILT_RANGE``; 0: the
            paper's camera): the frames, flows and detections are the tilted camera's (:meth:`camera`).
    """

    laps: int = 4
    speed_min: float = setting(6.0, range=COLLECT_SPEED_RANGE, help="the slowest lap's target speed, in {range}")
    speed_max: float = setting(14.0, range=COLLECT_SPEED_RANGE, help="the fastest lap's target speed, in {range}")
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
    camera_tilt_deg: float = setting(0.0, range=CAMERA_TILT_RANGE,
                                     help="the camera tilted up on its mount by DEG degrees (0: the paper's; racing "
                                          "drones: 20-50), in {range}")

    def __post_init__(self):
        check(self)  # the speeds and the camera's tilt, each in its field's range
        if int(self.laps) < 1:
            raise ValueError(f"CollectConfig.laps must be >= 1, got {self.laps}")
        if not self.speed_min <= self.speed_max:
            raise ValueError(f"CollectConfig needs speed_min <= speed_max, got {self.speed_min}, {self.speed_max}")
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
                and self.excitation_hold_s >= 3 * timing.CONTROL_DT and self.excitation_gap_s > 0):
            raise ValueError("CollectConfig excitation: pulse and dither amplitudes must be >= 0, the hold at "
                             f"least {3 * timing.CONTROL_DT:g} s and the gap > 0")

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

    def camera(self) -> camera_lib.Camera:
        """The camera the laps are seen through: the paper's, tilted up by ``camera_tilt_deg``."""
        return camera_lib.default_camera(tilt=math.radians(self.camera_tilt_deg))

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


@functools.lru_cache(maxsize=4)
def _cached_runner(num_samples: int, max_time_s: float, excitation: tuple | None = None) -> episode_lib.Runner:
    """The nominal MPPI episode runner (``controllers.make_policy("mppi", ...)`` on the paper's MPPI settings at
    ``num_samples`` and the default racing cost), compiled once per size; with ``excitation``
    (``CollectConfig.excitation_params()``) wrapped in :func:`excited_policy`."""
    policy = controllers.make_policy("mppi", ControllerConfig(mppi=paper_mppi_config(num_samples=num_samples)))
    if excitation is not None:
        policy = excited_policy(policy, *excitation, num_samples=num_samples)
    return episode_lib.make_runner(policy, episode_lib.EpisodeConfig(max_time_s=max_time_s))


class ExcitationState(NamedTuple):
    """Per-axis held pulse (3,) rad/s, ticks it has left (3,) int32, and the key."""

    pulse: jax.Array
    remaining: jax.Array
    key: jax.Array


def excited_policy(base: policies.Policy, pulse_rad_s: float = 1.5, hold_s: float = 0.3, gap_s: float = 0.5,
                   dither_rad_s: float = 0.3, num_samples: int = 512) -> policies.Policy:
    """``base`` with held rate pulses and dither added to its body-rate command (thrust untouched).

    Per axis and tick: an idle axis starts a pulse with probability ``dt / gap_s``, of amplitude uniform in
    ``+-pulse_rad_s``, held for a time uniform in ``[hold_s / 3, hold_s]``; white dither of std
    ``dither_rad_s`` is added on top. The result is clipped to the MPPI's rate bounds. The controller keeps
    acting on the true state, so it flies the perturbation out; the data see the rates move independently of
    the attitude and the place on the course.
    """
    dt = timing.CONTROL_DT
    bounds = paper_mppi_config(num_samples=num_samples)
    lo, hi = jnp.asarray(bounds.u_min[:3], jnp.float32), jnp.asarray(bounds.u_max[:3], jnp.float32)
    hold_max = max(int(round(hold_s / dt)), 3)
    hold_min = max(hold_max // 3, 1)
    start_probability = min(dt / gap_s, 1.0)

    def init(key, world):
        key_base, key_exc = jax.random.split(key)
        return (base.init(key_base, world),
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

    return policies.Policy(init=init, act=act, name=f"{base.name}+excitation",
                           compiler_options=base.compiler_options)


def _versions() -> dict:
    import cv2
    import flax

    return {"jax": jax.__version__, "flax": flax.__version__, "numpy": np.__version__, "opencv": cv2.__version__}


def _controller_source() -> dict:
    """sha256 (first 16 hex) of the controller's source files: the nominal MPPI's defaults change with them."""
    from pixelmpc_jax.control import costs

    return {Path(m.__file__).name: hashlib.sha256(Path(m.__file__).read_bytes()).hexdigest()[:16]
            for m in (episode_lib, env_lib, policies, costs, controllers)}


def fly_lap(world: env_lib.World, seed: int, runner: episode_lib.Runner) -> tuple[np.ndarray, np.ndarray,
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
        "flight_time_s": n * timing.CONTROL_DT,
        "end": "finished" if bool(log.finished) else env_lib.END_NAMES.get(cause, str(cause)),
        "gates_passed": int(log.gates_passed),
        "finished": bool(log.finished),
        "rates": np.asarray(log.body_rates[: frames + 1], np.float32),
    }
    return (np.asarray(log.states[: frames + 1], np.float32), np.asarray(log.controls[:frames], np.float32),
            np.asarray(log.target[: frames + 1], np.int32), summary)


def render_lap(world: env_lib.World, states: np.ndarray, config: CollectConfig, with_depth: bool,
               bar=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Grey frames (F + 1, H, W) uint8 and, with ``with_depth``, depth (F + 1, H, W) float32 of ``states``.

    Poses go through ``render_batch`` in chunks of ``config.render_batch``; the last chunk is padded with
    its last pose so every call has one shape (compiled once).
    """
    chunk = int(config.render_batch)
    render_batch = devices.compiled(render_lib.render_batch, ("supersample", "chunk"))
    greys, depths = [], []
    for start in range(0, states.shape[0], chunk):
        xs = states[start:start + chunk]
        count = xs.shape[0]
        if count < chunk:
            xs = np.concatenate([xs, np.repeat(xs[-1:], chunk - count, axis=0)])
        frame = render_batch(world.track, jnp.asarray(xs), world.camera, supersample=int(config.supersample), chunk=1)
        greys.append(np.asarray(frame.grey)[:count])
        if with_depth:
            depths.append(np.asarray(frame.depth)[:count])
        if bar is not None:
            bar.update(count)
    return np.concatenate(greys), (np.concatenate(depths) if with_depth else None)


# the exact flow of a batch of frame pairs (their poses, the first frames' depth), compiled where it runs
_exact_flow_batch = jax.vmap(render_lib.exact_flow, in_axes=(0, 0, 0, None))


@jax.jit
def _geometric_detections(track, camera, states: jax.Array, targets: jax.Array):
    def one(x, gate_id):
        det = detector_lib.detect_from_geometry(track.gate(gate_id), x, camera)
        return det.found, det.centre, det.corners

    return jax.vmap(one)(states, targets)


def lap_detections(world: env_lib.World, states: np.ndarray, targets: np.ndarray) -> dict:
    """The detector's view of each frame's target gate, as the closed loop's (geometric) detector gives it
    without noise: ``gate_found`` (F + 1,), ``gate_centre`` (F + 1, 2), ``gate_corners`` (F + 1, 4, 2)
    (``learn.dataset``): what a box-based pixel model (vdof) learns from."""
    found, centre, corners = _geometric_detections(world.track, world.camera, jnp.asarray(states),
                                                   jnp.asarray(targets, jnp.int32))
    return {"gate_found": np.asarray(found, bool), "gate_centre": np.asarray(centre, np.float32),
            "gate_corners": np.asarray(corners, np.float32)}


def lap_arrays(world: env_lib.World, states: np.ndarray, controls: np.ndarray, targets: np.ndarray,
               config: CollectConfig, with_exact: bool, bar=None, rates: np.ndarray | None = None) -> dict:
    """Render a flown lap and compute its flows: the arrays of one lap file (their format: ``learn.dataset``).
    ``rates``: the true body rates (F + 1, 3) at each state, stored when given."""
    frames = controls.shape[0]
    grey, depth = render_lap(world, states, config, with_exact, bar)
    H, W = grey.shape[1:]
    flow = np.empty((frames, H, W, 2), np.float16)
    for t in range(frames):
        flow[t] = flow_lib.farneback(grey[t], grey[t + 1], shape=None)
    arrays = {"flow": flow, "q": states[:frames, 3:7].copy(), "u": controls, "states": states, "target": targets,
              "w_flown": dataset_lib.flown_rates(states, timing.CONTROL_DT),
              **lap_detections(world, states, targets)}
    if rates is not None:
        arrays["rates"] = np.asarray(rates, np.float32)
    if with_exact:
        exact = np.empty((frames, H, W, 2), np.float16)
        valid = np.empty((frames, H, W), bool)
        chunk = int(config.render_batch)
        exact_flow_batch = devices.compiled(_exact_flow_batch)
        for start in range(0, frames, chunk):
            stop = min(start + chunk, frames)
            f, v = exact_flow_batch(jnp.asarray(states[start:stop]), jnp.asarray(states[start + 1:stop + 1]),
                                    jnp.asarray(depth[start:stop]), world.camera)
            exact[start:stop], valid[start:stop] = np.asarray(f), np.asarray(v)
        arrays["exact_flow"], arrays["exact_valid"] = exact, valid
    return arrays


def collect(out_dir, config: CollectConfig = CollectConfig(), progress: bool = True,
            policy: policies.Policy | None = None) -> dict:
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
    previous = dataset_lib.find_manifest(root)
    policy_name = policy.name if policy is not None else "mppi"
    if previous is not None and (not _same_config(previous.get("config"), config)
                                 or previous.get("policy") != policy_name):
        raise ValueError(f"{root} holds a dataset collected with another config ({previous.get('config')}, policy "
                         f"{previous.get('policy')!r}); use a new directory or the same config to resume")
    runner_of = _lap_runners(config, policy)
    base = env_lib.make_world(camera=config.camera())  # the tilt is a value of the world: the same compiled lap
    manifest = _initial_manifest(config, policy, base, previous)
    recorded_sha256 = {e["lap"]: e.get("sha256") for e in (previous or {}).get("laps", [])}
    done: dict[int, dict] = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.laps, desc="collect", unit="lap")
    t0 = time.perf_counter()
    interrupted = False
    try:
        for lap in range(config.laps):
            path = root / dataset_lib.lap_filename(lap)
            digest = dataset_lib.intact_lap_sha256(path, recorded_sha256.get(lap))
            if digest is not None:
                done[lap] = _lap_entry(lap, path, config.split_of(lap), dataset_lib.lap_meta(path), digest)
            else:
                if path.exists():
                    print(f"{path}: damaged (its checksum does not match); flying lap {lap} again", file=sys.stderr)
                done[lap] = _fly_and_store_lap(path, lap, base, runner_of, config, bar)
                _write_manifest(root, manifest, done, config, complete=False)
            if bar is not None:
                bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        print(f"\ninterrupted: keeping the {len(done)} finished lap(s) in {root}; run again to resume")
    finally:
        if bar is not None:
            bar.close()
    manifest = _write_manifest(root, manifest, done, config, complete=not interrupted and len(done) == config.laps)
    manifest["wall_s_this_call"] = time.perf_counter() - t0
    manifest["interrupted"] = interrupted
    return manifest


def _lap_runners(config: CollectConfig, policy: policies.Policy | None) -> Callable[[int], episode_lib.Runner]:
    """The episode runner of each lap (by index), built on first use: ``policy``, or the nominal MPPI
    (:func:`_cached_runner`), wrapped in :func:`excited_policy` for the excited laps."""
    runners: dict[bool, episode_lib.Runner | None] = {False: None, True: None}
    if policy is not None:
        episode = episode_lib.EpisodeConfig(max_time_s=config.max_lap_time_s)
        runners[False] = episode_lib.make_runner(policy, episode)
        if config.excitation:
            excited = excited_policy(policy, *config.excitation_params(), num_samples=config.num_samples)
            runners[True] = episode_lib.make_runner(excited, episode)

    def runner_of(lap: int) -> episode_lib.Runner:
        excited = config.excited(lap)
        if runners[excited] is None:
            runners[excited] = _cached_runner(int(config.num_samples), float(config.max_lap_time_s),
                                              config.excitation_params() if excited else None)
        return runners[excited]

    return runner_of


def _initial_manifest(config: CollectConfig, policy: policies.Policy | None, base: env_lib.World,
                      previous: dict | None) -> dict:
    """The manifest before any lap of this call is stored: what is collected, how, and with what."""
    manifest = {
        "format": dataset_lib.DATASET_FORMAT,
        "format_version": dataset_lib.DATASET_VERSION,
        "config": config.to_json(),
        "policy": policy.name if policy is not None else "mppi",
        "mppi_config": dataclasses.asdict(paper_mppi_config(num_samples=config.num_samples))
        if policy is None else None,
        "image_size_wh": [int(base.camera.width), int(base.camera.height)],
        "frame_dt_s": timing.CONTROL_DT,
        "flown_rates": dataset_lib.FLOWN_RATES,
        "excited_laps": [i for i in range(config.laps) if config.excited(i)],
        "farneback": {k: v for k, v in flow_lib.FARNEBACK_PARAMS.items()},
        "split": {"train": [i for i in range(config.laps) if config.split_of(i) == "train"],
                  "test": config.test_indices()},
        "laps": [],
        "frames": {"train": 0, "test": 0},
        "versions": _versions(),
        "controller_source_sha256": _controller_source() if policy is None else None,
        "command": platform_info.invocation(),
        "created": (previous or {}).get("created", datetime.datetime.now().isoformat(timespec="seconds")),
        "complete": False,
    }
    if previous is not None and previous.get("format_version", 1) != dataset_lib.DATASET_VERSION:
        manifest["format_version"] = previous.get("format_version", 1)  # laps of mixed formats: the oldest
    return strict_json.json_safe(manifest)


def _fly_and_store_lap(path: Path, lap: int, base: env_lib.World, runner_of: Callable[[int], episode_lib.Runner],
                       config: CollectConfig, bar=None) -> dict:
    """Fly lap ``lap``, render it, compute its flows and write its file to ``path``; returns its manifest
    entry. ``bar``: the laps' progress bar (a frames bar is shown beside it while the lap renders)."""
    split, speed, seed = config.split_of(lap), config.speeds()[lap], config.seeds()[lap]
    world = base.replace(target_speed=jnp.asarray(speed, jnp.float32))
    if bar is not None:
        bar.set_postfix(lap=lap, speed=f"{speed:.1f}", stage="fly")
    states, controls, targets, summary = fly_lap(world, seed, runner_of(lap))
    rates = summary.pop("rates")
    if summary["frames"] < 1:
        raise RuntimeError(f"lap {lap} (seed {seed}, {speed:.1f} m/s) ended before a single "
                           f"frame pair ({summary['end']}); nothing to store")
    frames_bar = None
    if bar is not None:
        from tqdm.auto import tqdm

        bar.set_postfix(lap=lap, speed=f"{speed:.1f}", stage="render+flow")
        frames_bar = tqdm(total=states.shape[0], desc=f"lap {lap} frames", unit="frame", leave=False)
    with_exact = config.exact_flow == "all" or split == "test"
    try:
        arrays = lap_arrays(world, states, controls, targets, config, with_exact, frames_bar, rates)
    finally:
        if frames_bar is not None:
            frames_bar.close()
    meta = {"lap": lap, "split": split, "speed": speed, "seed": seed, "excited": config.excited(lap), **summary}
    arrays.update({f"meta_{k}": np.asarray(v) for k, v in meta.items()})
    strict_json.write_atomic(path, functools.partial(np.savez_compressed, **arrays))
    return _lap_entry(lap, path, split, dataset_lib.lap_meta(path), dataset_lib.file_sha256(path))


def _lap_entry(lap: int, path: Path, split: str, meta: dict, sha256: str) -> dict:
    entry = dict(meta)
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
    strict_json.write_json_atomic(root / dataset_lib.MANIFEST, strict_json.json_safe(manifest))
    return manifest


# --------------------------------------------------------------------------------------------------
# The `pixelmpc collect` entry point.
# --------------------------------------------------------------------------------------------------


def run_collect(out_dir, laps: int = 4, seed: int = 0, max_lap_time_s: float = 10.0, speed_min: float = 6.0,
                speed_max: float = 14.0, supersample: int = 1, test_laps: Sequence[int] | None = None,
                paper: bool = False, progress: bool = True, excitation: bool = False,
                excitation_pulse_rad_s: float = 1.5, excitation_dither_rad_s: float = 0.3,
                camera_tilt_deg: float = 0.0) -> dict:
    """Collect a dataset and print a short summary. ``paper=True`` starts from :meth:`CollectConfig.paper`
    (10 laps of 30 s) and ignores ``laps`` and ``max_lap_time_s``. ``excitation``: held rate pulses and
    dither on the train laps (see :func:`excited_policy`). ``camera_tilt_deg``: the racing camera, tilted up."""
    fields = dict(seed=seed, speed_min=speed_min, speed_max=speed_max, supersample=supersample,
                  test_laps=None if test_laps is None else tuple(test_laps), excitation=bool(excitation),
                  excitation_pulse_rad_s=float(excitation_pulse_rad_s),
                  excitation_dither_rad_s=float(excitation_dither_rad_s), camera_tilt_deg=float(camera_tilt_deg))
    config = (CollectConfig.paper(**fields) if paper
              else CollectConfig(laps=laps, max_lap_time_s=max_lap_time_s, **fields))
    manifest = collect(out_dir, config, progress=progress)
    print(dataset_lib.summarise_manifest(manifest, out_dir))
    return manifest
