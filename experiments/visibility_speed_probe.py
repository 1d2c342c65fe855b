"""Probe: what does PixelMPC's visibility cost in lap time, over target speeds and pixel-cost weights?

Flies nominal MPPI and PixelMPC (t_f = 1 s by default) for each pixel model and each c_pixel at one target
speed and reports time with visibility < 50 % (and the part of it no attitude could avoid: the target gate
too close to fit the field of view), time at 0 %, lap time and mean speed, mean ± 2 sigma, beside the
change against nominal MPPI. Writes ``results.json`` (resumable per cell), ``REPORT.md`` and
``tradeoff.png`` (time with low visibility against lap time, one point per cell) in DIR.

    python experiments/visibility_speed_probe.py --speed 8 --laps 4 --out DIR
    python experiments/visibility_speed_probe.py --speed 14 --c-pixel 9e6 3e7 1e8 3e8 --out DIR

At 14 m/s our nominal MPPI averages 10.5 m/s (21.8 s laps), faster than the paper's 31.8 s laps; 8 m/s
gives about the paper's lap time.
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.grid import Cell, run_grid
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import PixelMPCConfig

KEYS = ("time_vis_below_50_s", "time_vis_below_50_unavoidable_s", "time_vis_zero_s", "lap_time_s", "mean_speed")
LABELS = ("vis < 50 % [s]", "of which unavoidable [s]", "vis = 0 % [s]", "lap time [s]", "mean speed [m/s]")


def cells_for(speed: float, models, c_pixels, t_f: float) -> list[Cell]:
    """Nominal MPPI, then PixelMPC for every (pixel model, c_pixel) at ``speed``."""
    return [Cell("mppi", RaceSpec("mppi", speed=speed))] + [
        Cell(f"pixelmpc_{model}_tf{t_f:g}_c{c:.0e}",
             RaceSpec("pixelmpc", config=PixelMPCConfig(t_f=t_f, c_pixel=c, pixel_model=model), speed=speed))
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
        marker = "s" if cell.spec.controller == "mppi" else ("o" if cell.spec.pixel_model == "projection" else "^")
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speed", type=float, default=8.0, help="target speed, m/s (default 8)")
    parser.add_argument("--laps", type=int, default=4, help="laps per cell (default 4)")
    parser.add_argument("--models", nargs="+", default=["projection", "dof"], choices=["projection", "dof"])
    parser.add_argument("--c-pixel", type=float, nargs="+", default=[9e6], help="pixel cost weights (default 9e6)")
    parser.add_argument("--t-f", type=float, default=1.0, help="seconds of the horizon with the pixel cost")
    parser.add_argument("--dof-weights", type=Path, default=None,
                        help="DOF weights file for the dof cells (default: the shipped weights)")
    parser.add_argument("--out", type=Path, default=Path("runs/visibility_probe"))
    args = parser.parse_args(argv)
    if args.laps <= 0 or args.speed <= 0 or args.t_f <= 0 or min(args.c_pixel) <= 0:
        parser.error("--laps, --speed, --t-f and --c-pixel must be positive")
    cells = cells_for(args.speed, args.models, args.c_pixel, args.t_f)
    dof_params, weights_note = None, ""
    if args.dof_weights is not None:
        from pixelmpc_jax.dynamics import dof

        dof_params, record = dof.load_checkpoint(args.dof_weights)
        loss = record.get("train_config", {}).get("loss", "polar")
        weights_note = f"weights `{args.dof_weights.name}`, trained with the {loss} loss"
    results = run_grid(cells, args.out, laps=args.laps, dof_params=dof_params)
    text = report(results, cells, args.speed, weights_note)
    (args.out / "REPORT.md").write_text(text)
    plot(results, cells, args.out / "tradeoff.png", args.speed)
    print(text)
    return results


if __name__ == "__main__":
    main()
