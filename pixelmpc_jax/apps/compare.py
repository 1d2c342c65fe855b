"""The main job: one race flown by PixelMPC and by nominal MPPI at the same target, seeds and MPPI settings, printed
side by side and drawn in one trajectory plot and one visibility strip chart.

``metrics.json`` names the preset and every setting the race resolved to, and holds each controller's laps; it is
rewritten after each controller, so an interrupted run keeps what finished.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps import race
from pixelmpc_jax.apps.presets import nominal_of
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.sim.metrics import LOSS_CAUSES
from pixelmpc_jax.strict_json import write_json_atomic
from pixelmpc_jax.timing import CONTROL_DT

LABELS = {"pixelmpc": "PixelMPC", "mppi": "nominal MPPI"}
COLOURS = {"pixelmpc": "tab:green", "mppi": "tab:red"}


def run_compare(spec: RaceSpec, controllers=("pixelmpc", "mppi"), out: Path | None = None, preset: str | None = None,
                batch_size: int = 1, progress: bool = True, video: bool = False, dof_params=None) -> dict:
    """Fly ``spec`` with each of ``controllers`` (the same race otherwise; nominal MPPI with the paper's sampling,
    :func:`~pixelmpc_jax.apps.presets.nominal_of`, each controller's race recorded under its name) and return
    ``{"preset", "race", "controllers": {name: run_laps' results}, "interrupted"}``; with ``out``, write
    ``metrics.json`` after each controller, then ``trajectories.png`` and ``visibility.png``."""
    record = {"preset": preset, "race": spec.record(), "controllers": {}, "interrupted": False}
    flown = {}
    for name in controllers:
        flight = nominal_of(spec) if name == "mppi" else spec.replace(controller=name)
        results = race.run_laps(flight, batch_size=batch_size, progress=progress, video=video and name == "pixelmpc",
                                out=None, dof_params=dof_params if flight.uses_dof else None)
        flown[name] = results
        record["controllers"][name] = {k: v for k, v in results.items()
                                       if k not in ("trajectories", "covariances", "visibility")}
        record["controllers"][name]["race"] = flight.record()
        record["interrupted"] = bool(results["interrupted"])
        if out is not None:
            write_json_atomic(Path(out) / "metrics.json", record)
        if record["interrupted"]:
            break
    if out is not None and any(results["trajectories"] for results in flown.values()):
        plot_trajectories(spec, flown, Path(out) / "trajectories.png")
        plot_visibility(flown, Path(out) / "visibility.png")
    return {**record, "flown": flown}


def _mean(results: dict, key: str) -> float | None:
    entry = results["aggregate"].get(key) or {}
    return entry.get("mean")


def _avoidable(results: dict) -> float | None:
    below, floor = _mean(results, "time_vis_below_50_s"), _mean(results, "time_vis_below_50_unavoidable_s")
    return None if below is None or floor is None else below - floor


def side_by_side(record: dict) -> str:
    """A terminal table: one column per controller, rows of lap time, low visibility, its causes and the view."""
    names = list(record["controllers"])
    results = [record["controllers"][n] for n in names]
    rows = [("laps completed", [f"{sum(lap['success'] for lap in r['laps'])}/{len(r['laps'])}" for r in results]),
            ("lap time [s]", [_fmt(_mean(r, "lap_time_s")) for r in results]),
            ("vis < 50 % [s]", [_fmt(_mean(r, "time_vis_below_50_s")) for r in results]),
            ("  of which avoidable [s]", [_fmt(_avoidable(r)) for r in results]),
            ("vis = 0 % [s]", [_fmt(_mean(r, "time_vis_zero_s")) for r in results])]
    rows += [(f"  cause: {cause} [s]", [_fmt(_mean(r, f"time_vis_below_50_{cause}_s")) for r in results])
             for cause in LOSS_CAUSES]
    rows += [("target in view [% of time]", [_fmt(_percent(_mean(r, "share_target_in_view"))) for r in results]),
             ("mean angle to target [deg]", [_fmt(_mean(r, "mean_target_angle_deg")) for r in results])]
    width = max(len(label) for label, _ in rows)
    lines = [f"{'':{width}}  " + "  ".join(f"{LABELS.get(n, n):>14}" for n in names)]
    lines += [f"{label:{width}}  " + "  ".join(f"{value:>14}" for value in values) for label, values in rows]
    return "\n".join(lines)


def _percent(share: float | None) -> float | None:
    return None if share is None else 100.0 * share


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_trajectories(spec: RaceSpec, flown: dict, path: Path) -> None:
    """Top-down view: every lap of each controller in its colour, the gates as their frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    track = race.make_course(spec.course)
    fig, ax = plt.subplots(figsize=(7, 9))
    for name, results in flown.items():
        for i, states in enumerate(results["trajectories"]):
            ax.plot(states[:, 0], states[:, 1], color=COLOURS.get(name), lw=1.2, alpha=0.8,
                    label=LABELS.get(name, name) if i == 0 else None)
    race.draw_course(ax, track)
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set(xlabel="x [m]", ylabel="y [m]", title=f"target {spec.speed:g} m/s, seeds from {spec.seed}")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_visibility(flown: dict, path: Path) -> None:
    """A strip per controller: the target gate's visibility over the first lap, the ticks below 50 % shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(flown), 1, figsize=(10, 1.8 * len(flown) + 0.6), sharex=True, squeeze=False)
    for ax, (name, results) in zip(axes[:, 0], flown.items()):
        if not results["visibility"]:
            continue
        visibility = np.asarray(results["visibility"][0])
        time = np.arange(len(visibility)) * CONTROL_DT
        ax.fill_between(time, 0.0, 1.0, where=visibility < 0.5, color="0.85", step="mid", label="below 50 %")
        ax.plot(time, visibility, color=COLOURS.get(name), lw=1.0)
        ax.axhline(0.5, color="0.4", lw=0.6, ls="--")
        lap = results["laps"][0]
        ax.set(ylim=(-0.02, 1.02), ylabel="visibility",
               title=f"{LABELS.get(name, name)}: {lap['time_vis_below_50_s']:.1f} s below 50 % (seed {lap['seed']})")
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
