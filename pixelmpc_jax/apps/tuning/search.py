"""``pixelmpc tune``: a controller's settings found by search against the speed frontier, not by hand (issue 29).

**Objective.** Nominal MPPI flies the training seeds at a few target speeds once (the nominal frontier of
:mod:`~pixelmpc_jax.apps.experiments.frontier`); every trial flies the base race (a preset, ``best`` by default)
with the trial's settings on the same seeds and laps, through :func:`~pixelmpc_jax.apps.racing.grid.run_grid` (the
grids' laps, batched over the devices), and scores its frontier gain: the nominal avoidable low-visibility time at the
trial's mean lap time over the trial's (floored at one control tick, as :func:`frontier.build` does; the avoidable
time counts every tick a gate is the target, :func:`~pixelmpc_jax.sim.metrics.visibility_masks`). The constraints
that make a trial feasible: every lap completed; a mean lap time at most ``(1 + bound)`` times nominal MPPI's at the
same target; and, against nominal MPPI at the trial's own lap time, a raw time below 50 % (nothing excused) no
higher, a share of time with the target in view no lower, and a mean angle to the target no larger, so a gain
cannot be bought by looking away where the avoidable time does not look. An infeasible trial scores
``-(failed laps + excess / bound + view shortfall)``, ``excess`` the lap-time change past the bound and the view
shortfall the sum of the three figures' relative shortfalls against nominal's: below every feasible score
(a gain is >= 0), finite, and worse the more laps it lost, the slower it flew or the less it saw, so the sampler
still learns which way feasibility lies. A feasible trial whose lap time the nominal frontier does not bracket
scores 0, unless it dominates: faster than nominal MPPI's fastest point (where nominal's lap stops getting faster as
its target rises, as it does on the racing camera at 13.5-14.5 m/s), with less avoidable time than every nominal
point and seeing no worse than the fastest point; then it scores the smallest nominal avoidable time over its own
(:func:`dominating_gain`), the gain against the nominal point that saw best, so a racing search is not pushed to
slower laps by a frontier that cannot follow.

**Engine: Optuna's TPE sampler, seeded.** Optuna is a well-kept library with the store a long search needs: the
study lives in a database (SQLite in ``DIR/study.db`` by default), so an interrupted search resumes where it
stopped, and with a server database (``--storage postgresql://...``) several processes or machines work on one
study (docs/tune.md). TPE copes with mixed log and linear ranges and with choices, and learns from few trials
(30 here, each a minute or two of laps on a 2-core CPU); CMA-ES wants more evaluations than that and handles no
choices; evosax's strategies would batch trials on the accelerator, but one trial is already a batch of laps.

**Resuming.** Finished trials are never flown again: ``--trials N`` is the number of completed trials the study
must hold. A trial interrupted by Ctrl-C is marked failed and queued once more with the same settings; one whose
process was killed outright stops sending its heartbeat and is failed and queued the same way by the next trial
to start once :data:`GRACE_S` has passed. The nominal frontier is kept in the study (and in ``DIR/nominal/``).

Files in ``DIR``: ``study.db``, ``nominal/`` and ``trials/trial_NNNN/`` (the grids), ``trials.json`` and
``trials.csv`` (every trial), ``best.json`` (the best trial's race, :meth:`RaceSpec.record`: ``pixelmpc race
--config``), ``tune.png``; after validation, ``validation/``, ``validation.json`` and ``validation.md``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path

from pixelmpc_jax.apps.experiments import frontier
from pixelmpc_jax.apps.racing import grid
from pixelmpc_jax.apps.racing.presets import preset
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.apps.tuning import report
from pixelmpc_jax.apps.tuning.space import Param, with_settings
from pixelmpc_jax.strict_json import write_json_atomic

NOMINAL_SPEEDS = (7.0, 8.0, 8.5, 10.0)  # m/s: brackets the best preset's laps at 8.5 m/s and +10 % beyond
LAP_TIME_BOUND = 0.10  # a tuned lap may be at most 10 % slower than nominal MPPI's at the same target
HEARTBEAT_S = 30  # a running trial writes its heartbeat this often
GRACE_S = 120  # a trial silent this long was killed: it is failed and queued again

Fly = Callable[[list, Path, int, int], dict]  # (cells, folder, laps, seed) -> {cell name: race results}


def fly_grid(cells: list[grid.Cell], out: Path, laps: int, seed: int) -> dict:
    """The laps of ``cells``: :func:`grid.run_grid` into ``out`` (resumable per cell)."""
    return grid.run_grid(cells, out, laps=laps, seed=seed, progress=False)


@dataclasses.dataclass(frozen=True)
class TuneSetup:
    """What a study searches and how it scores: the base race (``preset``), the searched settings (``space``), the
    nominal speeds, the training laps (seeds ``seed .. seed + laps - 1``) and the lap-time bound."""

    preset: str = "best"
    space: tuple[Param, ...] = ()
    nominal_speeds: tuple[float, ...] = NOMINAL_SPEEDS
    laps: int = 4
    seed: int = 0
    bound: float = LAP_TIME_BOUND

    def __post_init__(self):
        if not self.bound > 0:
            raise ValueError(f"the lap-time bound must be positive, got {self.bound!r}")
        speeds = {float(v) for v in self.nominal_speeds} | {self.base.speed}  # the bound needs the base's target
        object.__setattr__(self, "nominal_speeds", tuple(sorted(speeds)))

    @property
    def base(self) -> RaceSpec:
        return preset(self.preset)

    def nominal_cells(self) -> list[grid.Cell]:
        return [self.nominal_cell(v) for v in self.nominal_speeds]

    def nominal_cell(self, speed: float) -> grid.Cell:
        """Nominal MPPI at ``speed`` with the base race's lap timeout and camera (a trial's visibility is held to
        nominal's seen through the same camera)."""
        cell = frontier.nominal_cell(speed, self.base.max_time_s)
        return dataclasses.replace(cell, spec=cell.spec.replace(camera_tilt_deg=self.base.camera_tilt_deg))

    def record(self) -> dict:
        """In JSON types, as the study stores it (a study answers one setup)."""
        return json.loads(json.dumps({"preset": self.preset, "base": self.base.record(),
                                      "space": {p.name: p.record() for p in self.space},
                                      "nominal_speeds": list(self.nominal_speeds), "laps": self.laps,
                                      "seed": self.seed, "bound": self.bound}))


