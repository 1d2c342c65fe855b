"""Racing laps with a controller and writing what a person wants to see: metrics.json, a table, a plot; the closed
loop from Python: :func:`race` flies a :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec`, :func:`fly` one's own
controller or course, each returning a :class:`RaceResult`.

Laps are run in batches (``vmap`` of the episode); after every batch ``metrics.json`` and the per-tick record
``ticks_<controller>.npz`` are rewritten atomically, so an interrupted run keeps the laps it finished.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from pixelmpc_jax.apps.racing.spec import PACKAGED_WEIGHTS, RaceSpec
from pixelmpc_jax.control.pixelmpc import LEARNED_PIXEL_MODELS, ControllerConfig
from pixelmpc_jax.devices import Execution, usable_sample_devices
from pixelmpc_jax.dynamics.network_weights import variant_for_camera
from pixelmpc_jax.perception import association as association_lib
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.sim.controllers import CONTROLLERS, make_policy
from pixelmpc_jax.sim.policies import Policy
from pixelmpc_jax.strict_json import write_json_atomic
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import track as track_lib


def lap_worlds(base: env_lib.World, seeds: list[int], perturb: bool, map: str = "surveyed",
               survey_error: bool = False, gates: str = "map") -> env_lib.World:
    """One World per lap, stacked; with ``perturb`` each lap's course is perturbed with its own seed, and the world
    flies it while the map stays the nominal course (``map`` "surveyed") or the map is the perturbed course too
    ("known"). With ``survey_error`` (no ``perturb``) each lap's gates stand off the map by a survey's error drawn with
    its seed (:func:`~pixelmpc_jax.world.course.survey_gates`). With ``gates`` "estimated" the world tells the drone
    how far its map's gates may be off (``World.gate_std``: :func:`~pixelmpc_jax.world.course.gate_prior_std`)."""
    worlds = []
    for seed in seeds:
        world = base
        if perturb:
            moved = course_lib.perturb_gates(base.track, jax.random.PRNGKey(10_000 + seed))
            course = course_lib.move_gates(base.track, moved)
            world = base.replace(course=course) if map == "surveyed" else base.replace(track=course)
        elif survey_error:
            moved = course_lib.survey_gates(base.track, jax.random.PRNGKey(20_000 + seed))
            world = base.replace(course=course_lib.move_gates(base.track, moved))
        if gates == "estimated":
            world = world.replace(gate_std=course_lib.gate_prior_std(base.track, perturb and map == "surveyed"))
        worlds.append(world)
    return env_lib.stack_worlds(worlds)


class _Flight(NamedTuple):
    """What flies a race's laps: the compiled runner, the base world and how a step's samples are split."""

    runner: episode_lib.Runner
    base: env_lib.World
    policy_name: str
    sample_devices: int


def _prepare_flight(spec: RaceSpec, batch_size: int, dof_params) -> _Flight:
    """The runner and world of ``spec``; with a batch of one and several local devices, one lap flies at a time
    with its controller's samples split over the devices."""
    sample_devices = 1
    if batch_size == 1 and jax.process_count() == 1:
        sample_devices = usable_sample_devices(spec.config.mppi.num_samples)
    runner, policy_name = _runner(spec.controller, spec.config, sample_devices, spec.episode_config())
    if dof_params is None:
        dof_params = spec.packaged_dof()
    camera = camera_lib.default_camera(tilt=math.radians(spec.camera_tilt_deg))
    base = env_lib.make_world(track=course_lib.make_course(spec.course), target_speed=spec.speed, dof=dof_params,
                              camera=camera)
    return _Flight(runner, base, policy_name, sample_devices)


@functools.lru_cache(maxsize=16)
def _runner(controller: str, config, sample_devices: int, episode_config: episode_lib.EpisodeConfig
            ) -> tuple[episode_lib.Runner, str]:
    """The compiled runner of a controller's configuration and its episode (and the policy's name), one per process:
    races that differ only in what their worlds hold (the target speed, the course, the DOF weights) or in their
    seeds and laps fly one compiled program, so a grid's cells at several speeds compile it once. A runner compiles
    on its first batch (:func:`~pixelmpc_jax.sim.episode.make_runner`), once per batch shape."""
    policy = make_policy(controller, config, Execution(sample_devices=sample_devices))
    return episode_lib.make_runner(policy, episode_config), policy.name


