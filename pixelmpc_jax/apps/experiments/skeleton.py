"""One skeleton for every experiment: cells -> grid -> summary -> report -> plot.

An :class:`Experiment` holds what is particular to one experiment: its cells, how their results sum up, the
report of that summary, its figures and the JSON record of it. :func:`run` does the rest, the same for each: it
flies the cells not finished yet (:func:`~pixelmpc_jax.apps.racing.grid.run_grid`, resumable per cell; a cell
another grid folder already flew is copied), keeps the finished cells that answer this run (the same race, laps,
seed and weights), summarises them and writes the record, ``REPORT.md`` and the figures. Interrupted (Ctrl-C), it
writes all of them from the cells finished so far (the report names the others) and raises the KeyboardInterrupt
again: an experiment never returns as if it were complete.

Also the summaries' shared piece: the failed laps counted by cause (:func:`failure_counts`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pixelmpc_jax.apps.racing import grid
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash
from pixelmpc_jax.strict_json import write_json_atomic


@dataclasses.dataclass(frozen=True)
class Experiment:
    """What is particular to one experiment; :func:`run` flies and writes it.

    Attributes:
        cells: the grid's cells, in the order they fly (names unique).
        summarise: ``{cell name: race results}`` of the finished cells -> the summary (rows, a frontier, ...).
        report: (summary, names of the cells not finished) -> the Markdown of ``REPORT.md``.
        plot: (summary, output folder) -> draws the figures into the folder and returns the Markdown appended to
            the report ("" where the report already shows them); None: no figures.
        record: summary -> the JSON object written to ``record_file``; None: no record.
        record_file: the record's file name in the output folder.
        cell_laps: ``{cell name: laps}`` of the cells that fly another number of laps than the run's.
    """

    cells: tuple[grid.Cell, ...]
    summarise: Callable[[dict], Any]
    report: Callable[[Any, list[str]], str]
    plot: Callable[[Any, Path], str] | None = None
    record: Callable[[Any], Any] | None = None
    record_file: str = "summary.json"
    cell_laps: Mapping[str, int] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        names = [cell.name for cell in self.cells]
        if len(set(names)) != len(names):
            raise ValueError(f"cell names repeat: {sorted(n for n in set(names) if names.count(n) > 1)}")

    def laps_of(self, cell: grid.Cell, laps: int | None) -> int:
        """The laps ``cell`` flies in a run of ``laps`` laps."""
        return self.cell_laps.get(cell.name, laps)


def fly(experiment: Experiment, out: Path, laps: int | None, seed: int, progress: bool = True, dof_params=None,
        reuse=(), executor=None) -> None:
    """Fly the experiment's cells not finished in ``out`` (:func:`grid.run_grid`, on ``executor``: None flies them
    one after another in this process), the cells of one number of laps at a time, the most laps first."""
    counts = sorted({experiment.laps_of(cell, laps) for cell in experiment.cells}, reverse=True)
    for count in counts:
        grid.run_grid([cell for cell in experiment.cells if experiment.laps_of(cell, laps) == count], out,
                      laps=count, seed=seed, progress=progress, dof_params=dof_params, reuse=reuse, executor=executor)


def finished(experiment: Experiment, out: Path, laps: int | None, seed: int, dof_params=None) -> dict:
    """``{cell name: race results}`` of the cells finished in ``out/results.json`` that answer this run: its laps,
    seed and DOF weights (:func:`grid.is_current`); a cell recorded otherwise counts as not finished."""
    recorded = grid.load_results(out)
    weights = None if dof_params is None else dof_weights_hash(dof_params)
    return {cell.name: recorded[cell.name] for cell in experiment.cells
            if grid.is_current(recorded.get(cell.name), cell.race(experiment.laps_of(cell, laps), seed, weights))}


def write(experiment: Experiment, summary, missing: list[str], out: Path) -> None:
    """The record, the figures and ``REPORT.md`` of ``summary`` in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if experiment.record is not None:
        write_json_atomic(out / experiment.record_file, experiment.record(summary))
    figures = experiment.plot(summary, out) if experiment.plot is not None else ""
    (out / "REPORT.md").write_text(experiment.report(summary, missing) + figures)