def view_shortfall(row: dict) -> dict:
    """How far a frontier row (:func:`frontier.build`) sees worse than nominal MPPI at its own lap time, per figure,
    relative to nominal's (0 where it sees as well or better, or where the frontier does not bracket the row): the
    raw time below 50 % above nominal's, the share of time in view below it, the mean angle to the target above it."""
    def relative(mine, nominal, worse_when_higher: bool) -> float:
        if mine is None or nominal is None:
            return 0.0
        over = (mine - nominal) if worse_when_higher else (nominal - mine)
        return max(0.0, over) / max(abs(nominal), 1e-9)

    return {"vis_below_50_s": relative(row.get("vis_below_50_s"), row.get("frontier_vis_below_50_s"), True),
            "share_target_in_view": relative(row.get("share_target_in_view"),
                                             row.get("frontier_share_target_in_view"), False),
            "mean_target_angle_deg": relative(row.get("mean_target_angle_deg"),
                                              row.get("frontier_mean_target_angle_deg"), True)}


def dominating_gain(row: dict, nominal: list[dict]) -> float | None:
    """A frontier row the nominal points ``nominal`` (``frontier.build``'s, each with ``lap_time_s`` and
    ``avoidable_s``) do not bracket, held against them where it is faster than their fastest lap: the smallest nominal
    avoidable time over the row's (floored at one control tick as :func:`frontier.build` floors it) where that is
    above 1 (less avoidable time than every nominal point) and the row sees no worse than the fastest point (the
    three figures of :func:`view_shortfall`); None otherwise (slower than the fastest point, or not dominating)."""
    points = [p for p in nominal if p.get("lap_time_s") is not None and p.get("avoidable_s") is not None]
    if row["bracketed"] or row["lap_time_s"] is None or row["avoidable_s"] is None or not points:
        return None
    fastest = min(points, key=lambda p: p["lap_time_s"])
    if row["lap_time_s"] >= fastest["lap_time_s"]:
        return None
    gain = min(p["avoidable_s"] for p in points) / max(row["avoidable_s"], frontier.AVOIDABLE_FLOOR_S)
    against = {**row, **{f"frontier_{figure}": fastest.get(figure) for figure in
                         ("vis_below_50_s", "share_target_in_view", "mean_target_angle_deg")}}
    return gain if gain > 1.0 and not any(view_shortfall(against).values()) else None


