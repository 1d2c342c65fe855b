"""The main job: one race flown by PixelMPC and by nominal MPPI at the same target, seeds and MPPI settings, printed
side by side and drawn in one trajectory plot and one visibility strip chart.

Nominal MPPI flies the faster lap at the same target, so beside the table the job shows what nominal MPPI loses at
PixelMPC's lap time on the committed speed frontier (:mod:`~pixelmpc_jax.apps.racing.nominal_frontier`), where the
race is one the frontier speaks for.

The two controllers fly alternately, a batch of laps each, and after every batch ``metrics.json`` (the preset,
every setting the race resolved to, each controller's laps and ``nominal_frontier``, :func:`frontier_entry`) and
``ticks_<controller>.npz`` (the per-tick record, :mod:`~pixelmpc_jax.sim.ticks`) are rewritten: a stopped comparison
(Ctrl-C, or SIGTERM under the ``pixelmpc`` command) keeps matching laps of both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.racing import nominal_frontier, race
from pixelmpc_jax.apps.racing.presets import nominal_of
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.sim.metrics import LOSS_CAUSES, lap_tail, tail_columns
from pixelmpc_jax.strict_json import write_json_atomic
from pixelmpc_jax.timing import CONTROL_DT
from pixelmpc_jax.world.course import make_course

LABELS = {"pixelmpc": "PixelMPC", "mppi": "nominal MPPI"}
COLOURS = {"pixelmpc": "tab:green", "mppi": "tab:red"}


def controller_race(spec: RaceSpec, name: str) -> RaceSpec:
    """The race controller ``name`` flies in a comparison of ``spec``: nominal MPPI with the paper's sampling
    (:func:`~pixelmpc_jax.apps.racing.presets.nominal_of`), PixelMPC as the spec says."""
    return nominal_of(spec) if name == "mppi" else spec.replace(controller=name)


def run_compare(spec: RaceSpec, controllers=("pixelmpc", "mppi"), out: Path | None = None, preset: str | None = None,
                batch_size: int = 1, progress: bool = True, video: bool = False, dof_params=None) -> dict:
    """Fly ``spec`` with each of ``controllers`` (the same race otherwise; each controller's race recorded under its
    name, :func:`controller_race`), a batch of laps each in turn, and return ``{"preset", "race", "controllers":
    {name: results}, "interrupted", "nominal_frontier": frontier_entry(record), "flown": {name: run_laps'
    results}}``; with ``out``, write ``metrics.json`` and ``ticks_<controller>.npz`` after every batch, then
    ``trajectories.png`` and ``visibility.png``."""
    races = {}
    for name in controllers:
        flight = controller_race(spec, name)
        races[name] = race.prepare(flight, batch_size, dof_params if flight.uses_dof else None)
    books = {name: race.LapBook(prepared) for name, prepared in races.items()}
    record = {"preset": preset, "race": spec.record(), "controllers": {}, "interrupted": False}
    pending = {name: race.fly_batches(prepared) for name, prepared in races.items()}
    bar = _progress_bar(spec, len(controllers)) if progress else None

    def save() -> None:
        record["controllers"] = {name: book.results for name, book in books.items() if book.results["laps"]}
        record["nominal_frontier"] = frontier_entry(record)
        if out is not None:
            write_json_atomic(Path(out) / "metrics.json", record)
            for book in books.values():
                book.write_ticks(out)

    try:
        while pending:
            for name in list(pending):
                laps = next(pending[name], None)
                if laps is None:
                    del pending[name]
                    continue
                books[name].add(laps)
                if video and out is not None and name == "pixelmpc" and laps[0].record["seed"] == spec.seed:
                    from pixelmpc_jax.apps.racing.video import write_onboard_video

                    write_onboard_video(races[name].flight.base.track, laps[0].log, Path(out) / "onboard.mp4",
                                        races[name].camera)
                save()
                if bar is not None:
                    bar.update(len(laps))
                    bar.set_postfix({LABELS.get(n, n): f"{sum(lap['success'] for lap in b.results['laps'])}/"
                                                       f"{len(b.results['laps'])}" for n, b in books.items()})
    except KeyboardInterrupt:
        record["interrupted"] = True
        for book in books.values():
            book.results["interrupted"] = True
        save()
        print("\ninterrupted: keeping the finished laps ("
              + ", ".join(f"{LABELS.get(n, n)} {len(b.results['laps'])}" for n, b in books.items()) + ")")
    finally:
        if bar is not None:
            bar.close()
    flown = {name: book.flown() for name, book in books.items() if book.results["laps"]}
    if out is not None and flown:
        plot_controller_trajectories(spec, flown, Path(out) / "trajectories.png")
        plot_visibility(flown, Path(out) / "visibility.png", spec.speed)
    return {**record, "flown": flown}


def _progress_bar(spec: RaceSpec, controllers: int):
    from tqdm.auto import tqdm

    return tqdm(total=spec.laps * controllers, desc=f"race @ {spec.speed:g} m/s", unit="lap")


def _mean(results: dict, key: str) -> float | None:
    entry = results["aggregate"].get(key) or {}
    return entry.get("mean")


def frontier_entry(record: dict) -> dict:
    """What nominal MPPI loses at PixelMPC's lap time on the committed frontier, for a comparison's ``record``
    (:func:`~pixelmpc_jax.apps.racing.nominal_frontier.held_against` of its race and PixelMPC's laps)."""
    return nominal_frontier.held_against(record["race"], record["controllers"].get("pixelmpc"))


def side_by_side(record: dict) -> str:
    """A terminal table: one column per controller, rows of the laps finished and their tail, lap time, low
    visibility, its causes and the view; below it, nominal MPPI at PixelMPC's lap time on the committed frontier
    (:func:`frontier_entry`), or why that is not shown."""
    names = list(record["controllers"])
    results = [record["controllers"][n] for n in names]
    tails = [tail_columns(lap_tail(r["laps"])) for r in results]
    rows = [("laps completed", [t[0] for t in tails]),
            ("worst lap vs median", [t[1] for t in tails]),
            ("laps > 10 % over median", [t[2] for t in tails]),
            ("lap time [s]", [_fmt(_mean(r, "lap_time_s")) for r in results]),
            ("avoidable vis < 50 % [s]", [_fmt(_mean(r, "time_vis_avoidable_s")) for r in results]),
            ("vis < 50 %, nothing excused [s]", [_fmt(_mean(r, "time_vis_below_50_s")) for r in results]),
            ("vis = 0 % [s]", [_fmt(_mean(r, "time_vis_zero_s")) for r in results])]
    rows += [(f"  cause: {cause} [s]", [_fmt(_mean(r, f"time_vis_below_50_{cause}_s")) for r in results])
             for cause in LOSS_CAUSES]
    rows += [("target in view [% of time]", [_fmt(_percent(_mean(r, "share_target_in_view"))) for r in results]),
             ("mean angle to target [deg]", [_fmt(_mean(r, "mean_target_angle_deg")) for r in results]),
             ("paper's rule: vis < 50 % after first seen [s]",
              [_fmt(_mean(r, "time_vis_below_50_after_seen_s")) for r in results])]
    width = max(len(label) for label, _ in rows)
    lines = [f"{'':{width}}  " + "  ".join(f"{LABELS.get(n, n):>14}" for n in names)]
    lines += [f"{label:{width}}  " + "  ".join(f"{value:>14}" for value in values) for label, values in rows]
    return "\n".join([*lines, "", nominal_frontier.describe(frontier_entry(record))])


def _percent(share: float | None) -> float | None:
    return None if share is None else 100.0 * share


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_controller_trajectories(spec: RaceSpec, flown: dict, path: Path) -> None:
    """Top-down view: every lap of each controller in its colour, the gates as their frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    track = make_course(spec.course)
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


def plot_visibility(flown: dict, path: Path, target_speed: float) -> None:
    """A strip per controller: the target gate's visibility over the first lap, the ticks below 50 % shaded (grey
    where avoidable, blue where the floor excuses them), and a line where each gate becomes the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(flown), 1, figsize=(10, 1.8 * len(flown) + 0.6), sharex=True, squeeze=False)
    for ax, (name, results) in zip(axes[:, 0], flown.items()):
        if not results["ticks"]:
            continue
        lap_ticks = results["ticks"][0]
        masks = ticks_lib.lap_masks(lap_ticks, target_speed)
        visibility = np.asarray(lap_ticks["visibility"])
        time = np.arange(len(visibility)) * CONTROL_DT
        ax.fill_between(time, 0.0, 1.0, where=masks["avoidable"], color="0.8", step="mid", label="avoidable < 50 %")
        ax.fill_between(time, 0.0, 1.0, where=masks["excused"], color="lightblue", step="mid", label="excused")
        for switch in np.flatnonzero(np.diff(lap_ticks["target"])) + 1:
            ax.axvline(switch * CONTROL_DT, color="0.3", lw=0.5, ls=":")
        ax.plot(time, visibility, color=COLOURS.get(name), lw=1.0)
        ax.axhline(0.5, color="0.4", lw=0.6, ls="--")
        lap = results["laps"][0]
        in_view = 100 * (lap["share_target_in_view"] or 0.0)
        ax.set(ylim=(-0.02, 1.02), ylabel="visibility",
               title=f"{LABELS.get(name, name)}: {lap['time_vis_avoidable_s']:.1f} s avoidable below 50 %, target in "
                     f"view {in_view:.0f} % (seed {lap['seed']}; dotted: a new target)")
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
