"""Experiment grids: named cells of laps, run batched, resumable, reported beside the paper's figures.

A grid is a list of :class:`Cell` (a name and the race it flies, a :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec`);
each cell flies ``laps`` laps (seeds ``seed .. seed + laps - 1``, batched with ``vmap``) with the grid's DOF
weights. After every cell the results file is rewritten atomically, and a cell already in the file is not
recomputed, so an interrupted run resumes. A finished cell is kept only while the race it recorded has the same
:meth:`~pixelmpc_jax.apps.racing.spec.RaceSpec.key` as the race asked now (settings, seed, number of laps, DOF
weights); otherwise it is flown again and replaced.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from pixelmpc_jax.apps.racing import race
from pixelmpc_jax.apps.racing.executor import Executor
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.sim import ticks_compact
from pixelmpc_jax.sim.metrics import MEASURE
from pixelmpc_jax.strict_json import write_json_atomic

RUN_FIELDS = ("laps", "seed", "dof_weights")  # a cell's race takes these from the grid run, not from the cell


@dataclasses.dataclass(frozen=True)
class Cell:
    """One cell of an experiment grid: its name (the key in ``results.json``) and the race it flies. The race's
    laps, seed and DOF weights are the grid run's (:func:`run_grid`), so the cell's own stay at their defaults."""

    name: str
    spec: RaceSpec = dataclasses.field(default_factory=RaceSpec)

    def __post_init__(self):
        default = RaceSpec()
        set_here = [f for f in RUN_FIELDS if getattr(self.spec, f) != getattr(default, f)]
        if set_here:
            raise ValueError(f"cell {self.name!r} sets {', '.join(set_here)}: a grid cell takes them from the run")

    def race(self, laps: int, seed: int, dof_weights: str | None) -> RaceSpec:
        """The race this cell flies in a run of ``laps`` laps from ``seed`` with DOF weights ``dof_weights``
        (a fingerprint, None for the packaged weights)."""
        return self.spec.replace(laps=laps, seed=seed, dof_weights=dof_weights)


CPU_BATCH = 4  # laps per vmapped batch on the CPU (see default_batch_size)


def default_batch_size(laps: int) -> int:
    """How many laps of a cell to fly in one vmapped batch.

    A batch runs until its longest lap ends (a ``while_loop`` under ``vmap`` steps every lane while any is
    running), so one lap that hovers until the timeout keeps the whole batch busy; but a batch also
    amortises the episode's small sequential work (plant substeps, filter, detector). On accelerators the
    batch is what fills the device, so the whole cell flies at once (split over the devices). On the
    2-core CPU, PixelMPC with the particle filter cost 70 ms per lap and tick at a batch of 1 and 34 ms at
    a batch of 4 (whole grid cells at 10 and 25 laps ran at 40-50 ms), so the CPU flies
    :data:`CPU_BATCH` laps at a time.
    """
    import jax

    if jax.default_backend() == "cpu":
        return max(1, min(laps, CPU_BATCH))
    return laps


def cell_record(cell: Cell) -> dict:
    """The cell as stored in results.json (``"config"``): its name and its race's settings in JSON types, less
    the run's laps, seed and DOF weights (recorded beside them: the laps flown, ``seed``, ``dof_weights_sha256``)."""
    record = {"name": cell.name, **cell.spec.record()}
    for field in RUN_FIELDS:
        del record[field]
    return record


def recorded_race(done: dict) -> RaceSpec | None:
    """The race a finished cell's results ``done`` were flown as; None if they name no race this version knows.

    A setting a record lacks counts as its default (older files record fewer settings), and results written
    before the weights were recorded count as the packaged weights: the default they were flown with."""
    settings = {k: v for k, v in done.get("config", {}).items() if k != "name"}
    try:
        return RaceSpec.from_record({**settings, "laps": len(done.get("laps", [])), "seed": done.get("seed", 0),
                                     "dof_weights": done.get("dof_weights_sha256")})
    except ValueError:  # an unknown setting (a record of another version), no laps
        return None


