"""Experiment grids: named cells of laps, run batched, resumable, reported beside the paper's figures.

A grid is a list of :class:`Cell` (a controller and its settings); each cell flies ``laps`` races
(seeds ``seed .. seed + laps - 1``, batched with ``vmap``). After every cell the results file is
rewritten atomically, and a cell already in the file is not recomputed, so an interrupted run resumes.
A cell is kept only when it was flown with the same settings (:func:`cell_record`), seed, number of laps and
DOF weights (:func:`dof_weights_hash`) as the new run; otherwise it is flown again and replaced.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from pixelmpc_jax.apps import race


@dataclasses.dataclass(frozen=True)
class Cell:
    """One cell of an experiment grid."""

    name: str
    controller: str = "mppi"
    t_f: float = 1.0
    c_pixel: float = 9e6
    pixel_model: str = "dof"
    speed: float = 14.0
    estimator: str = "truth"
    course: str = "alphapilot"
    max_time_s: float = 60.0
    options: tuple = ()

    def __post_init__(self):
        # options: (name, value) pairs of further controller settings (see race.make_policy), kept sorted
        # so that the same settings always make the same cell
        object.__setattr__(self, "options", tuple(sorted((str(k), v) for k, v in dict(self.options).items())))

    def key(self) -> str:
        return self.name


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
    """The cell's settings as stored in results.json (JSON types: the options as a name -> value mapping)."""
    record = dataclasses.asdict(cell)
    record["options"] = dict(cell.options)
    if not record["options"]:
        del record["options"]  # cells without options keep the record older results files hold
    return record


def uses_dof(cell: Cell) -> bool:
    """Whether the cell's controller evaluates the DOF network (PixelMPC with the "dof" pixel model)."""
    return cell.controller == "pixelmpc" and cell.pixel_model == "dof"


def dof_weights_hash(params) -> str:
    """A short fingerprint of DOF weights: the first 16 hex digits of the sha256 of every leaf's dtype, shape
    and bytes (in ``jax.tree_util.tree_leaves`` order)."""
    import jax

    digest = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(params):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def packaged_dof_hash() -> str:
    """:func:`dof_weights_hash` of the DOF weights shipped inside the package."""
    from pixelmpc_jax.dynamics import dof

    return dof_weights_hash(dof.load_packaged_dof())


def is_current(done: dict | None, cell: Cell, laps: int, seed: int, dof_hash: str | None,
               packaged_hash=packaged_dof_hash) -> bool:
    """Whether a finished cell's results ``done`` answer a run of ``cell`` for ``laps`` laps from ``seed`` with
    DOF weights of fingerprint ``dof_hash`` (None for a cell that uses no DOF).

    Results written before the seed and the weights were recorded count as seed 0 and the packaged weights
    (``packaged_hash``: called only for such a record of a DOF cell), the defaults they were flown with."""
    if not done or len(done.get("laps", [])) != laps or done.get("config") != cell_record(cell):
        return False
    if done.get("seed", 0) != seed:
        return False
    if "dof_weights_sha256" in done:
        return done["dof_weights_sha256"] == dof_hash
    return dof_hash is None or dof_hash == packaged_hash()


def load_results(out: Path) -> dict:
    """``{cell name: race results}`` finished so far in ``out/results.json`` (empty if none)."""
    path = Path(out) / "results.json"
    return json.loads(path.read_text()) if path.exists() else {}


def _fingerprints(dof_params):
    """``(run_hash, packaged_hash)``: callables giving the fingerprint of the weights a DOF cell flies with
    (``dof_params``, or the packaged weights when None) and of the packaged weights, each computed once."""
    hashes: dict[str, str] = {}

    def packaged_hash() -> str:
        if "packaged" not in hashes:
            hashes["packaged"] = packaged_dof_hash()
        return hashes["packaged"]

    def run_hash() -> str:
        if "run" not in hashes:
            hashes["run"] = packaged_hash() if dof_params is None else dof_weights_hash(dof_params)
        return hashes["run"]

    return run_hash, packaged_hash