def score(row: dict, nominal_lap_s: float, bound: float, nominal: list[dict] | None = None) -> dict:
    """A trial's objective from its frontier row (:func:`frontier.build`) and nominal MPPI's lap time at the same
    target: the frontier gain when every lap completed within the bound and it sees no worse than nominal MPPI at
    its lap time (:func:`view_shortfall`), else ``-(failed laps + excess / bound + view shortfall)``. A feasible row
    the frontier does not bracket scores its :func:`dominating_gain` against the nominal points ``nominal`` where it
    dominates them, else 0."""
    failed = row["laps"] - row["laps_completed"]
    change = None if row["lap_time_s"] is None else row["lap_time_s"] / nominal_lap_s - 1.0
    excess = 0.0 if change is None else max(0.0, change - bound)
    shortfall = view_shortfall(row)
    feasible = failed == 0 and excess == 0.0 and not any(shortfall.values())
    dominating = dominating_gain(row, nominal or []) if feasible else None
    if feasible:
        value = row["frontier_gain"] if row["frontier_gain"] is not None else (dominating or 0.0)
    else:
        value = -(failed + excess / bound + sum(shortfall.values()))
    return {"score": float(value), "feasible": feasible, "gain": row["frontier_gain"],
            "gain_interval": row["frontier_gain_interval"], "bracketed": row["bracketed"],
            "dominating": dominating is not None,
            "lap_time_s": row["lap_time_s"], "lap_time_change": change, "bound_excess": excess,
            "avoidable_s": row["avoidable_s"], "laps_completed": row["laps_completed"], "laps": row["laps"],
            "view_shortfall": shortfall, "vis_below_50_s": row.get("vis_below_50_s"),
            "share_target_in_view": row.get("share_target_in_view"),
            "mean_target_angle_deg": row.get("mean_target_angle_deg")}


def evaluate(results: dict, cell: grid.Cell, nominal: dict, setup: TuneSetup) -> dict:
    """:func:`score` of a cell's race ``results`` against the ``nominal`` results (``{cell name: race results}``)."""
    built = frontier.build({**nominal, cell.name: results}, setup.nominal_speeds, [cell], setup.laps, setup.seed,
                           setup.base.max_time_s)
    at_target = next(p for p in built["nominal"] if p["speed"] == setup.base.speed)
    if at_target["lap_time_s"] is None:
        raise RuntimeError(f"nominal MPPI at {setup.base.speed:g} m/s completed no lap: no lap time to bound")
    return score(built["cells"][0], at_target["lap_time_s"], setup.bound, built["nominal"])


def open_study(storage: str, name: str, setup: TuneSetup, sampler_seed: int = 0, heartbeat_s: int = HEARTBEAT_S,
               grace_s: int = GRACE_S):
    """The Optuna study ``name`` in ``storage`` (created if new), maximising; a ValueError if it was made for
    another setup. Its TPE sampler is seeded with ``sampler_seed`` plus the trials already in the study, so a
    resumed search does not draw its first trials' settings again, and a constant liar, so workers sharing the
    study do not draw the settings of each other's running trials."""
    import optuna
    from optuna.exceptions import ExperimentalWarning

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        store = optuna.storages.RDBStorage(
            storage, heartbeat_interval=heartbeat_s, grace_period=grace_s,
            heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=1))
    study = optuna.create_study(storage=store, study_name=name, direction="maximize", load_if_exists=True)
    recorded, wanted = study.user_attrs.get("setup"), setup.record()
    if recorded is None:
        study.set_user_attr("setup", wanted)
    elif recorded != wanted:
        changed = sorted(k for k in wanted if recorded.get(k) != wanted[k])
        raise ValueError(f"study {name!r} in {storage} searches another setup (its {', '.join(changed)} differ): "
                         "give another --out, --study or --storage")
    sampler = optuna.samplers.TPESampler(seed=sampler_seed + len(study.trials), constant_liar=True)
    return optuna.load_study(study_name=name, storage=store, sampler=sampler)