def fly_batch(race: Race, seeds: list[int]) -> list[tuple]:
    """Fly the laps of ``seeds`` (at most the race's batch size) in one call; ``[(log, the course the lap flew)]``,
    host arrays.

    The seeds are padded to a whole batch (the last repeated, the copies dropped), so every batch has one
    shape and the vmapped episode compiles once."""
    padded = seeds + seeds[-1:] * (race.batch_size - len(seeds))
    worlds = lap_worlds(race.flight.base, padded, race.spec.perturb, race.spec.map, race.spec.survey_error,
                        race.spec.gates)
    return _fly_worlds(race.flight, worlds, padded)[:len(seeds)]


def _fly_worlds(flight: _Flight, worlds: env_lib.World, seeds: list[int]) -> list[tuple]:
    """The laps of ``seeds`` in ``worlds`` (stacked, one per seed) in one call: ``[(log, the course the lap flew)]``,
    host arrays. With its samples over several devices, a lap at a time."""
    keys = jax.vmap(jax.random.PRNGKey)(np.asarray(seeds))
    if flight.sample_devices > 1:  # one lap, its samples over the devices
        logs = metrics_lib.unbatch(flight.runner.single(jax.tree_util.tree_map(lambda a: a[0], worlds), keys[0]))
    else:
        logs = metrics_lib.unbatch(flight.runner.batch(worlds, keys))
    flown = worlds.track if worlds.course is None else worlds.course
    return [(log, jax.tree_util.tree_map(lambda leaf, i=lane: leaf[i], flown)) for lane, log in enumerate(logs)]


def lap_record(log, track: track_lib.Track, camera, seed: int, target_speed: float, estimator: str) -> dict:
    """One lap's metrics (:func:`~pixelmpc_jax.sim.metrics.lap_metrics`) at ``target_speed``, with the filter's figures
    when the lap flies on the estimate of ``estimator`` (its mean and largest position error), whether the vehicle
    turned upside down, and the lap's seed. With gates painted alike, the ticks whose candidates the estimator named the
    target's (``associations_accepted``), rejected (``associations_rejected``: none within the gate) or found ambiguous
    (``associations_ambiguous``): the last two made no update."""
    lap = metrics_lib.lap_metrics(log, track=track, camera=camera, target_speed=target_speed)
    n = int(log.num_ticks)
    association = np.asarray(log.association)  # none in a log built by hand
    if association.ndim == 1 and np.any(association[:n] != association_lib.NOT_ASSOCIATING):
        association = association[:n]
        for outcome in ("accepted", "rejected", "ambiguous"):
            code = association_lib.OUTCOMES.index(outcome)
            lap[f"associations_{outcome}"] = int(np.sum(association == code))
    gate_errors = None if log.gate_centre_error is None else np.asarray(log.gate_centre_error)
    if gate_errors is not None and np.any(np.isfinite(gate_errors)):  # the drone's gate centres at their passage
        lap["mean_gate_centre_error_m"] = float(np.nanmean(gate_errors))
        lap["max_gate_centre_error_m"] = float(np.nanmax(gate_errors))
    if estimator != "truth":
        lap["max_position_cov_trace"] = float(np.max(log.position_cov_trace[:n])) if n else None
        errors = np.linalg.norm(np.asarray(log.states)[:n, :3] - np.asarray(log.estimates)[:n, :3], axis=1)
        lap["mean_position_error_m"] = float(np.mean(errors)) if n else None
        lap["rms_position_error_m"] = float(np.sqrt(np.mean(errors**2))) if n else None
        lap["max_position_error_m"] = float(np.max(errors)) if n else None
    quaternions = np.asarray(log.states)[:n + 1, 3:7]
    # the body's z axis (the thrust) below the horizon: the world z of its third column, 1 - 2 (qx^2 + qy^2) < 0
    lap["flipped"] = bool(np.any(1.0 - 2.0 * (quaternions[:, 1] ** 2 + quaternions[:, 2] ** 2) < 0.0))
    lap["seed"] = seed
    return lap


