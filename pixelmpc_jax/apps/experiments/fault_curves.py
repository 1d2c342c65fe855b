"""Success against the size of a fault: steady wind 0-6 m/s and detection delay 0-3 ticks (issue 39, item 4).

The robustness grid (:mod:`~pixelmpc_jax.apps.experiments.robustness`) flies each fault at two sizes; these curves
sweep the two faults whose size decides most where a filter stops helping: a steady wind along the course's x axis
(:data:`WIND_M_S`, the grid's moderate level is 3 m/s and its severe 6 m/s) and the ticks a detection arrives late
(:data:`DELAY_TICKS`, 25 ms each). Each point is flown by nominal MPPI (the paper's settings) and PixelMPC (the
``best`` preset) at the preset's pace, on the particle filter's estimate and on the error-state Kalman filter's,
:data:`LAPS` laps from the robustness grid's seed, so the fault-free point is the grid's fault-free cell (and is
copied from a robustness folder passed in ``reuse``). With ``levers`` (names of
:data:`~pixelmpc_jax.apps.experiments.robustness.LEVER_SETS` that apply to both filters: ``model``), both
controllers fly every point once more with them on, as they do in the grid.

Writes ``results.json`` (resumable per cell), ``curves.json``, ``REPORT.md`` and ``fault_curves.png``: success
against wind and against delay, one line per controller and estimator, in one figure.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from pixelmpc_jax.apps.experiments import robustness as robust_lib
from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.experiments.skeleton import Experiment, failure_counts
from pixelmpc_jax.apps.racing.grid import Cell, fmt
from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.sim.faults import Faults

WIND_M_S = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)  # steady wind along +x, m/s
DELAY_TICKS = (0, 1, 2, 3)  # detection delay, control ticks (25 ms each)
CURVES = {"wind": WIND_M_S, "detection_delay": DELAY_TICKS}
UNITS = {"wind": "m/s", "detection_delay": "ticks"}
ESTIMATORS = ("pf", "eskf")
LAPS = 10
QUICK_LAPS = 2


class CurvePoint(NamedTuple):
    """A cell with what it measures: the curve (None for the fault-free point, on both curves), the fault's size,
    the controller, the estimator and the set of levers (None: none)."""

    cell: Cell
    curve: str | None
    value: float
    controller: str
    estimator: str
    levers: str | None


def faults_at(curve: str, value: float) -> Faults:
    """The faults of one point of ``curve``."""
    if curve == "wind":
        return Faults(wind=(float(value), 0.0, 0.0))
    if curve == "detection_delay":
        return Faults(detection_delay_ticks=int(value))
    raise ValueError(f"unknown curve {curve!r}; choose one of {', '.join(CURVES)}")


def curve_cells(estimators: tuple = ESTIMATORS, levers: tuple = (), quick: bool = False,
                curves: tuple = tuple(CURVES)) -> list[CurvePoint]:
    """Every point of the ``curves`` (names of :data:`CURVES`; default both) for each controller, estimator (of
    :data:`ESTIMATORS`) and set of ``levers`` (each a set of
    :data:`~pixelmpc_jax.apps.experiments.robustness.LEVER_SETS` that applies to both filters; both controllers),
    the fault-free point once; ``quick``: the ends and the middle of each curve only."""
    for estimator in estimators:
        if estimator not in ESTIMATORS:
            raise ValueError(f"unknown estimator {estimator!r}; the curves fly {', '.join(ESTIMATORS)}")
    for curve in curves:
        if curve not in CURVES:
            raise ValueError(f"unknown curve {curve!r}; choose from {', '.join(CURVES)}")
    for lever in levers:
        if lever not in robust_lib.LEVER_SETS or not all(robust_lib.applies(lever, e) for e in ESTIMATORS):
            raise ValueError(f"levers {lever!r} do not fly on both filters; choose from "
                             f"{', '.join(robust_lib.CONTROLLER_LEVERS)}")
    points = []
    for estimator in estimators:
        for controller in robust_lib.CONTROLLERS:
            for lever in (None, *levers):
                suffix = f"_{lever}" if lever else ""
                spec = robust_lib.race(controller, estimator, Faults(), lever)
                points.append(CurvePoint(Cell(f"{controller}_{estimator}_none{suffix}", spec), None, 0.0, controller,
                                         estimator, lever))
                for curve, values in ((c, v) for c, v in CURVES.items() if c in curves):
                    kept = (values[len(values) // 2], values[-1]) if quick else values[1:]
                    for value in kept:
                        spec = robust_lib.race(controller, estimator, faults_at(curve, value), lever)
                        points.append(CurvePoint(Cell(f"{controller}_{estimator}_{curve}_{value:g}{suffix}", spec),
                                                 curve, float(value), controller, estimator, lever))
    return points


def summarise(results: dict, points: list[CurvePoint]) -> list[dict]:
    """One row per finished point: what it measures, its success, lap time, position errors and failures."""
    rows = []
    for point in points:
        res = results.get(point.cell.name)
        if res is None:
            continue
        laps = res["laps"]
        squares = [lap["rms_position_error_m"] ** 2 for lap in laps if lap.get("rms_position_error_m") is not None]
        worst = [lap["max_position_error_m"] for lap in laps if lap.get("max_position_error_m") is not None]
        rows.append({"cell": point.cell.name, "curve": point.curve, "value": point.value,
                     "controller": point.controller, "estimator": point.estimator, "levers": point.levers,
                     "num_laps": len(laps), "successes": sum(bool(lap.get("success")) for lap in laps),
                     "lap_time_s": res.get("aggregate", {}).get("lap_time_s"),
                     "rms_position_error_m": float(np.sqrt(np.mean(squares))) if squares else None,
                     "max_position_error_m": max(worst) if worst else None,
                     "failures": failure_counts(laps, robust_lib.failure_cause),
                     "wall_time_s": res.get("wall_time_s"), "shared_from": res.get("shared_from")})
    return rows


def _loops(rows: list[dict]) -> list[tuple]:
    """(controller, estimator, levers) of the rows, in a fixed order."""
    present = {(r["controller"], r["estimator"], r["levers"]) for r in rows}
    order = [(c, e, lever) for e in ESTIMATORS for c in robust_lib.CONTROLLERS
             for lever in (None, *robust_lib.LEVER_SETS)]
    return [key for key in order if key in present]


def curve_points(rows: list[dict], curve: str, loop: tuple) -> list[dict]:
    """The rows of one loop along ``curve``, its fault-free point first, by size."""
    return sorted((r for r in rows if (r["controller"], r["estimator"], r["levers"]) == loop
                   and r["curve"] in (None, curve)), key=lambda r: r["value"])


def _curve_table(rows: list[dict], curve: str) -> list[str]:
    values = sorted({r["value"] for r in rows if r["curve"] in (None, curve)})
    lines = ["| loop | " + " | ".join(f"{v:g} {UNITS[curve]}" for v in values) + " |",
             "|---|" + "---|" * len(values)]
    for loop in _loops(rows):
        by_value = {r["value"]: r for r in curve_points(rows, curve, loop)}
        cells = [f"{by_value[v]['successes']}/{by_value[v]['num_laps']}" if v in by_value else "-" for v in values]
        lines.append(f"| {robust_lib.loop_label(*loop)} | " + " | ".join(cells) + " |")
    return lines


def _detail_table(rows: list[dict]) -> list[str]:
    lines = ["| curve | size | loop | success | lap time [s] | RMS position error [m] | max position error [m] | "
             "failures |", "|---" * 8 + "|"]
    for r in rows:
        rms, worst = r["rms_position_error_m"], r["max_position_error_m"]
        loop = robust_lib.loop_label(r["controller"], r["estimator"], r["levers"])
        lines.append(f"| {r['curve'] or 'none'} | {r['value']:g} | {loop} | "
                     f"{r['successes']}/{r['num_laps']} | {fmt(r['lap_time_s'])} | "
                     f"{'-' if rms is None else f'{rms:.3f}'} | {'-' if worst is None else f'{worst:.2f}'} | "
                     f"{robust_lib.failures_text(r['failures'])} |")
    return lines


def markdown_report(rows: list[dict], device: str, missing: list[str]) -> str:
    """REPORT.md: success along each curve per loop, then every point in detail."""
    lines = ["# Success against steady wind and detection delay", "",
             f"Device: {device}. Nominal MPPI (the paper's settings) and PixelMPC (`best` preset) at the paper's pace "
             f"(8.5 m/s) on the AlphaPilot course, seeds from {robust_lib.SEED}, on the particle filter's and the "
             "error-state Kalman filter's estimate. Wind: steady, along the course's x axis. Delay: control ticks of "
             f"25 ms between an image and its detection reaching the loop. Laps completed / flown; a failed lap whose "
             f"estimate strayed more than {robust_lib.DIVERGED_M:g} m counts as \"estimate diverged\".", "",
             "![success against wind and delay](fault_curves.png)", "",
             "## Steady wind", "", *_curve_table(rows, "wind"), "",
             "## Detection delay", "", *_curve_table(rows, "detection_delay"), "",
             "## Every point", "", *_detail_table(rows)]
    lines += skeleton.report_end(rows, missing)
    return "\n".join(lines) + "\n"


def plot_curves(rows: list[dict], path: Path) -> None:
    """Success against wind (left) and delay (right), one line per loop: colour by estimator, style by controller."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"pf": "tab:orange", "eskf": "tab:blue"}
    styles = {"mppi": "--", "pixelmpc": "-"}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), sharey=True, layout="constrained")
    for ax, curve in zip(axes, CURVES):
        for loop in _loops(rows):
            points = curve_points(rows, curve, loop)
            if not points:
                continue
            x = [p["value"] for p in points]
            y = [p["successes"] / max(p["num_laps"], 1) for p in points]
            ax.plot(x, y, styles[loop[0]], marker="o" if loop[2] is None else "s", color=colours[loop[1]],
                    label=robust_lib.loop_label(*loop), alpha=1.0 if loop[2] is None else 0.6)
        ax.set_xlabel(f"{curve.replace('_', ' ')} [{UNITS[curve]}]")
        ax.set_xticks(CURVES[curve])
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("laps completed (share)")
    handles, labels = axes[0].get_legend_handles_labels()
    if not handles:  # the wind curve not flown: the delay panel names the loops
        handles, labels = axes[1].get_legend_handles_labels()
    columns = 4 if len(labels) <= 4 else 2  # more loops: two columns, each label whole inside the figure
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncol=min(len(labels), columns) or 1)
    fig.suptitle("Success against steady wind and detection delay (8.5 m/s, AlphaPilot)", fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _figure(rows: list[dict], out: Path) -> str:
    if rows:
        plot_curves(rows, out / "fault_curves.png")
    return ""


def fault_curves_experiment(out: Path, quick: bool = False, progress: bool = True, estimators: tuple = ESTIMATORS,
                            levers: tuple = (), reuse=(), run: bool = True,
                            curves: tuple = tuple(CURVES), executor=None) -> list[dict]:
    """Fly the ``curves`` (default both) into ``out`` (resumable per cell; :data:`LAPS` laps per point,
    :data:`QUICK_LAPS` and three points per curve when ``quick``) and write the report of their points; returns the
    rows. ``reuse``: grid folders (the robustness
    grid's) whose finished cells answer a point here (the fault-free races, and the moderate wind, 3 m/s, and the
    one-tick delay on the same seeds) and are copied, not flown.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    points = curve_cells(estimators, levers, quick, curves)
    experiment = Experiment(tuple(p.cell for p in points), summarise=lambda results: summarise(results, points),
                            report=lambda rows, missing: markdown_report(rows, device_line(), missing),
                            plot=_figure, record=lambda rows: {"device": device_line(), "rows": rows,
                                                               "curves": {k: list(v) for k, v in CURVES.items()}},
                            record_file="curves.json")
    return skeleton.run(experiment, out, QUICK_LAPS if quick else LAPS, robust_lib.SEED, progress, reuse=reuse,
                        flies=run, executor=executor)