def run(experiment: Experiment, out: Path, laps: int | None, seed: int = 0, progress: bool = True, dof_params=None,
        reuse=(), flies: bool = True, executor=None):
    """Fly ``experiment`` into ``out`` (``laps`` laps per cell but its ``cell_laps``, from ``seed``, with the DOF
    weights ``dof_params``, None for the packaged ones; cells a folder in ``reuse`` already flew are copied; on
    ``executor``, :mod:`~pixelmpc_jax.apps.racing.executor`, None for this process),
    summarise the finished cells and write the outputs (:func:`write`); returns the summary. ``flies=False``:
    only the outputs of the cells already finished. Interrupted, the outputs of the finished cells are written and
    the KeyboardInterrupt is raised again."""
    out = Path(out)
    interrupted = False
    if flies:
        try:
            fly(experiment, out, laps, seed, progress, dof_params, reuse, executor)
        except KeyboardInterrupt:
            interrupted = True
    results = finished(experiment, out, laps, seed, dof_params)
    summary = experiment.summarise(results)
    missing = [cell.name for cell in experiment.cells if cell.name not in results]
    write(experiment, summary, missing, out)
    if interrupted:
        raise KeyboardInterrupt(f"interrupted: {len(missing)} cell(s) not finished; run again to resume")
    return summary


def cells_experiment(cells) -> Experiment:
    """An experiment of explicit cells (a grid file's, :mod:`~pixelmpc_jax.apps.racing.grid_file`): its summary is
    each finished cell's success rate and lap time (``summary.json``), its report their table."""

    def summarise(results: dict) -> list[dict]:
        return [{"cell": cell.name, "settings": cell.spec.changed_settings(), **_cell_row(results[cell.name])}
                for cell in cells if cell.name in results]

    def report(rows: list[dict], missing: list[str]) -> str:
        lines = ["# Grid of cells", "", "| cell | laps | success | lap time [s] | worst lap [s] |",
                 "|---|---|---|---|---|"]
        for row in rows:
            worst = "-" if row["worst_lap_s"] is None else f"{row['worst_lap_s']:.2f}"
            lines.append(f"| {row['cell']} | {row['laps']} | {row['success_rate'] * 100:.0f}% | "
                         f"{grid.fmt(row['lap_time_s'], 2)} | {worst} |")
        if missing:
            lines += ["", f"Not finished: {', '.join(missing)}."]
        return "\n".join(lines) + "\n"

    return Experiment(tuple(cells), summarise=summarise, report=report, record=lambda rows: rows)


def _cell_row(done: dict) -> dict:
    """A finished cell's laps, success rate, lap time (mean and two sigma) and worst finished lap."""
    times = [lap["lap_time_s"] for lap in done["laps"] if lap.get("success") and lap.get("lap_time_s") is not None]
    return {"laps": len(done["laps"]), "success_rate": done["aggregate"]["success_rate"],
            "lap_time_s": done["aggregate"].get("lap_time_s"), "worst_lap_s": max(times) if times else None}


def report_end(rows: list[dict], missing: list[str]) -> list[str]:
    """A report's closing lines: the cells not run yet (the experiment resumes with them), and the wall time of the
    cells ``rows`` flown here (each row's ``wall_time_s``)."""
    lines = []
    if missing:
        lines += ["", f"Not yet run (the experiment resumes with them): {', '.join(missing)}."]
    wall = sum(r["wall_time_s"] or 0.0 for r in rows)
    return lines + ["", f"Wall time of the cells flown here: {wall / 60:.1f} min."]


def episode_end(lap: dict) -> str | None:
    """How a lap's episode ended: its ``crash`` (gate, ground, wall, missed_gate, timeout, target_mismatch; None while
    flying)."""
    return lap.get("crash")


def failure_counts(laps: list[dict], cause: Callable[[dict], str | None] = episode_end) -> dict:
    """``{cause: failed laps}`` over the laps that did not succeed, each failed lap's cause ``cause(lap)`` (by
    default the end of its episode)."""
    counts: dict = {}
    for lap in laps:
        if not lap.get("success"):
            counts[cause(lap)] = counts.get(cause(lap), 0) + 1
    return counts