def flies_race(done: dict | None, spec: RaceSpec) -> bool:
    """Whether a finished cell's results ``done`` were flown as the race ``spec``: the same :meth:`RaceSpec.key`."""
    flown = recorded_race(done) if done else None
    return flown is not None and flown.key() == spec.key()


def is_current(done: dict | None, spec: RaceSpec) -> bool:
    """Whether a finished cell's results ``done`` answer the race ``spec``: flown as it (:func:`flies_race`) and
    measured with this version's visibility measure (:data:`~pixelmpc_jax.sim.metrics.MEASURE`); results measured
    otherwise are flown again."""
    return flies_race(done, spec) and done.get("measure") == MEASURE


def load_results(out: Path) -> dict:
    """``{cell name: race results}`` finished so far in ``out/results.json`` (empty if none)."""
    path = Path(out) / "results.json"
    return json.loads(path.read_text()) if path.exists() else {}


def current_results(cells: list[Cell], out: Path, laps: int, seed: int = 0, dof_params=None) -> dict:
    """``{cell name: race results}`` of the cells in ``out/results.json`` that answer a run of ``cells`` with
    ``laps``, ``seed`` and ``dof_params`` (:func:`is_current`): what :func:`run_grid` would keep."""
    results = load_results(out)
    weights = None if dof_params is None else dof_weights_hash(dof_params)
    return {cell.name: results[cell.name] for cell in cells
            if is_current(results.get(cell.name), cell.race(laps, seed, weights))}


def find_shared(spec: RaceSpec, folders) -> tuple[Path, str, dict] | None:
    """``(folder, cell name, results)`` of a finished cell in one of ``folders`` (each a grid's output folder)
    that answers the race ``spec`` (:func:`is_current`, whatever its name); None when none does."""
    for folder in folders:
        for name, done in load_results(folder).items():
            if isinstance(done, dict) and is_current(done, spec):
                return Path(folder), name, done
    return None


def _copy_shared(shared: tuple[Path, str, dict], out: Path, name: str) -> dict:
    """The shared cell's results under ``name``, its trajectory files copied into ``out``."""
    import shutil

    folder, shared_name, done = shared
    for kind in ("trajectories", "covariances", "ticks"):
        source = folder / f"{kind}_{shared_name}.npz"
        if source.exists():
            shutil.copyfile(source, out / f"{kind}_{name}.npz")
    # the wall time was spent where it was flown; here it cost nothing
    return {**done, "shared_from": f"{folder.name}/{shared_name}", "wall_time_s": 0.0}


def _add_to_compact_record(out: Path, name: str, shared: tuple[Path, str, dict] | None = None) -> None:
    """Add cell ``name``'s per-tick record in ``out`` (``ticks_<name>.npz``, when it has one) to the folder's compact
    record (:mod:`~pixelmpc_jax.sim.ticks_compact`), the one a result folder commits. A cell copied from ``shared``
    (:func:`find_shared`) whose full record was not kept there (a folder brought back with its compact record only)
    takes its part of that folder's compact record."""
    source = out / f"ticks_{name}.npz"
    if source.exists():
        ticks_compact.update(out / ticks_compact.FILE_NAME, {name: ticks_compact.from_record(ticks_lib.load(source))})
        return
    if shared is None:
        return
    folder, shared_name, _ = shared
    compact = folder / ticks_compact.FILE_NAME
    if compact.exists():
        races = ticks_compact.load(compact, [shared_name])
        if shared_name in races:
            ticks_compact.update(out / ticks_compact.FILE_NAME, {name: races[shared_name]})


@dataclasses.dataclass(frozen=True)
class CellTask:
    """One cell's race to fly (:func:`fly_cell`), as an executor's task: it pickles to another process.

    Attributes:
        name: the cell's name.
        spec: the race, with the run's laps, seed and DOF weights (:meth:`Cell.race`).
        batch_size: laps per vmapped batch.
        dof_params: the DOF weights flown (None: the packaged ones), as NumPy arrays.
        progress: a progress bar over the laps (in-process only: workers fly silently).
    """

    name: str
    spec: RaceSpec
    batch_size: int
    dof_params: object = None
    progress: bool = False