def adopt(cells: list[grid.Cell], out: Path, laps: int, seed: int, sources=()) -> list[str]:
    """Copy into ``out/results.json`` each cell's finished race from the grid folders ``sources`` (any cell name
    there whose recorded race is the one asked, :func:`grid.is_current`), so :func:`grid.run_grid` keeps it
    instead of flying it again; returns the names copied."""
    out = Path(out)
    results = grid.load_results(out)
    flown = {Path(folder): grid.load_results(folder) for folder in sources}
    copied = []
    for cell in cells:
        race = cell.race(laps, seed, None)
        if grid.is_current(results.get(cell.name), race):
            continue
        found = next(((folder, name) for folder, done in flown.items() for name in done
                      if grid.is_current(done[name], race)), None)
        if found is None:
            continue
        folder, name = found
        # the wall time was spent where it was flown; here it cost nothing
        results[cell.name] = {**flown[folder][name], "shared_from": f"{Path(folder).name}/{name}", "wall_time_s": 0.0}
        trajectories = folder / f"trajectories_{name}.npz"
        if trajectories.exists():
            out.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(trajectories, out / f"trajectories_{cell.name}.npz")
        copied.append(cell.name)
    if copied:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / "results.json", results)
    return copied


def nominal_results(study, setup: TuneSetup, out: Path, fly: Fly, reuse=()) -> dict:
    """Nominal MPPI's training laps at each nominal speed (``{cell name: race results}``): from the study when it
    holds them for these races, else flown into ``out/nominal/`` (or copied from ``reuse``) and stored in it."""
    cells = setup.nominal_cells()
    keys = {cell.name: cell.race(setup.laps, setup.seed, None).key() for cell in cells}
    stored = study.user_attrs.get("nominal")
    if stored and stored["keys"] == keys:
        return stored["results"]
    adopt(cells, out / "nominal", setup.laps, setup.seed, reuse)
    print(f"nominal MPPI at {', '.join(f'{v:g}' for v in setup.nominal_speeds)} m/s, {setup.laps} laps each "
          f"(seeds {setup.seed}-{setup.seed + setup.laps - 1}) -> {out / 'nominal'}", flush=True)
    flown = fly(cells, out / "nominal", setup.laps, setup.seed)
    results = {cell.name: {"laps": flown[cell.name]["laps"], "wall_time_s": flown[cell.name].get("wall_time_s")}
               for cell in cells}
    study.set_user_attr("nominal", {"keys": keys, "results": results})
    return results


def make_objective(setup: TuneSetup, nominal: dict, out: Path, fly: Fly, interrupted: list):
    """The study's objective: fly a trial's settings, record its figures in the trial's user attributes, return
    its :func:`score`. A trial that Ctrl-C stops is appended to ``interrupted`` (its number)."""

    def objective(trial) -> float:
        settings = {param.name: param.suggest(trial) for param in setup.space}
        cell = grid.Cell(f"trial_{trial.number:04d}", with_settings(setup.base, settings))
        try:
            flown = fly([cell], out / "trials" / cell.name, setup.laps, setup.seed)
        except KeyboardInterrupt:
            interrupted.append(trial.number)
            raise
        outcome = evaluate(flown[cell.name], cell, nominal, setup)
        for key, value in outcome.items():
            trial.set_user_attr(key, value)
        trial.set_user_attr("wall_time_s", flown[cell.name].get("wall_time_s"))
        trial.set_user_attr("race", cell.race(setup.laps, setup.seed, None).record())
        return outcome["score"]

    return objective


