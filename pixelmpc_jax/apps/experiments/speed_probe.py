"""The visibility probe: what does PixelMPC's visibility cost in lap time, over pixel-cost weights at one speed?

Flies nominal MPPI and PixelMPC (t_f = 1 s by default) for each pixel model and each c_pixel at one target
speed and reports time with visibility < 50 % (and the part of it no attitude could avoid: the target gate
too close to fit the field of view), time at 0 %, lap time and mean speed, mean ± 2 sigma, beside the
change against nominal MPPI. Writes ``results.json`` (resumable per cell), ``REPORT.md`` and
``tradeoff.png`` (time with low visibility against lap time, one point per cell) in its folder.

    pixelmpc experiment speed-probe --speed 8 --laps 4 --out DIR
    pixelmpc experiment speed-probe --speed 14 --c-pixel 9e6 3e7 1e8 3e8 --out DIR

At 14 m/s our nominal MPPI averages 10.5 m/s (21.8 s laps), faster than the paper's 31.8 s laps; 8 m/s
gives about the paper's lap time.
"""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.experiments.skeleton import Experiment
from pixelmpc_jax.apps.racing.grid import Cell
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig

KEYS = ("time_vis_below_50_s", "time_vis_below_50_unavoidable_s", "time_vis_zero_s", "lap_time_s", "mean_speed")
LABELS = ("vis < 50 % [s]", "of which unavoidable [s]", "vis = 0 % [s]", "lap time [s]", "mean speed [m/s]")


def cells_for(speed: float, models, c_pixels, t_f: float) -> list[Cell]:
    """Nominal MPPI, then PixelMPC for every (pixel model, c_pixel) at ``speed``."""
    return [Cell("mppi", RaceSpec("mppi", speed=speed))] + [
        Cell(f"pixelmpc_{model}_tf{t_f:g}_c{c:.0e}",
             RaceSpec("pixelmpc", config=ControllerConfig(t_f=t_f, c_pixel=c, pixel_model=model), speed=speed))
        for model in models for c in c_pixels]


def _mean(agg: dict, key: str):
    entry = agg.get(key) or {}
    return entry.get("mean")


def report(results: dict, cells: list[Cell], speed: float, dof_weights: str = "") -> str:
    """Markdown: one row per cell, with the change of vis < 50 % and lap time against nominal MPPI."""
    nominal = results.get("mppi", {}).get("aggregate", {})
    header = "| cell | laps done | " + " | ".join(LABELS) + " | vis < 50 % vs nominal | lap time vs nominal |"
    lines = [f"# Visibility against lap time at a {speed:g} m/s target", ""]
    if dof_weights:
        lines += [f"DOF cells: {dof_weights}.", ""]
    lines += [header, "|" + "---|" * (header.count("|") - 1)]
    for cell in cells:
        agg = results.get(cell.name, {}).get("aggregate")
        if not agg:
            continue
        figures = []
        for key in KEYS:
            entry = agg.get(key) or {}
            figures.append("-" if entry.get("mean") is None else f"{entry['mean']:.2f} ± {entry['two_sigma']:.2f}")
        changes = []
        for key in ("time_vis_below_50_s", "lap_time_s"):
            ours, base = _mean(agg, key), _mean(nominal, key)
            missing = cell.name == "mppi" or ours is None or not base
            if not missing and key == "time_vis_below_50_s" and agg["success_rate"] < 1.0:
                changes.append("n/a (laps lost)")  # a lap that ends early also ends its loss of visibility
                continue
            changes.append("-" if missing else f"{(ours / base - 1) * 100:+.0f} %")
        done = f"{round(agg['success_rate'] * agg['num_laps'])}/{agg['num_laps']}"
        lines.append(f"| {cell.name} | {done} | " + " | ".join(figures + changes) + " |")
    return "\n".join(lines) + "\n"


def plot(results: dict, cells: list[Cell], path: Path, speed: float) -> None:
    """Time with visibility < 50 % against lap time, one point (mean, 2 sigma bars) per cell."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for cell in cells:
        agg = results.get(cell.name, {}).get("aggregate")
        if not agg or _mean(agg, "lap_time_s") is None:
            continue
        lap, vis = agg["lap_time_s"], agg["time_vis_below_50_s"]
        projection = cell.spec.config.pixel_model == "projection"
        marker = "s" if cell.spec.controller == "mppi" else ("o" if projection else "^")
        done = round(agg["success_rate"] * agg["num_laps"])
        label = cell.name if done == agg["num_laps"] else f"{cell.name} ({done}/{agg['num_laps']} laps; faded)"
        # lost laps end early, and so does their low visibility: such a cell is drawn faded
        ax.errorbar(lap["mean"], vis["mean"], xerr=lap["two_sigma"], yerr=vis["two_sigma"], fmt=marker, capsize=3,
                    label=label, alpha=1.0 if done == agg["num_laps"] else 0.35)
        unavoidable = _mean(agg, "time_vis_below_50_unavoidable_s")
        if unavoidable is not None:
            ax.plot(lap["mean"], unavoidable, marker, mfc="none", color="grey")
    nominal = results.get("mppi", {}).get("aggregate")
    if nominal and _mean(nominal, "time_vis_below_50_s") is not None:
        lap0, vis0 = nominal["lap_time_s"]["mean"], nominal["time_vis_below_50_s"]["mean"]
        ax.axhline(vis0 / 3, color="k", ls=":", lw=1, label="nominal / 3")
        ax.axvline(lap0 * 1.1, color="k", ls="--", lw=1, label="nominal lap + 10 %")
    ax.set_xlabel("lap time [s]")
    ax.set_ylabel("time with visibility < 50 % [s] (hollow: unavoidable part)")
    ax.set_title(f"target {speed:g} m/s")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def tradeoff_figure(results: dict, cells: list[Cell], out: Path, speed: float) -> str:
    """Draw ``tradeoff.png`` (:func:`plot`); the report does not link it."""
    plot(results, cells, Path(out) / "tradeoff.png", speed)
    return ""


def speed_probe(out: Path, speed: float = 8.0, laps: int = 4, models=("projection", "dof"), c_pixels=(9e6,),
                t_f: float = 1.0, dof_weights: Path | None = None, progress: bool = True,
                executor=None) -> dict:
    """Fly the probe's cells (:func:`cells_for`) from seed 0 into ``out``, the DOF cells with the weights file
    ``dof_weights`` (None: the packaged weights), and write ``REPORT.md`` and ``tradeoff.png``
    (:func:`~pixelmpc_jax.apps.experiments.skeleton.run`); returns ``{cell name: race results}`` of the cells.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    cells = cells_for(speed, models, c_pixels, t_f)
    dof_params, weights_note = None, ""
    if dof_weights is not None:
        from pixelmpc_jax.dynamics import dof

        dof_params, record = dof.load_checkpoint(dof_weights)
        loss = record.get("train_config", {}).get("loss", "polar")
        weights_note = f"weights `{Path(dof_weights).name}`, trained with the {loss} loss"
    experiment = Experiment(tuple(cells), summarise=lambda results: results,
                            report=lambda results, missing: report(results, cells, speed, weights_note),
                            plot=lambda results, folder: tradeoff_figure(results, cells, folder, speed))
    return skeleton.run(experiment, out, laps, 0, progress, dof_params, executor=executor)