@dataclasses.dataclass
class FlownCell:
    """What flying a cell returns to the process that writes the grid (:func:`fly_cell`).

    Attributes:
        results: the race's results (``laps``, ``aggregate``, ...) less its arrays, its race and key.
        trajectories: (T_i + 1, 10) flown states per lap.
        covariances: (T_i,) position covariance trace per tick per lap, with a filter (else empty).
        ticks: the per-tick records of the laps (:mod:`~pixelmpc_jax.sim.ticks`).
        camera: the camera the laps were seen with.
        wall_time_s: seconds the race took where it flew.
    """

    results: dict
    trajectories: list
    covariances: list
    ticks: list
    camera: object
    wall_time_s: float


def fly_cell(task: CellTask) -> FlownCell:
    """Fly one cell's race (:func:`~pixelmpc_jax.apps.racing.race.run_laps`): the task an executor runs."""
    start = time.perf_counter()
    res = race.run_laps(task.spec, batch_size=task.batch_size, progress=task.progress, dof_params=task.dof_params)
    trajectories, covariances = res.pop("trajectories"), res.pop("covariances")
    lap_ticks, camera = res.pop("ticks", []), res.pop("camera", None)
    for kind in ("visibility", "estimates", "race", "key"):  # the cell records its race itself (cell_record)
        res.pop(kind, None)
    return FlownCell(res, trajectories, covariances, lap_ticks, camera, time.perf_counter() - start)


def _write_flown(out: Path, results: dict, cell: Cell, spec: RaceSpec, flown: FlownCell) -> None:
    """Add a flown cell to the grid in ``out``: its results (with its ``config``, ``seed``, DOF fingerprint and wall
    time) into ``results`` and ``results.json`` (atomically), its trajectories, per-tick record (and its part of the
    compact record) and covariances beside it. A race cut short (Ctrl-C inside the cell) is not written: the
    KeyboardInterrupt is raised again with the finished cells kept."""
    path = out / "results.json"
    res = flown.results
    if res.get("interrupted") or len(res["laps"]) < spec.laps:
        raise KeyboardInterrupt(f"interrupted in cell {cell.name}: {len(results)} finished cell(s) kept in "
                                f"{path}; run again to resume")
    results[cell.name] = {**res, "config": cell_record(cell), "seed": spec.seed,
                          "dof_weights_sha256": spec.dof_fingerprint(), "wall_time_s": flown.wall_time_s}
    write_json_atomic(path, results)
    np.savez_compressed(out / f"trajectories_{cell.name}.npz", *flown.trajectories)
    if flown.ticks:
        ticks_lib.write(out / f"ticks_{cell.name}.npz", flown.ticks, flown.camera, spec.speed)
        _add_to_compact_record(out, cell.name)
    if flown.covariances:
        np.savez_compressed(out / f"covariances_{cell.name}.npz", *flown.covariances)


