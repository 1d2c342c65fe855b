"""The picture a reader looks at first: lap time against avoidable low-visibility time, one dot per lap, both
controllers, every pace; beside it, the share of time with the target in view.

It reads result folders as they are written: a grid's (a frontier's, ``results.json``: a race per cell) or a
comparison's (``pixelmpc race --out``, ``metrics.json``: a race per controller). Every race recorded under this
version's visibility measure is drawn; others are left out (their avoidable time means something else). The colour of
a dot is its race's target speed, one scale for both controllers; nominal MPPI's dots are small circles, each
PixelMPC race has a marker of its own. A lap that did not finish has no lap time and no dot: the legend counts it.

``pixelmpc experiment lap-picture DIR [DIR ...]`` writes it (``laps.png`` in the first folder by default); the
frontier experiment draws it into its folder beside ``frontier.png``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pixelmpc_jax.sim.metrics import MEASURE

NOMINAL = "mppi"
PIXEL_MARKERS = ("^", "D", "s", "P", "X", "v", "*", "<", ">", "h")


class RaceLaps(NamedTuple):
    """One race's laps as a result folder holds them: its name there (a cell's or a controller's), its controller
    (``mppi`` or ``pixelmpc``), its target speed in m/s and its laps' metrics."""

    label: str
    controller: str
    speed: float
    laps: list


def _race(label: str, race: dict, results: dict) -> RaceLaps:
    return RaceLaps(label, race["controller"], float(race["speed"]), list(results.get("laps", [])))


def folder_races(folder: Path, names=None) -> list[RaceLaps]:
    """The races recorded in ``folder`` under this version's measure (:data:`~pixelmpc_jax.sim.metrics.MEASURE`):
    a grid's ``results.json`` (only the cells in ``names`` when given) or a comparison's ``metrics.json`` (a
    ``pixelmpc race --out`` folder, one controller or both). A ValueError when it holds neither."""
    folder = Path(folder)
    if (folder / "results.json").is_file():
        recorded = json.loads((folder / "results.json").read_text())
        return [_race(name, done["config"], done) for name, done in recorded.items()
                if isinstance(done, dict) and done.get("measure") == MEASURE and (names is None or name in names)]
    if (folder / "metrics.json").is_file():
        record = json.loads((folder / "metrics.json").read_text())
        if "controllers" in record:
            return [_race(name, results["race"], results) for name, results in record["controllers"].items()
                    if results.get("measure") == MEASURE]
        return [_race(record["race"]["controller"], record["race"], record)] if record.get("measure") == MEASURE else []
    raise ValueError(f"{folder} holds no results.json (a grid's, a frontier's) or metrics.json (pixelmpc race --out)")


def finished_points(race: RaceLaps) -> np.ndarray:
    """(F, 3) lap time s, avoidable time s and share of time with the target in view (%) of the race's finished
    laps with both visibility figures."""
    rows = [(lap["lap_time_s"], lap["time_vis_avoidable_s"], 100.0 * lap["share_target_in_view"])
            for lap in race.laps if lap.get("success") and lap.get("lap_time_s") is not None
            and lap.get("time_vis_avoidable_s") is not None and lap.get("share_target_in_view") is not None]
    return np.asarray(rows, np.float64).reshape(-1, 3)


def plot_laps(races: list[RaceLaps], path: Path, title: str | None = None) -> None:
    """Draw the picture of ``races`` into ``path``: left, every finished lap's avoidable time against its lap time;
    right, its share of time with the target in view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    if not races:
        raise ValueError("no race to draw")
    speeds = [race.speed for race in races]
    low, high = min(speeds), max(speeds)
    norm = Normalize(low - 0.5, high + 0.5) if low == high else Normalize(low, high)
    cmap = plt.get_cmap("viridis")
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.8), sharex=True, layout="constrained")
    nominal = [race for race in races if race.controller == NOMINAL]
    pixel = [race for race in races if race.controller != NOMINAL]
    for i, race in enumerate(nominal):
        points = finished_points(race)
        style = dict(s=14, marker="o", color=cmap(norm(race.speed)), alpha=0.75, linewidths=0)
        for ax, column in ((left, 1), (right, 2)):
            ax.scatter(points[:, 0], points[:, column], **style,
                       label=_nominal_label(nominal) if (i == 0 and ax is left) else None)
    for i, race in enumerate(pixel):
        points = finished_points(race)
        style = dict(s=40, marker=PIXEL_MARKERS[i % len(PIXEL_MARKERS)], color=cmap(norm(race.speed)),
                     edgecolors="black", linewidths=0.7, zorder=3)
        for ax, column in ((left, 1), (right, 2)):
            ax.scatter(points[:, 0], points[:, column], **style,
                       label=f"{race.label} ({_finished(race)} laps)" if ax is left else None)
    left.set(xlabel="lap time [s]", ylabel="avoidable time with visibility < 50 % [s per lap]",
             title="one dot per finished lap")
    right.set(xlabel="lap time [s]", ylabel="target in view [% of flown time]", title="share of time in view")
    for ax in (left, right):
        ax.grid(alpha=0.3)
    fig.legend(fontsize=8, loc="outside lower center", ncol=min(3, len(pixel) + 1))
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=[left, right], pad=0.01)
    bar.set_label("target speed [m/s]")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _finished(race: RaceLaps) -> str:
    return f"{sum(bool(lap.get('success')) for lap in race.laps)}/{len(race.laps)}"


def _nominal_label(nominal: list[RaceLaps]) -> str:
    done = sum(sum(bool(lap.get("success")) for lap in race.laps) for race in nominal)
    total = sum(len(race.laps) for race in nominal)
    speeds = sorted(race.speed for race in nominal)
    return f"nominal MPPI, {len(nominal)} target speeds {speeds[0]:g}-{speeds[-1]:g} m/s ({done}/{total} laps)"


def _same_laps(race: RaceLaps) -> tuple:
    """What makes two folders' races one: the controller, the target and every lap's seed and figures (a race one
    folder copied from another with ``--reuse``)."""
    return race.controller, race.speed, json.dumps(race.laps, sort_keys=True)


def write_lap_picture(folders, out: Path | None = None, names=None) -> Path:
    """Draw the races of ``folders`` (:func:`folder_races`) into ``out`` (default ``laps.png`` in the first
    folder); returns the file. With several folders a PixelMPC race's label names its folder too, and a race a later
    folder holds again (copied with ``--reuse``) is drawn once."""
    folders = [Path(folder) for folder in folders]
    races, drawn = [], set()
    for folder in folders:
        for race in folder_races(folder, names):
            same = _same_laps(race)
            if same in drawn:
                continue
            drawn.add(same)
            label = race.label if len(folders) == 1 else f"{folder.name}/{race.label}"
            races.append(race._replace(label=label))
    out = Path(out) if out is not None else folders[0] / "laps.png"
    plot_laps(races, out, title=", ".join(folder.name for folder in folders))
    return out