class FlownLap(NamedTuple):
    """One flown lap: its metrics (:func:`lap_record`), its per-tick arrays
    (:func:`~pixelmpc_jax.sim.ticks.lap_ticks`), its episode log (host arrays) and its track as flown."""

    record: dict
    ticks: dict
    log: episode_lib.EpisodeLog
    track: track_lib.Track


class RaceResult(NamedTuple):
    """A race's laps as a program reads them (:func:`race`, :func:`fly`); lap i flew seed ``laps[i]["seed"]``.

    Attributes:
        laps: each lap's metrics (:func:`lap_record`): ``success``, ``lap_time_s`` (None unless finished),
            ``crash``, ``gates_passed``, the visibility figures (``time_vis_below_50_s``, ...), ``seed``.
        aggregate: each metric's mean, two sigma and count over the laps, ``success_rate`` and ``num_laps``
            (:func:`~pixelmpc_jax.sim.metrics.aggregate`).
        ticks: each lap's per-tick arrays, S = its ticks + 1 (state 0 the start): ``states`` (S, 10),
            ``estimates`` (S, 10), ``target`` (S,), ``visibility`` (S,), ``pointed_visibility`` (S,), ``controls``
            (S - 1, 4) and the gates as flown (:func:`~pixelmpc_jax.sim.ticks.lap_ticks`).
        logs: each lap's whole :class:`~pixelmpc_jax.sim.episode.EpisodeLog` (host arrays, padded to the time
            limit: the detections and the controller's predicted pixel too).
        controller: the controller's name.
        interrupted: Ctrl-C stopped the race; the laps are those finished before it.
    """

    laps: list[dict]
    aggregate: dict
    ticks: list[dict]
    logs: list[episode_lib.EpisodeLog]
    controller: str
    interrupted: bool = False

    @classmethod
    def of(cls, records: list[dict], ticks: list[dict], logs: list, controller: str,
           interrupted: bool = False) -> RaceResult:
        """The result of laps' records, per-tick arrays (:func:`~pixelmpc_jax.sim.ticks.lap_ticks`) and logs, each
        lap's commands added to its ticks and the records aggregated."""
        ticks = [{**lap, "controls": np.asarray(log.controls)[: int(log.num_ticks)]} for lap, log in zip(ticks, logs)]
        return cls(list(records), metrics_lib.aggregate(list(records)), ticks, list(logs), controller, interrupted)

    @property
    def lap_times(self) -> np.ndarray:
        """(L,) each lap's time, s; NaN for a lap not finished."""
        return np.asarray([np.nan if lap["lap_time_s"] is None else lap["lap_time_s"] for lap in self.laps])


class Race(NamedTuple):
    """A race ready to fly: the spec, how its laps fly, and the camera they are seen with."""

    spec: RaceSpec
    flight: _Flight
    batch_size: int

    @property
    def camera(self):
        return self.flight.base.camera


def prepare(spec: RaceSpec, batch_size: int = 1, dof_params=None) -> Race:
    """Check the race's weights and build what flies it (compiled on the first batch)."""
    if not (isinstance(batch_size, int) and batch_size > 0):
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    spec.check_weights(dof_params)
    return Race(spec, _prepare_flight(spec, batch_size, dof_params), min(batch_size, spec.laps))


def fly_batches(race: Race) -> Iterator[list[FlownLap]]:
    """The race's laps, a batch at a time (lap i flies seed ``spec.seed + i``)."""
    spec = race.spec
    seeds = list(range(spec.seed, spec.seed + spec.laps))
    for first in range(0, spec.laps, race.batch_size):
        chunk = seeds[first:first + race.batch_size]
        flown = []
        for lap_seed, (log, lap_track) in zip(chunk, fly_batch(race, chunk)):
            flown.append(_flown_lap(log, lap_track, race.camera, lap_seed, spec.speed, spec.estimator))
        yield flown


def _flown_lap(log, track: track_lib.Track, camera, seed: int, target_speed: float, estimator: str) -> FlownLap:
    return FlownLap(lap_record(log, track, camera, seed, target_speed, estimator),
                    ticks_lib.lap_ticks(log, track.gates, camera, seed), log, track)