def run_grid(cells: list[Cell], out: Path, laps: int = 10, seed: int = 0, batch_size: int | None = None,
             progress: bool = True, dof_params=None, reuse=(), executor: Executor | None = None) -> dict:
    """Run every cell not yet in ``out/results.json``; returns ``{cell name: race results}``.

    Each cell flies its race with ``laps``, ``seed`` and the DOF weights ``dof_params`` (None: the packaged
    weights). A cell in the file is kept only if it recorded the same race (see :func:`is_current`); each cell's
    results record its settings (``config``, :func:`cell_record`), ``seed`` and ``dof_weights_sha256``
    (:func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`, null for a cell that uses no DOF).

    ``batch_size`` laps fly in one vmapped batch (default :func:`default_batch_size`); a lap's result does
    not depend on it (lap i always uses seed ``seed + i``).

    Each finished cell also leaves ``trajectories_<cell>.npz`` (the flown states per lap), ``ticks_<cell>.npz``
    (the per-tick record, :mod:`~pixelmpc_jax.sim.ticks`, from which any measure is recomputed), its part of
    ``ticks_compact.npz`` (what the measure reads, small enough to commit: :mod:`~pixelmpc_jax.sim.ticks_compact`)
    and, with the particle filter, ``covariances_<cell>.npz`` (its position covariance trace per tick). A cell whose
    race a finished cell in one of the ``reuse`` folders already answers (:func:`find_shared`) is copied from there,
    not flown again (its results name it in ``shared_from``).

    ``executor`` (:mod:`~pixelmpc_jax.apps.racing.executor`) flies the cells left as its tasks, each in whichever
    worker is free, while this process writes each cell as it completes (the files and resume are the same); a cell
    that fails is named with its error, the others are written, and a RuntimeError naming the failed cells is raised
    at the end. None: the cells fly one after another here, a failure raised at once (as before executors).
    Interrupted (Ctrl-C, SIGTERM under the ``pixelmpc`` command), the finished cells stay in ``results.json``, the
    executor's workers are stopped and the KeyboardInterrupt is raised again: a grid never returns as if it were
    complete."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = load_results(out)
    batch_size = batch_size or default_batch_size(laps)
    weights = None if dof_params is None else dof_weights_hash(dof_params)
    specs = {cell.name: cell.race(laps, seed, weights) for cell in cells}
    to_fly = [cell for cell in cells if not _kept_or_shared(cell, specs[cell.name], out, results, reuse, progress)]
    if executor is None:
        for cell in to_fly:
            task = CellTask(cell.name, specs[cell.name], batch_size, dof_params, progress)
            _write_flown(out, results, cell, specs[cell.name], fly_cell(task))
        return results
    host_params = None if dof_params is None else jax.tree_util.tree_map(np.asarray, dof_params)
    tasks = [CellTask(cell.name, specs[cell.name], batch_size, host_params) for cell in to_fly]
    by_name = {cell.name: cell for cell in to_fly}
    failed = {}
    bar = tqdm(total=len(tasks), unit="cell", desc=out.name, disable=not progress or not tasks)
    try:
        with contextlib.closing(executor.run(fly_cell, tasks)) as completed:
            for task, flown, error in completed:
                if error is None:
                    _write_flown(out, results, by_name[task.name], task.spec, flown)
                else:
                    failed[task.name] = error
                    bar.write(f"[{task.name}] failed: {error}")
                bar.update(1)
    finally:
        bar.close()
        executor.close()
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(tasks)} cell(s) failed ({', '.join(failed)}); the others are in "
                           f"{out / 'results.json'}. First: [{next(iter(failed))}] {next(iter(failed.values()))}")
    return results


def _kept_or_shared(cell: Cell, spec: RaceSpec, out: Path, results: dict, reuse, progress: bool) -> bool:
    """Whether ``cell`` needs no flying: kept from ``results`` (it answers ``spec``) or copied from a folder of
    ``reuse`` (:func:`find_shared`; added to ``results`` and ``results.json``)."""
    path = out / "results.json"
    done = results.get(cell.name)
    if is_current(done, spec):
        if progress:
            print(f"[{cell.name}] kept from {path} ({len(done['laps'])} laps)")
        return True
    shared = find_shared(spec, [folder for folder in reuse if Path(folder).resolve() != out.resolve()])
    if shared is None:
        return False
    results[cell.name] = _copy_shared(shared, out, cell.name)
    write_json_atomic(path, results)
    _add_to_compact_record(out, cell.name, shared)
    if progress:
        print(f"[{cell.name}] shared from {results[cell.name]['shared_from']}")
    return True


def fmt(entry: dict | None, digits: int = 1) -> str:
    """'mean +- 2sigma' of an aggregate entry."""
    if not entry or entry.get("mean") is None:
        return "-"
    return f"{entry['mean']:.{digits}f} ± {entry['two_sigma']:.{digits}f}"
