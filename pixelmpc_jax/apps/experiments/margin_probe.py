"""The margin probe: the ``best`` preset's clearance to the gate frames (``presets.BEST_VEHICLE_RADIUS_M``, 0.3 m)
against the vehicle's own 0.1 m, where the reproduction reports it: the true-state frontier cell at the preset's
pace (10 laps) and Table IV's filter cells at both paces (25 laps).

    pixelmpc reproduce frontier --out runs/reproduce
    pixelmpc experiment margin-probe --out runs/margin --frontier runs/reproduce/frontier [--seed 200]

Two experiments (:mod:`~pixelmpc_jax.apps.experiments.skeleton`), each resumable per cell: ``truth/``, the speed
frontier of the reproduction's nominal speeds with both clearances (:func:`~pixelmpc_jax.apps.experiments.frontier.
frontier_experiment`: ``frontier.json``, ``REPORT.md``, ``frontier.png``; the nominal cells the ``--frontier``
folders flew on the same seeds are copied, not flown again), and ``pf/``, the filter cells (``summary.json``,
``REPORT.md``: laps completed and failures by cause). Cells: ``margin_*`` the preset, ``plain_*`` the preset with
the 0.1 m clearance.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pixelmpc_jax.apps.experiments import frontier, skeleton
from pixelmpc_jax.apps.experiments.reproduce import SEED
from pixelmpc_jax.apps.experiments.skeleton import Experiment, failure_counts
from pixelmpc_jax.apps.racing.grid import Cell, fmt
from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEEDS, preset
from pixelmpc_jax.control.costs import RacingCostConfig

TRUTH_LAPS = 10  # the frontier's laps per cell
FILTER_LAPS = 25  # Table IV's
FILTER_LABELS = (16.0, 14.0)  # the paper's labels whose paces the filter cells fly, the fastest first


def clearances() -> dict:
    """``{"margin": the best preset, "plain": the preset with the vehicle's own 0.1 m clearance}``."""
    best = preset("best")
    return {"margin": best, "plain": best.replace(config=dataclasses.replace(best.config, racing=RacingCostConfig()))}


def filter_cells() -> list[Cell]:
    """Both clearances on the particle filter at each label's pace."""
    return [Cell(f"{name}_{PAPER_PACE_SPEEDS[label]:g}ms_pf", spec.replace(speed=PAPER_PACE_SPEEDS[label],
                                                                          estimator="pf"))
            for label in FILTER_LABELS for name, spec in clearances().items()]


def filter_rows(results: dict, cells: list[Cell]) -> list[dict]:
    """One row per finished filter cell: laps completed, lap time and failures by cause."""
    return [{"cell": cell.name, "speed": cell.spec.speed, "successes": sum(bool(lap["success"]) for lap in
                                                                          results[cell.name]["laps"]),
             "num_laps": len(results[cell.name]["laps"]), "lap_time_s": results[cell.name]["aggregate"]["lap_time_s"],
             "failures": failure_counts(results[cell.name]["laps"])}
            for cell in cells if cell.name in results]


def filter_report(rows: list[dict], missing: list[str]) -> str:
    lines = ["# The clearance on the particle filter", "",
             "`margin_*`: the `best` preset (0.3 m to the frames); `plain_*`: the preset with the vehicle's 0.1 m. "
             "Lap time over the completed laps, mean ± 2σ.", "",
             "| cell | target [m/s] | laps completed | lap time [s] | failures |", "|---|---|---|---|---|"]
    for r in rows:
        failures = ", ".join(f"{cause}: {count}" for cause, count in r["failures"].items()) or "-"
        lines.append(f"| {r['cell']} | {r['speed']:g} | {r['successes']}/{r['num_laps']} | {fmt(r['lap_time_s'])} | "
                     f"{failures} |")
    if missing:
        lines += ["", f"Not yet run (the experiment resumes with them): {', '.join(missing)}."]
    return "\n".join(lines) + "\n"


def margin_probe(out: Path, frontier_folders=(), seed: int = SEED, progress: bool = True, executor=None) -> dict:
    """Fly both clearances on the true state (against the nominal frontier, in ``out/truth``) and on the filter (in
    ``out/pf``), laps from ``seed``; nominal cells the grid folders ``frontier_folders`` flew are copied. Returns
    ``{"truth": the frontier, "filter": the filter rows}``.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    out = Path(out)
    spaced = clearances()
    truth_cells = [Cell(f"{name}_v{spec.speed:g}", spec) for name, spec in spaced.items()]
    truth = frontier.frontier_experiment(frontier.DEFAULT_SPEEDS, truth_cells, TRUTH_LAPS, seed,
                                         spaced["margin"].max_time_s)
    built = skeleton.run(truth, out / "truth", TRUTH_LAPS, seed, progress, reuse=frontier_folders,
                         executor=executor)
    cells = filter_cells()
    filtered = Experiment(tuple(cells), summarise=lambda results: filter_rows(results, cells), report=filter_report,
                          record=lambda rows: rows)
    return {"truth": built,
            "filter": skeleton.run(filtered, out / "pf", FILTER_LAPS, seed, progress, executor=executor)}