class LapBook:
    """What a race has flown so far, and its files: ``metrics.json`` (the laps' metrics and their aggregate) and
    ``ticks_<name>.npz`` (the per-tick record, :mod:`~pixelmpc_jax.sim.ticks`), rewritten atomically after each
    batch."""

    def __init__(self, race: Race, name: str | None = None):
        self.race = race
        self.name = name or race.spec.controller
        self.results: dict = {"race": race.spec.record(), "key": race.spec.key(), "measure": metrics_lib.MEASURE,
                              "controller": race.flight.policy_name, "laps": [], "aggregate": {},
                              "interrupted": False, "sample_devices": race.flight.sample_devices}
        self.ticks: list[dict] = []
        self.logs: list[episode_lib.EpisodeLog] = []

    def add(self, laps: list[FlownLap]) -> None:
        for lap in laps:
            self.results["laps"].append(lap.record)
            self.ticks.append(lap.ticks)
            self.logs.append(lap.log)
        self.results["aggregate"] = metrics_lib.aggregate(self.results["laps"])

    def write_ticks(self, out: Path) -> None:
        if self.ticks:
            ticks_lib.write(Path(out) / f"ticks_{self.name}.npz", self.ticks, self.race.camera, self.race.spec.speed)

    def result(self) -> RaceResult:
        """The laps flown so far as a :class:`RaceResult`."""
        return RaceResult.of(self.results["laps"], self.ticks, self.logs, self.race.flight.policy_name,
                             self.results["interrupted"])

    def flown(self) -> dict:
        """The results with each lap's flown states (``trajectories``), the target's visibility at each tick
        (``visibility``), the states the controller acted on (``estimates``), with a filter the trace
        of its position covariance at each tick (``covariances``), the per-tick record (``ticks``) and the camera
        the laps were seen with (``camera``)."""
        out = {**self.results, "trajectories": [], "visibility": [], "estimates": [], "covariances": [],
               "ticks": self.ticks, "camera": self.race.camera}
        for log in self.logs:
            n = int(log.num_ticks)
            out["trajectories"].append(np.asarray(log.states)[: n + 1])
            out["visibility"].append(np.asarray(log.visibility)[: n + 1])
            out["estimates"].append(np.asarray(log.estimates)[:n])
            if self.race.spec.estimator != "truth":
                out["covariances"].append(np.asarray(log.position_cov_trace)[:n])
        return out


def run_laps(spec: RaceSpec, out: Path | None = None, batch_size: int = 1, progress: bool = True,
             video: bool = False, dof_params=None) -> dict:
    """Fly the race ``spec`` and return ``{"race": spec.record(), "laps": [...], "aggregate": {...}, ...}``.

    Lap i uses PRNG key ``spec.seed + i`` for the plant noise and the controller, so a lap is reproducible on
    its own and a batch gives the same per-lap result as single runs. ``dof_params`` are the DOF weights the
    spec names (None: the packaged weights; a ValueError if their fingerprint is not the spec's). The result
    also holds what :meth:`LapBook.flown` adds. Laps fly ``batch_size`` at a time. With a batch of one and several
    local devices (a CPU's cores split by ``pixelmpc race``), a lap flies at a time with the controller's samples
    split over the devices (``Execution.sample_devices``: the same samples, the plan up to float rounding);
    ``sample_devices`` in the result says how many. With ``out``, ``metrics.json`` and ``ticks_<controller>.npz``
    are rewritten after every batch, ``trajectories.png`` drawn at the end (:func:`plot_coloured_trajectories`)
    and, with ``video``, the first lap's ``onboard.mp4`` written. ``interrupted`` is True when Ctrl-C (or SIGTERM,
    under the ``pixelmpc`` command) stopped the run: the laps finished before it are kept (and in ``out``).
    """
    return _fly_race(spec, out, batch_size, progress, video, dof_params).flown()


def race(spec: RaceSpec, out: Path | None = None, batch_size: int = 1, progress: bool = False,
         dof_params=None) -> RaceResult:
    """Fly the race ``spec`` (a preset, :func:`~pixelmpc_jax.apps.racing.presets.preset`, or one's own
    :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec`) and return its laps, their metrics and per-tick arrays.

    The laps fly as :func:`run_laps` flies them (the ``pixelmpc race`` command flies the same batches, the same
    records): lap i on seed ``spec.seed + i``, ``batch_size`` at a time; with ``out`` the race's files are written
    there too. ``dof_params``: the learned pixel model's weights when the spec names weights that do not ship in
    the package. A lap of the ``best`` preset from Python, and what comes back: docs/closed_loop.md.
    """
    return _fly_race(spec, out, batch_size, progress, False, dof_params).result()


