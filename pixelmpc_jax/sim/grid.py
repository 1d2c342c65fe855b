"""Experiment grids: named cells of laps, run batched, resumable, reported beside the paper's figures.

A grid is a list of :class:`Cell` (a controller and its settings); each cell flies ``laps`` races
(seeds ``seed .. seed + laps - 1``, batched with ``vmap``). After every cell the results file is
rewritten atomically, and a cell already in the file is not recomputed, so an interrupted run resumes.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from pixelmpc_jax.sim import race


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


def load_results(out: Path) -> dict:
    """``{cell name: race results}`` finished so far in ``out/results.json`` (empty if none)."""
    path = Path(out) / "results.json"
    return json.loads(path.read_text()) if path.exists() else {}


def run_grid(cells: list[Cell], out: Path, laps: int = 10, seed: int = 0, batch_size: int | None = None,
             progress: bool = True, dof_params=None) -> dict:
    """Run every cell not yet in ``out/results.json``; returns ``{cell name: race results}``.

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
    for cell in cells:
        done = results.get(cell.key())
        if done and len(done.get("laps", [])) >= laps and done.get("config") == cell_record(cell):
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