def current_results(cells: list[Cell], out: Path, laps: int, seed: int = 0, dof_params=None) -> dict:
    """``{cell name: race results}`` of the cells in ``out/results.json`` that answer a run of ``cells`` with
    ``laps``, ``seed`` and ``dof_params`` (:func:`is_current`): what :func:`run_grid` would keep."""
    results = load_results(out)
    run_hash, packaged_hash = _fingerprints(dof_params)
    return {cell.key(): results[cell.key()] for cell in cells
            if is_current(results.get(cell.key()), cell, laps, seed, run_hash() if uses_dof(cell) else None,
                          packaged_hash)}


def run_grid(cells: list[Cell], out: Path, laps: int = 10, seed: int = 0, batch_size: int | None = None,
             progress: bool = True, dof_params=None) -> dict:
    """Run every cell not yet in ``out/results.json``; returns ``{cell name: race results}``.

    A cell in the file is kept only if it was flown with the same settings, ``laps``, ``seed`` and DOF weights
    (``dof_params``, or the packaged weights when None) as asked now (see :func:`is_current`); each cell's
    results record its ``seed`` and ``dof_weights_sha256`` (:func:`dof_weights_hash`, null for a cell that
    uses no DOF).

    ``batch_size`` laps fly in one vmapped batch (default :func:`default_batch_size`); a lap's result does
    not depend on it (lap i always uses seed ``seed + i``).

    Each finished cell also leaves ``trajectories_<cell>.npz`` (the flown states per lap) and, with the
    particle filter, ``covariances_<cell>.npz`` (its position covariance trace per tick). Interrupted (Ctrl-C),
    the finished cells stay in ``results.json`` and the KeyboardInterrupt is raised again: a grid never returns
    as if it were complete."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    results = load_results(out)
    batch_size = batch_size or default_batch_size(laps)
    run_hash, packaged_hash = _fingerprints(dof_params)
    for cell in cells:
        done = results.get(cell.key())
        dof_hash = run_hash() if uses_dof(cell) else None
        if is_current(done, cell, laps, seed, dof_hash, packaged_hash):
            if progress:
                print(f"[{cell.name}] kept from {path} ({len(done['laps'])} laps)")
            continue
        start = time.perf_counter()
        res = race.run_laps(controller=cell.controller, speed=cell.speed, laps=laps, seed=seed, out=None,
                            batch_size=batch_size, max_time_s=cell.max_time_s, progress=progress,
                            pixel_model=cell.pixel_model, t_f=cell.t_f, c_pixel=cell.c_pixel,
                            dof_params=dof_params, estimator=cell.estimator, course=cell.course,
                            options=dict(cell.options))
        trajectories = res.pop("trajectories")
        covariances = res.pop("covariances")
        if res.get("interrupted") or len(res["laps"]) < laps:  # interrupted inside the cell: keep what is done
            raise KeyboardInterrupt(f"interrupted in cell {cell.name}: {len(results)} finished cell(s) kept in "
                                    f"{path}; run again to resume")
        res["config"] = cell_record(cell)
        res["seed"] = seed
        res["dof_weights_sha256"] = dof_hash
        res["wall_time_s"] = time.perf_counter() - start
        results[cell.key()] = res
        race.write_json_atomic(path, results)
        np.savez_compressed(out / f"trajectories_{cell.name}.npz", *trajectories)
        if covariances:
            np.savez_compressed(out / f"covariances_{cell.name}.npz", *covariances)
    return results


def fmt(entry: dict | None, digits: int = 1) -> str:
    """'mean +- 2sigma' of an aggregate entry."""
    if not entry or entry.get("mean") is None:
        return "-"
    return f"{entry['mean']:.{digits}f} ± {entry['two_sigma']:.{digits}f}"