def _fly_race(spec: RaceSpec, out: Path | None, batch_size: int, progress: bool, video: bool, dof_params) -> LapBook:
    """Fly ``spec`` batch by batch into a :class:`LapBook` (see :func:`run_laps`)."""
    prepared = prepare(spec, batch_size, dof_params)
    book = LapBook(prepared)
    bar = _progress_bar(spec) if progress else None
    try:
        for laps in fly_batches(prepared):
            book.add(laps)
            if video and out is not None and laps[0].record["seed"] == spec.seed:
                from pixelmpc_jax.apps.racing.video import write_onboard_video

                write_onboard_video(prepared.flight.base.track, laps[0].log, Path(out) / "onboard.mp4",
                                    prepared.camera)
            if out is not None:
                write_json_atomic(Path(out) / "metrics.json", book.results)
                book.write_ticks(out)
            if bar is not None:
                bar.update(len(laps))
                bar.set_postfix(done=sum(lap["success"] for lap in book.results["laps"]))
    except KeyboardInterrupt:
        book.results["interrupted"] = True
        if out is not None and book.results["laps"]:
            write_json_atomic(Path(out) / "metrics.json", book.results)
            book.write_ticks(out)
        print(f"\ninterrupted: keeping the {len(book.results['laps'])} finished lap(s)")
    finally:
        if bar is not None:
            bar.close()
    if out is not None and book.logs:
        trajectories = [np.asarray(log.states)[: int(log.num_ticks) + 1] for log in book.logs]
        plot_coloured_trajectories(prepared.flight.base.track, trajectories, Path(out) / "trajectories.png",
                                   title=f"{spec.controller}, target {spec.speed:g} m/s, {len(trajectories)} lap(s)")
    return book


def fly(controller: str | Policy = "mppi", world: env_lib.World | None = None, *,
        config: ControllerConfig | None = None, laps: int = 1, seed: int = 0,
        episode: episode_lib.EpisodeConfig | None = None, batch_size: int = 1) -> RaceResult:
    """Fly ``laps`` laps of one's own controller, or of one's own course, and return their laps, metrics and
    per-tick arrays (as :func:`race` does for a :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec`).

    Args:
        controller: "mppi" (nominal MPPI) or "pixelmpc" with its ``config``
            (:class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig`; None: its defaults), or a
            :class:`~pixelmpc_jax.sim.policies.Policy` of one's own (``init(key, world)``,
            ``act(state, observation, world) -> (u, state, predicted)``; its ``world`` is the
            :class:`~pixelmpc_jax.sim.env.PolicyWorld`, what the drone knows of ``world``).
        world: the course, the target speed, the vehicle and the camera
            (:func:`~pixelmpc_jax.sim.env.make_world`; None: the AlphaPilot course at 14 m/s). PixelMPC with a
            learned pixel model flies the packaged weights when ``world.dof`` is None: those trained for the world's
            camera tilt where the package ships them, else the model's default (:func:`packaged_weights_for`).
        laps: lap i flies PRNG seed ``seed + i`` (the plant's noise and the controller's).
        episode: the loop (:class:`~pixelmpc_jax.sim.episode.EpisodeConfig`: time limit, detector, estimator;
            None: its defaults, the true state and the detector clipped at the image border).
        batch_size: laps flown at once (a ``vmap`` over laps).

    Nominal MPPI on a course of one's own, in five lines: docs/closed_loop.md.
    """
    if not (isinstance(laps, int) and laps > 0) or not (isinstance(batch_size, int) and batch_size > 0):
        raise ValueError(f"laps and batch_size must be positive integers, got {laps!r} and {batch_size!r}")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    world = env_lib.make_world() if world is None else world
    if not isinstance(world, env_lib.World):
        raise ValueError(f"world must be a World (make_world), got {type(world).__name__}")
    episode = episode_lib.EpisodeConfig() if episode is None else episode
    if isinstance(controller, Policy):
        if config is not None:
            raise ValueError("config configures a named controller ('mppi', 'pixelmpc'); a Policy brings its own")
        runner, name = episode_lib.make_runner(controller, episode), controller.name
    else:
        if controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {', '.join(CONTROLLERS)} or a Policy, got {controller!r}")
        config = ControllerConfig() if config is None else config
        runner, name = _runner(controller, config, 1, episode)
        if controller == "pixelmpc" and world.dof is None and config.pixel_model in LEARNED_PIXEL_MODELS:
            world = world.replace(dof=packaged_weights_for(config.pixel_model, world.camera))
    flight = _Flight(runner, world, name, 1)
    batch_size = min(batch_size, laps)
    seeds, flown = list(range(seed, seed + laps)), []
    for first in range(0, laps, batch_size):
        chunk = seeds[first:first + batch_size]
        padded = chunk + chunk[-1:] * (batch_size - len(chunk))
        logs = _fly_worlds(flight, env_lib.stack_worlds([world] * batch_size), padded)
        flown += [_flown_lap(log, lap_track, world.camera, lap_seed, float(world.target_speed), episode.estimator)
                  for lap_seed, (log, lap_track) in zip(chunk, logs)]
    return RaceResult.of([lap.record for lap in flown], [lap.ticks for lap in flown], [lap.log for lap in flown],
                         name)