def completed(study) -> int:
    from optuna.trial import TrialState

    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


def run_tune(setup: TuneSetup, out: Path, trials: int, minutes: float | None = None, storage: str | None = None,
             study_name: str = "tune", sampler_seed: int = 0, fly: Fly = fly_grid, reuse=(), progress: bool = True):
    """Search until the study holds ``trials`` completed trials (or ``minutes`` have passed), then write the
    outputs; returns the study. Interrupted (Ctrl-C), the interrupted trial is queued again, the outputs are
    written from the finished trials, and the KeyboardInterrupt is raised again."""
    import optuna
    from optuna.exceptions import ExperimentalWarning

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    storage = storage or f"sqlite:///{out / 'study.db'}"
    study = open_study(storage, study_name, setup, sampler_seed)
    nominal = nominal_results(study, setup, out, fly, reuse)
    interrupted: list[int] = []
    callbacks = [optuna.study.MaxTrialsCallback(trials, states=(optuna.trial.TrialState.COMPLETE,)),
                 lambda study, trial: report.write_outputs(study, setup, nominal, out, trial)]
    try:
        if completed(study) < trials:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ExperimentalWarning)
                study.optimize(make_objective(setup, nominal, out, fly, interrupted),
                               n_trials=trials - completed(study), timeout=None if minutes is None else 60 * minutes,
                               callbacks=callbacks, show_progress_bar=progress)
    except KeyboardInterrupt:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ExperimentalWarning)
            retry = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=1)
        for trial in study.get_trials(deepcopy=False):
            if trial.number in interrupted and trial.state == optuna.trial.TrialState.FAIL:
                retry(study, trial)
        report.write_outputs(study, setup, nominal, out)
        raise
    report.write_outputs(study, setup, nominal, out)
    return study


def validate(study, setup: TuneSetup, out: Path, seed: int, laps: int = 10, fly: Fly = fly_grid,
             reuse=(), course: str | None = None) -> dict:
    """Fly the study's best trial, the base preset and the nominal frontier on the held-out seeds ``seed ..
    seed + laps - 1`` (races already flown in a ``reuse`` grid folder are copied, not flown) into
    ``out/validation/``; write ``validation.json`` and ``validation.md``; returns the table's record. With
    ``course`` (a name or a course file, e.g. a generated course nobody tuned on) every cell flies that course
    instead, into ``out/validation_course/``, ``validation_course.json`` and ``validation_course.md``."""
    trial = report.best_trial(study)
    if trial is None:
        raise ValueError("the study holds no completed trial to validate: run the search first")
    best = RaceSpec.from_record(trial.user_attrs["race"]).replace(laps=1, seed=0)
    tuned = grid.Cell("tuned", best)
    hand = grid.Cell(f"preset_{setup.preset}", setup.base)
    at_target = setup.nominal_cell(setup.base.speed)
    cells = setup.nominal_cells() + [hand, tuned]
    if course is not None:
        cells = [dataclasses.replace(cell, spec=cell.spec.replace(course=course)) for cell in cells]
        tuned, hand = cells[-1], cells[-2]
        at_target = dataclasses.replace(at_target, spec=at_target.spec.replace(course=course))
    name = "validation" if course is None else "validation_course"
    folder = Path(out) / name
    shared = adopt(cells, folder, laps, seed, reuse)
    print(f"validation on seeds {seed}-{seed + laps - 1}{'' if course is None else f', course {course}'}: "
          f"{len(cells) - len(shared)} cell(s) to fly, {len(shared)} copied ({', '.join(shared) or 'none'}) -> "
          f"{folder}", flush=True)
    results = fly(cells, folder, laps, seed)
    built = frontier.build(results, setup.nominal_speeds, [tuned, hand, at_target], laps, seed,
                           setup.base.max_time_s)
    record = report.validation_record(built, trial, setup, results, course)
    write_json_atomic(Path(out) / f"{name}.json", record)
    (Path(out) / f"{name}.md").write_text(report.validation_markdown(record))
    return record