def packaged_weights_for(pixel_model: str, camera: camera_lib.Camera):
    """The learned pixel model's packaged weights (:data:`~pixelmpc_jax.apps.racing.spec.PACKAGED_WEIGHTS`) for
    ``camera``: the first whose record states its tilt (to 1e-4 deg: a tilt held in float32), else the model's
    default, trained for the untilted camera."""
    packaged = PACKAGED_WEIGHTS[pixel_model]
    tilt_deg = round(math.degrees(float(camera.tilt)), 4)
    return packaged.load(variant_for_camera(packaged.variants, tilt_deg) or next(iter(packaged.variants)))


def _progress_bar(spec: RaceSpec):
    from tqdm.auto import tqdm

    return tqdm(total=spec.laps, desc=f"{spec.controller} @ {spec.speed:g} m/s", unit="lap")


def draw_course(ax, track: track_lib.Track) -> None:
    """The desired path, the gates' frames with their order and names, and the start, top down."""
    path_xy = np.asarray(track.path_points)[:, :2]
    ax.plot(path_xy[:, 0], path_xy[:, 1], "k:", lw=0.8, label="desired path")
    corners = np.asarray(track.gates.outer_corners())  # (G, 4, 3)
    for g in range(track.num_gates):
        left, right = corners[g, 0, :2], corners[g, 1, :2]
        ax.plot([left[0], right[0]], [left[1], right[1]], "r-", lw=3)
        name = track.names[g] if track.names else str(g)
        ax.annotate(f"{g + 1}:{name}", np.asarray(track.gates.centre[g, :2]), fontsize=7,
                    xytext=(4, 4), textcoords="offset points")
    start = np.asarray(track.start[:2])
    ax.plot(*start, "g^", ms=9, label="start")


def plot_coloured_trajectories(track: track_lib.Track, trajectories: list[np.ndarray], path: Path, title: str = "",
                               colour_by: list[np.ndarray] | None = None, colour_label: str = "speed [m/s]") -> None:
    """Top-down view: trajectories coloured by speed (or ``colour_by``), gates drawn as their frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig, ax = plt.subplots(figsize=(7, 9))
    values = colour_by or [np.linalg.norm(t[:, 7:10], axis=1) for t in trajectories]
    vmax = max(float(np.max(v)) for v in values) if values else 1.0
    norm = plt.Normalize(0.0, vmax)
    for traj, value in zip(trajectories, values):
        points = traj[:, :2]
        segments = np.stack([points[:-1], points[1:]], axis=1)
        lc = LineCollection(segments, cmap="viridis", norm=norm, linewidths=1.2, alpha=0.85)
        lc.set_array(value[:-1])
        ax.add_collection(lc)
    draw_course(ax, track)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=ax, label=colour_label, shrink=0.7)
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set(xlabel="x [m]", ylabel="y [m]", title=title)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
