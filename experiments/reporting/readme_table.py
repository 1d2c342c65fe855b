"""The README's results table, rebuilt from the committed result folders (``pixelmpc report --readme``).

Which rows the table holds, in which order, each with its claim, its kind and its folder, is data: the ``readme`` list
of ``experiments/results/index.json`` (:mod:`experiments.reporting.index`). A row's kind names the function here
that reads its folder (:data:`KINDS`); its claim is a template the function fills from what the folder's races flew
(``{controller}``, ``{speed}``, ...).

One row per headline claim: what is claimed, our figure with its interval where the folder records one, its tail
(the worst lap, the slowest step), the paper's figure, the loop and the machine it was measured on, the folder and
whether the folder commits its per-tick record (``ticks_compact.npz``, :mod:`~pixelmpc_jax.sim.ticks_compact`; "n/a"
where the figure is not one of laps). A row reads its figures, its device and its date from its folder's files
only; the paper's figures are the paper's (:data:`PAPER`). Where a folder commits its per-tick record, every lap
of it must give the figures the folder's results record (:func:`check_compact_record`), and a frontier row's gain
is recomputed from it (:func:`frontier_row_from_compact`).

The table sits in ``README.md`` between :data:`BEGIN` and :data:`END`; :func:`rewrite_readme` replaces that block,
and ``tests/test_readme.py`` fails when it differs from :func:`table`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from experiments.reporting import index, splice
from pixelmpc_jax.apps.bench.table1 import PAPER as PAPER_TABLE_I
from pixelmpc_jax.apps.experiments import frontier
from pixelmpc_jax.apps.experiments import gains as gains_lib
from pixelmpc_jax.apps.experiments.estimation import PAPER_TABLE_IV
from pixelmpc_jax.apps.experiments.paper import LABEL_SPEED, PAPER_LAP_TIME, PAPER_VIS_BELOW_50
from pixelmpc_jax.apps.experiments.skeleton import failure_counts
from pixelmpc_jax.apps.racing import frontier_curve
from pixelmpc_jax.apps.racing.presets import LOOK_AHEAD_BEST, PAPER_PACE_SPEEDS, preset
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.learn.evaluate import PAPER_AEE_PX
from pixelmpc_jax.perception.eskf import SURVEYED_MAP_SIGMA_M
from pixelmpc_jax.sim import metrics, ticks_compact

BEGIN = "<!-- results:begin -->"
END = "<!-- results:end -->"
NOT_RECORDED = "-"

# The paper's figures held against ours, each from the table or section that reports it (the values live with the
# job that reproduces that table).
PAPER = {
    "aee_px": PAPER_AEE_PX,  # Section V-A: the DOF's AEE on its test set
    "nominal_lap_s": PAPER_LAP_TIME[(0.0, 0.0)],  # Table III: nominal MPPI's lap at 14 m/s (mean, 2 sigma)
    "pixelmpc_lap_s": PAPER_LAP_TIME[(1.0, 9e6)],  # Table III: PixelMPC's best cell (t_f 1 s, c_pixel 9e6)
    "nominal_vis_below_50_s": PAPER_VIS_BELOW_50[(0.0, 0.0)],  # Table II: nominal MPPI at 14 m/s
    "pixelmpc_vis_below_50_s": PAPER_VIS_BELOW_50[(1.0, 9e6)],  # Table II: its best cell
    "nominal_success_16": PAPER_TABLE_IV[("mppi", 16.0)][0],  # Table IV: particle filter, 16 m/s, 25 laps
    "pixelmpc_success_16": PAPER_TABLE_IV[("pixelmpc", 16.0)][0],
    "step_ms": PAPER_TABLE_I[("dof", 1, 512, 80)],  # Table I: DOF, 512 samples x 80 steps (mean, 2 sigma, max)
}
COLUMNS = ("claim", "ours [90 % interval]", "tail", "paper", "loop", "measured on", "folder", "per-tick record")


class Row(NamedTuple):
    """One claim of the table; ``folder`` is relative to the checkout's root."""

    claim: str
    ours: str
    tail: str
    paper: str
    loop: str
    measured_on: str
    folder: Path
    per_tick: str


def _json(path: Path):
    return json.loads(Path(path).read_text())


DEVICE_LINE = re.compile(r"^(?P<platform>\w+) \((?P<kind>[^,]+), \d+ device\(s\)\); CPU (?P<cpu>.+?), "
                         r"(?P<cores>\d+) cores; jax (?P<jax>[\d.]+)")
ISO_DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")


def device_name(device: dict | str) -> str:
    """The machine in a few words, from a :func:`~pixelmpc_jax.platform_info.device_description` record or its
    :func:`~pixelmpc_jax.platform_info.device_line`: the accelerator, or the CPU and its cores; and JAX's version."""
    if isinstance(device, str):
        match = DEVICE_LINE.match(device)
        if match is None:
            return device
        device = {"platform": match["platform"], "device_kind": match["kind"], "cpu_model": match["cpu"],
                  "cpu_count": match["cores"], "jax": match["jax"]}
    if device["platform"] != "cpu":
        return f"{device['device_kind']}, jax {device['jax']}"
    return f"{device['cpu_count']}-core {device['cpu_model']}, jax {device['jax']}"


def stated_device(path: Path) -> str:
    """The machine a report or README states on its ``Device:`` line (a device line or plain words)."""
    for line in Path(path).read_text().splitlines():
        if line.startswith("Device: "):
            text = line.removeprefix("Device: ")
            match = DEVICE_LINE.match(text)
            return device_name(match.group(0)) if match else text.split(". ")[0].rstrip(".")
    raise ValueError(f"{path} states no device (a line 'Device: ...')")


def stated_date(path: Path) -> str:
    """The first date (YYYY-MM-DD) a report or README states."""
    match = ISO_DATE.search(Path(path).read_text())
    if match is None:
        raise ValueError(f"{path} states no date")
    return match.group(0)


def compact_records(folder: Path) -> list[Path]:
    """The compact per-tick records a result folder commits: its own, or else one in each of its course folders
    (``course_<seed>``, a folder of several courses' frontiers); none when one of those lacks it."""
    own = folder / ticks_compact.FILE_NAME
    if own.is_file():
        return [own]
    courses = sorted(p for p in folder.glob("course_*") if p.is_dir())
    records = [course / ticks_compact.FILE_NAME for course in courses]
    return records if records and all(record.is_file() for record in records) else []


def per_tick(folder: Path) -> str:
    """"yes" when the folder commits its compact per-tick record (:func:`compact_records`), else "no"."""
    return "yes" if compact_records(folder) else "no"


def _seeds(first: int, laps: int) -> str:
    return f"seeds {first}-{first + laps - 1}"


DETECTOR_WORDS = {"clipped": "detector clipped at the image border", "ideal": "ideal detector (the earlier loop)",
                  "image": "image detector"}


def _loop(estimator: str, config: dict | None = None) -> str:
    """The loop a race flew, in words: the estimator and, from its recorded ``config``, the detector, on a filter
    where the gate switch came from, and on the ESKF the map's accuracy it was told when that was not its default."""
    words = [{"truth": "true state", "pf": "particle filter", "eskf": "ESKF"}.get(estimator, estimator)]
    if config is not None and estimator == "eskf":
        sigma = config["eskf"]["map_sigma_m"]
        if sigma != SURVEYED_MAP_SIGMA_M:
            words[0] = "ESKF taking the map as exact" if sigma == 0 else f"ESKF told the map to {sigma:g} m"
    if config is not None:
        words.append(DETECTOR_WORDS[config["detector"]])
        if estimator != "truth":
            words.append("gate switch from the estimate" if config["gate_switch"] == "estimate"
                         else "the truth's gate switch")
    return ", ".join(words)


def _share(count: int, total: int) -> str:
    return f"{count}/{total}"


def wilson_interval(successes: int, trials: int, level: float = 0.90) -> tuple[float, float]:
    """The Wilson score interval of a success rate (two-sided, ``level`` 0.90: z = 1.645)."""
    z = {0.90: 1.6448536269514722, 0.95: 1.959963984540054}[level]
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return max(0.0, centre - half), min(1.0, centre + half)


# the lap figures a compact per-tick record must give back as its folder's results record them
CHECKED_FIGURES = ("success", "lap_time_s", "time_vis_below_50_s", "time_vis_avoidable_s", "share_target_in_view")


def check_compact_record(folder: Path, results: dict) -> None:
    """Every lap of the folder's compact per-tick record gives the figures its results record (``results``: ``{race
    name: {"laps": [...]}}``), or a ValueError names the first that does not."""
    races = ticks_compact.load(folder / ticks_compact.FILE_NAME)
    for name, race in races.items():
        if name not in results:
            raise ValueError(f"{folder}: the per-tick record holds {name!r}, its results do not")
        recorded = {lap["seed"]: lap for lap in results[name]["laps"]}
        for lap in ticks_compact.race_laps(race):
            want = recorded.get(lap["seed"])
            if want is None or any(not _same(lap[key], want.get(key)) for key in CHECKED_FIGURES):
                gives = {key: lap[key] for key in CHECKED_FIGURES}
                recorded_figures = {key: (want or {}).get(key) for key in CHECKED_FIGURES}
                raise ValueError(f"{folder}: race {name!r}, seed {lap['seed']}: the per-tick record gives {gives}, "
                                 f"the results {recorded_figures}")


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


def flown_preset(record: dict) -> str:
    """How a row names the PixelMPC a race flew, from the race's recorded settings: "`best`" when it flew the preset
    as it is, the preset with the exact projection as its pixel model (a tilted camera's race: the learned models are
    trained for the untilted one), or the preset before its two options against the tail
    (:data:`~pixelmpc_jax.apps.racing.presets.LOOK_AHEAD_BEST`). Any other race is a ValueError: a row names the
    controller its folder flew."""
    config = RaceSpec.from_record({k: v for k, v in record.items() if k != "name"}).config
    best = preset("best").config
    if config == best:
        return "`best`"
    if config == LOOK_AHEAD_BEST:
        return "`best` before its tail options"
    as_best = dataclasses.replace(config, pixel_model=best.pixel_model, box_size_limit=best.box_size_limit,
                                  look_ahead_model=best.look_ahead_model)
    if config.pixel_model == "projection" and as_best == best:  # the projection predicts the next gate as the target
        return "`best` with the exact projection"
    raise ValueError(f"the race {record.get('name', '')!r} flew neither the best preset (with its pixel model or the "
                     "exact projection) nor the preset before it")


def frontier_row_from_compact(folder: Path, cell: str) -> dict:
    """A frontier folder's row for ``cell`` (:func:`~pixelmpc_jax.apps.experiments.frontier.against_nominal`: its
    gain, the gain's interval, the figures at the same lap time) recomputed from the folder's compact per-tick
    record alone; the nominal points are its races named ``nominal_<speed>``, in order of speed (the order the
    frontier's bootstrap draws them in when its speeds were given ascending)."""
    races = ticks_compact.load(Path(folder) / ticks_compact.FILE_NAME)
    results = {name: {"laps": ticks_compact.race_laps(race)} for name, race in races.items()}
    speeds = sorted(float(race["target_speed"]) for name, race in races.items()
                    if name == frontier.nominal_cell(float(race["target_speed"])).name)
    names = [frontier.nominal_cell(speed).name for speed in speeds]
    nominal = [{"name": name, "speed": speed, **frontier_curve.summarise(results[name])}
               for speed, name in zip(speeds, names)]
    if cell not in results:
        raise ValueError(f"{folder}: the per-tick record holds no race {cell!r}")
    row = frontier.against_nominal(results[cell], nominal, [results[name] for name in names])
    row["gains"] = gains_lib.frontier_gains(gains_lib.completed_laps(results[cell]),
                                            [gains_lib.completed_laps(results[name]) for name in names])
    return row


def _frontier(root: Path, folder: Path, cell: str) -> tuple[dict, dict, dict]:
    """(the frontier's record, the cell's row, the nominal point at the cell's target) of a frontier folder; the row
    recomputed from the compact per-tick record where the folder commits one (and checked against the record's), and
    every nominal point checked to be nominal MPPI on the loop, course and camera the cell flew (a ValueError
    otherwise: the gain compares laps of one loop).
    Read once while the folder's files stay as they are (several rows read one folder; the gains' bootstrap over
    100 seeds takes seconds); the returned dicts are shared, not to be changed."""
    files = [Path(root) / folder / name for name in ("frontier.json", "results.json", ticks_compact.FILE_NAME)]
    stamp = tuple(path.stat().st_mtime_ns if path.exists() else None for path in files)
    return _read_frontier(Path(root), Path(folder), cell, stamp)


@functools.lru_cache(maxsize=16)
def _read_frontier(root: Path, folder: Path, cell: str, stamp: tuple) -> tuple[dict, dict, dict]:
    """:func:`_frontier` of the folder's files as they were at ``stamp`` (their modification times)."""
    from pixelmpc_jax.apps.racing import grid

    record, results = _json(root / folder / "frontier.json"), _json(root / folder / "results.json")
    row = next(r for r in record["cells"] if r["name"] == cell)
    for point in record["nominal"]:
        _check_nominal(folder, grid.recorded_race(results[cell]), point, results[point["name"]])
    if per_tick(root / folder) == "yes":
        check_compact_record(root / folder, results)
        recomputed = frontier_row_from_compact(root / folder, cell)
        for key in ("frontier_gain", "lap_time_s", "avoidable_s"):
            if not _same(recomputed[key], row[key]):
                raise ValueError(f"{folder}: {cell}'s {key} is {row[key]} in frontier.json, {recomputed[key]} from "
                                 f"its per-tick record")
        if "gains" in row and not _same(recomputed["gains"]["paired"]["gain"], row["gains"]["paired"]["gain"]):
            raise ValueError(f"{folder}: {cell}'s paired gain is {row['gains']['paired']['gain']} in frontier.json, "
                             f"{recomputed['gains']['paired']['gain']} from its per-tick record")
        row = {**row, **recomputed}
    at_target = next(p for p in record["nominal"] if p["speed"] == row["speed"])
    return record, row, at_target


def _measured(record: dict) -> str:
    measured = record["measured"]
    return f"{device_name(measured['device'])}, {measured['written'][:10]}"


def _frontier_loop(root: Path, folder: Path, record: dict, row: dict) -> str:
    results = _json(root / folder / "results.json")[row["name"]]
    course = results["config"]["course"]
    course = "AlphaPilot" if course == "alphapilot" else f"course {Path(course).stem}"
    seeds = record["measured"]["seeds"]
    return (f"{_loop(row['estimator'], results['config'])}, {course}, {record['measured']['laps']} laps, "
            f"seeds {seeds[0]}-{seeds[1]}")


def lap_tail(laps: list[dict]) -> str:
    """The tail of a race's laps (:func:`~pixelmpc_jax.sim.metrics.lap_tail`) in words: laps finished, the worst
    finished lap against the median, and how many finished more than 10 % over the median."""
    tail = metrics.lap_tail(laps)
    over = round(tail["share_over_median"] * tail["laps_finished"])
    return (f"{tail['laps_finished']}/{tail['laps']} laps finished, the worst {tail['worst_over_median']:+.1%} over "
            f"the median, {over} more than {metrics.TAIL_OVER_MEDIAN * 100:g} % over")


def gains_text(gains: dict, finished: int) -> str:
    """The three frontier gains of :func:`~pixelmpc_jax.apps.experiments.gains.frontier_gains` in words: the paired
    gain [its interval] with how many of the ``finished`` laps it paired, then the joined means and the local fit
    ("none" where nominal MPPI's points do not reach the cell's lap time)."""
    paired, joined, local = (gains[name] for name in ("paired", "joined_means", "local_fit"))
    low, high = paired["interval"]

    def gain(entry: dict) -> str:  # none where the construction does not reach the cell's lap time
        return "none" if entry["gain"] is None else f"{entry['gain']:.2f}"

    return (f"paired **{paired['gain']:.2f}** [{low:.2f}, {high:.2f}] ({gains['laps_paired']} of {finished} laps "
            f"paired); joined means {gain(joined)}, local fit {gain(local)}")


def paired_side_figures(root: Path, folder: Path, record: dict, cell: str,
                        *figures: str) -> list[gains_lib.PairedFigure]:
    """A frontier folder's cell and nominal MPPI at the same lap times, paired by seed as the gain is
    (:func:`~pixelmpc_jax.apps.experiments.gains.paired_figure`), one per lap figure named, from the folder's compact
    per-tick record where it commits one (its results.json otherwise); a ValueError where no lap pairs."""
    if per_tick(root / folder) == "yes":
        races = ticks_compact.load(root / folder / ticks_compact.FILE_NAME)
        results = {name: {"laps": ticks_compact.race_laps(race)} for name, race in races.items()}
    else:
        results = _json(root / folder / "results.json")
    nominal = [results[point["name"]] for point in record["nominal"]]
    paired = [gains_lib.paired_figure(results[cell], nominal, figure) for figure in figures]
    if any(figure is None for figure in paired):
        raise ValueError(f"{folder}: no lap of {cell} lies within its seed's nominal lap times")
    return paired


def _paired_text(paired: gains_lib.PairedFigure, unit: str) -> str:
    value = f"{paired.nominal:.1%}" if unit == "%" else f"{paired.nominal:.2f} {unit}"
    return f"nominal at the same lap time {value}, paired by seed"


def frontier_gain(root: Path, entry: dict) -> Row:
    """A row of `best`'s frontier gain in a frontier folder (``entry``: its ``folder``, ``claim`` and ``cell``): the
    paired gain [interval] at its lap time against nominal MPPI flown slower, beside the joined means and the local
    fit (the bars apply to the smallest of the three), and its share of time with the target in view beside
    nominal's at the same lap times; the tail of its laps and its worst lap's avoidable time beside nominal's mean at
    the same lap times (nominal's figures paired by seed as the gain is, :func:`paired_side_figures`; every nominal
    point nominal MPPI on the cell's loop, :func:`_frontier`). The claim names the controller as ``{controller}``,
    filled from what the folder's race flew (:func:`flown_preset`)."""
    path, cell = Path(entry["folder"]), entry["cell"]
    record, cell_row, at_target = _frontier(root, path, cell)
    results = _json(root / path / "results.json")[cell]
    laps = [lap for lap in results["laps"] if lap["success"]]
    worst = max(lap["time_vis_avoidable_s"] for lap in laps)
    lap_change = cell_row["lap_time_s"] / at_target["lap_time_s"] - 1
    in_view, avoidable = paired_side_figures(root, path, record, cell, "share_target_in_view", "time_vis_avoidable_s")
    return Row(entry["claim"].format(controller=flown_preset(results["config"])),
               f"{gains_text(cell_row['gains'], len(laps))}; at {lap_change:+.1%} lap time; in view "
               f"{in_view.cell:.1%} over the {in_view.laps_paired} paired laps ({_paired_text(in_view, '%')})",
               f"{lap_tail(results['laps'])}; worst lap {worst:.2f} s avoidable (a paired lap's mean "
               f"{avoidable.cell:.2f} s; {_paired_text(avoidable, 's')})",
               "not measured (one target speed)", _frontier_loop(root, path, record, cell_row), _measured(record),
               path, per_tick(root / path))


def _courses_tail(tails: list[dict]) -> str:
    """The tails of several courses' races (:func:`~pixelmpc_jax.sim.metrics.lap_tail` each) in words: laps finished
    in all, each course's worst lap against its own median, the laps more than 10 % over their course's median."""
    finished, flown = sum(t["laps_finished"] for t in tails), sum(t["laps"] for t in tails)
    over = sum(round(t["share_over_median"] * t["laps_finished"]) for t in tails)
    worst = ", ".join("-" if t["worst_over_median"] is None else f"{t['worst_over_median']:+.1%}" for t in tails)
    return (f"{finished}/{flown} laps finished; the worst {worst} over its course's median; {over} more than "
            f"{metrics.TAIL_OVER_MEDIAN * 100:g} % over")


def courses_gain(root: Path, entry: dict) -> Row:
    """A row of `best`'s paired gain on each generated course of the entry's folder: its frontier folders
    ``course_<seed>`` (each course flown from its own file beside them), the gains and the tail of every lap together;
    the machine is the folder README's ``Device:`` line (the laps were flown where the joining process did not run)."""
    path, cell = Path(entry["folder"]), entry["cell"]
    courses = sorted(p.name for p in (root / path).iterdir() if p.is_dir() and p.name.startswith("course_"))
    if not courses:
        raise ValueError(f"{path} holds no course folder (course_<seed>)")
    gains, tails, changes, loops, presets_flown = [], [], [], set(), set()
    for course in courses:
        record, cell_row, at_target = _frontier(root, path / course, cell)
        results = _json(root / path / course / "results.json")[cell]
        paired = cell_row["gains"]["paired"]
        gains.append(f"{course.removeprefix('course_')}: **{paired['gain']:.2f}** [{paired['interval'][0]:.2f}, "
                     f"{paired['interval'][1]:.2f}]")
        changes.append(f"{cell_row['lap_time_s'] / at_target['lap_time_s'] - 1:+.1%}")
        tails.append(metrics.lap_tail(results["laps"]))
        presets_flown.add(flown_preset(results["config"]))
        stem = Path(results["config"]["course"]).stem
        loops.add(_frontier_loop(root, path / course, record, cell_row).replace(
            f"course {stem}", f"{len(courses)} generated courses"))
    if len(loops) != 1 or len(presets_flown) != 1:
        raise ValueError(f"{path}: its courses were flown on different loops, seeds or presets: "
                         f"{sorted(loops | presets_flown)}")
    return Row(entry["claim"].format(controller=presets_flown.pop()),
               f"paired {'; '.join(gains)}; lap time {', '.join(changes)} against nominal MPPI at the same target",
               _courses_tail(tails), "not measured (AlphaPilot only)", loops.pop(),
               f"{stated_device(root / path / 'README.md')}, {stated_date(root / path / 'README.md')}", path,
               per_tick(root / path))


def visibility_at_same_lap_time(root: Path, entry: dict) -> Row:
    """Time below 50 % a lap, nominal MPPI at `best`'s lap times -> `best`, beside the paper's nominal -> best cell,
    from the entry's frontier folder and cell: each the mean over `best`'s laps that pair with their seed's nominal
    laps, nominal's read at the same lap time on the same seed (:func:`paired_side_figures`)."""
    path, cell = Path(entry["folder"]), entry["cell"]
    record, cell_row, _ = _frontier(root, path, cell)
    results = _json(root / path / "results.json")[cell]
    worst = max(lap["time_vis_below_50_s"] for lap in results["laps"] if lap["success"])
    (nominal, _), (best, _) = PAPER["nominal_vis_below_50_s"], PAPER["pixelmpc_vis_below_50_s"]
    (nominal_lap, _), (best_lap, _) = PAPER["nominal_lap_s"], PAPER["pixelmpc_lap_s"]
    (below,) = paired_side_figures(root, path, record, cell, "time_vis_below_50_s")
    return Row(entry["claim"].format(controller=flown_preset(results["config"])),
               f"{below.nominal:.2f} -> **{below.cell:.2f}** s (paired by seed, {below.laps_paired} of "
               f"{sum(lap['success'] for lap in results['laps'])} laps)",
               f"worst lap {worst:.2f} s", f"{nominal:g} -> {best:g} s (laps {nominal_lap:g} -> {best_lap:g} s)",
               _frontier_loop(root, path, record, cell_row), _measured(record), path, per_tick(root / path))


def dof_accuracy(root: Path, entry: dict) -> Row:
    """The DOF's AEE against Farneback on held-out frames."""
    path = Path(entry["folder"])
    data = _json(root / path / "dof_eval.json")
    return Row(entry["claim"], f"{data['aee_px']:.2f} px/frame",
               NOT_RECORDED, f"{PAPER['aee_px']:g} px/frame",
               f"{data['frames']:,} frames of {len(data['data']['test_laps'])} held-out laps of nominal MPPI",
               f"{stated_device(root / path / 'README.md')}, {data['created'][:10]}", path, "n/a")


def _tables(root: Path, path: Path) -> tuple[Path, dict, dict]:
    """(the folder, its rows by cell, its results) of a Tables II/III folder (`pixelmpc experiment table2 --main`),
    its compact per-tick record checked against its results where it commits one."""
    results = _json(root / path / "results.json")
    if per_tick(root / path) == "yes":
        check_compact_record(root / path, results)
    return path, {row["cell"]: row for row in _json(root / path / "summary.json")}, results


def _mean(row: dict, key: str) -> float:
    return row[key]["mean"]


def _tables_measured(root: Path, path: Path) -> str:
    return f"{stated_device(root / path / 'README.md')}, {stated_date(root / path / 'README.md')}"


def nominal_lap(root: Path, entry: dict) -> Row:
    """Nominal MPPI's lap at the paper's 14 m/s target (the Tables II/III folder's nominal cell)."""
    path, rows, results = _tables(root, Path(entry["folder"]))
    row = rows[frontier.nominal_cell(LABEL_SPEED).name]
    laps = results[row["cell"]]["laps"]
    done = [lap["lap_time_s"] for lap in laps if lap["success"]]
    lap_time = row["lap_time_s"]
    paper_mean, paper_sigma = PAPER["nominal_lap_s"]
    return Row(entry["claim"].format(speed=LABEL_SPEED),
               f"{lap_time['mean']:.1f} ± {lap_time['two_sigma']:.1f} s, {_share(len(done), len(laps))} laps",
               f"slowest lap {max(done):.1f} s", f"{paper_mean:.1f} ± {paper_sigma:.1f} s",
               f"{_loop('truth', results[row['cell']]['config'])}, AlphaPilot, {len(laps)} laps, "
               f"{_seeds(results[row['cell']]['seed'], len(laps))}",
               _tables_measured(root, path), path, per_tick(root / path))


def paper_main_cell(root: Path, entry: dict) -> Row:
    """The paper's own controller (the `paper` preset: its L1 cost, DOF and best cell) against nominal MPPI at the
    same target, at the 14 m/s label and at its pace: time a lap under 50 % in view under this measure, the paper's
    "after first seen" rule beside it."""
    path, rows, results = _tables(root, Path(entry["folder"]))
    parts, worst, laps = [], 0.0, None
    for speed in (LABEL_SPEED, PAPER_PACE_SPEEDS[LABEL_SPEED]):
        nominal = rows[frontier.nominal_cell(speed).name]
        paper = next(r for r in rows.values() if r["preset"] == "paper" and r["speed"] == speed)
        parts.append(f"{speed:g} m/s: {_mean(nominal, 'time_vis_below_50_s'):.1f} -> "
                     f"**{_mean(paper, 'time_vis_below_50_s'):.1f}** s (the paper's rule "
                     f"{_mean(nominal, 'time_vis_below_50_after_seen_s'):.1f} -> "
                     f"{_mean(paper, 'time_vis_below_50_after_seen_s'):.1f} s), "
                     f"{_share(round(paper['success_rate'] * paper['num_laps']), paper['num_laps'])} laps")
        worst = max([worst, *(lap["time_vis_below_50_s"] for lap in results[paper["cell"]]["laps"])])
        laps, seed = paper["num_laps"], results[paper["cell"]]["seed"]
    (paper_nominal, _), (paper_best, _) = PAPER["nominal_vis_below_50_s"], PAPER["pixelmpc_vis_below_50_s"]
    return Row(entry["claim"], "; ".join(parts), f"worst lap {worst:.1f} s",
               f"{paper_nominal:g} -> {paper_best:g} s (14 m/s)",
               f"{_loop('truth', results[paper['cell']]['config'])}, AlphaPilot, {laps} laps a cell, "
               f"{_seeds(seed, laps)}",
               _tables_measured(root, path), path, per_tick(root / path))


def _table_iv(root: Path, path: Path) -> tuple[Path, Callable[[str], tuple[dict, dict]], dict]:
    """Table IV's 16 m/s pace in the folder ``path``: the folder, nominal MPPI's and `best`'s rows of its summary on an
    estimator, and its results, every lap checked against the per-tick record (:func:`check_compact_record`)."""
    cells = {c["cell"]: c for c in _json(root / path / "summary.json")["table_iv"]}
    results = _json(root / path / "results.json")
    check_compact_record(root / path, results)
    return path, lambda estimator: (cells[f"mppi_9.1ms_{estimator}"], cells[f"best_9.1ms_{estimator}"]), results


def _successes(cell: dict) -> int:
    return round(cell["success_rate"] * cell["num_laps"])


def table_iv_filter(root: Path, entry: dict) -> Row:
    """Table IV: laps finished on the particle filter at the paper's 16 m/s pace, nominal MPPI -> `best`."""
    path, rows, results = _table_iv(root, Path(entry["folder"]))
    nominal, best = rows("pf")
    intervals = [wilson_interval(_successes(c), c["num_laps"]) for c in (nominal, best)]
    failures = ", ".join(f"{cause.replace('_', ' ')} {count}" for cause, count in sorted(nominal["failures"].items()))
    seed = results[best["cell"]]["seed"]
    return Row(entry["claim"].format(label=best["label"], controller=flown_preset(results[best["cell"]]["config"])),
               f"{_share(_successes(nominal), nominal['num_laps'])} -> "
               f"**{_share(_successes(best), best['num_laps'])}** "
               f"[{intervals[0][0]:.0%}, {intervals[0][1]:.0%}] -> [{intervals[1][0]:.0%}, {intervals[1][1]:.0%}]",
               f"nominal's failures: {failures or 'none'}",
               f"{PAPER['nominal_success_16']:.0%} -> {PAPER['pixelmpc_success_16']:.0%}",
               f"{_loop('pf', results[best['cell']]['config'])}, AlphaPilot, {best['speed']:g} m/s, "
               f"{best['num_laps']} laps a cell, "
               f"{_seeds(seed, best['num_laps'])}",
               _tables_measured(root, path), path, per_tick(root / path))


def table_iv_eskf(root: Path, entry: dict) -> Row:
    """The same cells on the error-state Kalman filter: laps finished and the RMS position error."""
    path, rows, results = _table_iv(root, Path(entry["folder"]))
    (nominal, best), (nominal_pf, best_pf) = rows("eskf"), rows("pf")
    worst = max(lap["rms_position_error_m"] for lap in results[best["cell"]]["laps"])
    seed = results[best["cell"]]["seed"]
    flown = flown_preset(results[best["cell"]]["config"])
    return Row(entry["claim"].format(controller=flown),
               f"{_share(_successes(nominal), nominal['num_laps'])} -> {_share(_successes(best), best['num_laps'])}; "
               f"{nominal['rms_position_error_m']:.3f} -> **{best['rms_position_error_m']:.3f}** m (particle filter "
               f"{nominal_pf['rms_position_error_m']:.3f} -> {best_pf['rms_position_error_m']:.3f} m)",
               f"its worst lap {worst:.3f} m", "not measured (particle filter only)",
               f"{_loop('eskf', results[best['cell']]['config'])}, AlphaPilot, {best['speed']:g} m/s, "
               f"{best['num_laps']} laps a cell, "
               f"{_seeds(seed, best['num_laps'])}",
               _tables_measured(root, path), path, per_tick(root / path))


def _nominal_frontier(root: Path, race: RaceSpec, folders: tuple[Path, ...],
                      others: dict[Path, dict] | None = None) -> list[tuple[float, dict]]:
    """Nominal MPPI's points of the frontier folders ``folders`` as ``(speed, results)``, slowest first, each checked
    against its folder's per-tick record (which holds the races of ``others[folder]`` too, ``{race: {"laps": [...]}}``)
    and to be nominal MPPI as every frontier flies it (the paper's settings) on the loop ``race`` flew (a ValueError
    otherwise); a point named in an earlier folder is read from that one."""
    points: dict[str, tuple[float, dict]] = {}
    for folder in folders:
        record, results = _json(root / folder / "frontier.json"), _json(root / folder / "results.json")
        check_compact_record(root / folder, {**results, **(others or {}).get(folder, {})})
        for point in record["nominal"]:
            _check_nominal(folder, race, point, results[point["name"]])
            points.setdefault(point["name"], (point["speed"], results[point["name"]]))
    return sorted(points.values(), key=lambda point: point[0])


def _check_nominal(folder: Path, race: RaceSpec, point: dict, result: dict) -> None:
    """A ValueError unless the frontier point ``point`` of ``folder`` (its results ``result``) is nominal MPPI as
    every frontier flies it (the paper's settings) on the loop, course and camera ``race`` flew."""
    from pixelmpc_jax.apps.racing import grid
    from pixelmpc_jax.control.pixelmpc import ControllerConfig

    baseline = race.replace(controller="mppi", config=ControllerConfig(), speed=point["speed"],
                            laps=len(result["laps"]), seed=result["seed"])
    if grid.recorded_race(result).key() != baseline.key():
        raise ValueError(f"{folder}: {point['name']} is not nominal MPPI on the loop {flown_preset(race.record())} "
                         "flew")


def _gains(cell: gains_lib.Laps, nominal: list[gains_lib.Laps]) -> dict:
    """:func:`~pixelmpc_jax.apps.experiments.gains.frontier_gains` of these laps, computed once for the same laps
    (its bootstrap takes about a second, and the table, its check and its tests ask again); the dict is shared, not
    to be changed."""
    def key(laps: gains_lib.Laps) -> tuple:
        return tuple(tuple(field.tolist()) for field in laps)

    return _cached_gains(key(cell), tuple(key(laps) for laps in nominal))


@functools.lru_cache(maxsize=16)
def _cached_gains(cell: tuple, nominal: tuple) -> dict:
    return gains_lib.frontier_gains(gains_lib.laps(*cell), [gains_lib.laps(*laps) for laps in nominal])


def _of_seeds(laps: gains_lib.Laps, seeds: set[int]) -> gains_lib.Laps:
    keep = np.isin(laps.seed, sorted(seeds))
    return gains_lib.Laps(*(field[keep] for field in laps))


class _RaceAgainstFrontier(NamedTuple):
    race: RaceSpec
    laps: list[dict]  # every lap of the race
    done: list[dict]  # its finished laps
    at_target: list[dict]  # nominal MPPI's finished laps at the race's target, of the race's seeds
    gains: dict  # :func:`~pixelmpc_jax.apps.experiments.gains.frontier_gains` against nominal's laps of its seeds


def _race_against_frontier(root: Path, path: Path, folders: tuple[Path, ...]) -> _RaceAgainstFrontier:
    """A `pixelmpc race` of PixelMPC in ``path``'s ``best/`` against nominal MPPI's points of the frontier folders
    ``folders`` (:func:`_nominal_frontier`, on the race's loop), their laps of other seeds left out; a ValueError when
    none was flown at the race's target. Every lap is checked against the folders' per-tick records, the race's against
    ``path``'s (as ``best``)."""
    metrics_ = _json(root / path / "best" / "metrics.json")["controllers"]["pixelmpc"]
    laps = metrics_["laps"]
    race = RaceSpec.from_record(metrics_["race"])
    seeds = {lap["seed"] for lap in laps}
    nominal = _nominal_frontier(root, race, folders, others={path: {"best": {"laps": laps}}})
    at_target = [result for speed, result in nominal if math.isclose(speed, race.speed)]
    if not at_target:
        raise ValueError(f"{path}: no nominal MPPI point at {race.speed:g} m/s")
    gains = _gains(gains_lib.completed_laps({"laps": laps}),
                   [_of_seeds(gains_lib.completed_laps(result), seeds) for _, result in nominal])
    return _RaceAgainstFrontier(race, laps, [lap for lap in laps if lap["success"]],
                                [lap for lap in at_target[0]["laps"] if lap["success"] and lap["seed"] in seeds], gains)


def _median_lap(laps: list[dict]) -> float:
    return statistics.median(lap["lap_time_s"] for lap in laps)


def _in_view(laps: list[dict]) -> float:
    return statistics.mean(lap["share_target_in_view"] for lap in laps)


def pace_paired_gain(root: Path, entry: dict) -> Row:
    """`best` at the 16 m/s label's pace on the true state (a `pixelmpc race` in the entry folder's ``best/``)
    against nominal MPPI flown slower on the same seeds (the points of its ``frontiers`` folders, their laps of other
    seeds left out): the paired gain, the joined means and the local fit with their intervals, and the median lap
    against nominal MPPI's at the same target on the same seeds; every lap checked against the folders' per-tick
    records."""
    path, frontiers = Path(entry["folder"]), tuple(Path(folder) for folder in entry["frontiers"])
    flown = _race_against_frontier(root, path, frontiers)
    race = flown.race
    median_change = _median_lap(flown.done) / _median_lap(flown.at_target) - 1
    label = next(label for label, pace in PAPER_PACE_SPEEDS.items() if math.isclose(pace, race.speed))
    return Row(entry["claim"].format(controller=flown_preset(race.record()), label=label, speed=race.speed),
               f"{gains_text(flown.gains, len(flown.done))}; in view {_in_view(flown.done):.1%}; median lap "
               f"{median_change:+.1%}",
               lap_tail(flown.laps), "not measured (one target speed)",
               f"{_loop(race.estimator, race.record())}, AlphaPilot, {len(flown.laps)} laps, "
               f"{_seeds(race.seed, len(flown.laps))}; nominal MPPI's laps of those seeds from "
               + " and ".join(f"[{folder.name}]({folder.as_posix()}/)" for folder in frontiers),
               _tables_measured(root, path), path, per_tick(root / path))


def aggressive_paired_gain(root: Path, entry: dict) -> Row:
    """PixelMPC at the paper's 14 m/s target with a camera tilted up for both controllers (a `pixelmpc race` in
    the entry folder's ``best/``) against nominal MPPI on the same camera, flown on the same seeds at speeds
    around its lap time (the folder's frontier points): its median lap, the paired gain with the joined means and
    the local fit, the share in view, and its median lap against nominal MPPI's at the same target; every lap checked
    against the folder's per-tick record."""
    path = Path(entry["folder"])
    flown = _race_against_frontier(root, path, (path,))
    race, median = flown.race, _median_lap(flown.done)
    return Row(entry["claim"].format(controller=flown_preset(race.record()), speed=race.speed,
                                     tilt=race.camera_tilt_deg),
               f"median lap **{median:.2f}** s ({median / _median_lap(flown.at_target) - 1:+.1%} against nominal "
               f"MPPI at the same target); {gains_text(flown.gains, len(flown.done))}; in view "
               f"{_in_view(flown.done):.1%} (nominal MPPI at the same target {_in_view(flown.at_target):.1%})",
               lap_tail(flown.laps), f"{PAPER['pixelmpc_lap_s'][0]:g} s laps at the same target (the paper's camera)",
               f"{_loop(race.estimator, race.record())}, AlphaPilot, camera tilted {race.camera_tilt_deg:g} deg, "
               f"{len(flown.laps)} laps, {_seeds(race.seed, len(flown.laps))}",
               _tables_measured(root, path), path, per_tick(root / path))


def _onboard_pace_races(root: Path, folder: Path, races: dict[str, tuple[str, ...]]) -> tuple[dict, dict]:
    """The races of ``folder`` (``races``: each controller's, by the folder its metrics.json is in), each controller's
    joined in order: the first race's record and every lap. Each race must fly its controller on the loop, course and
    target the folder's first race flew, and a controller's races must follow one another in seed (a ValueError
    otherwise)."""
    path = root / folder
    metrics = {name: _json(path / name / "metrics.json") for names in races.values() for name in names}
    check_compact_record(path, {name: {"laps": metrics[name]["controllers"][controller]["laps"]}
                                for controller, names in races.items() for name in names})
    flown = {name: metrics[name]["controllers"][controller]["race"]
             for controller, names in races.items() for name in names}
    first = RaceSpec.from_record(next(iter(flown.values())))
    records, laps = {}, {}
    for controller, names in races.items():
        seed = None
        for name in names:
            race = RaceSpec.from_record(flown[name])
            loop = first.replace(controller=race.controller, config=race.config, seed=race.seed, laps=race.laps)
            if race.controller != controller or race.key() != loop.key():
                raise ValueError(f"{folder / name}: not {controller} on the loop of the folder's other races")
            if seed is not None and race.seed != seed:
                raise ValueError(f"{folder / name}: its first seed is {race.seed}, the race before ended at "
                                 f"{seed - 1}")
            seed = race.seed + race.laps
            records.setdefault(controller, flown[name])
            laps.setdefault(controller, []).extend(metrics[name]["controllers"][controller]["laps"])
    return records, laps


def onboard_pace(root: Path, entry: dict) -> Row:
    """A row of laps finished at the paper's 16 m/s label's pace on the onboard loop, nominal MPPI -> `best`: the
    `pixelmpc race --loop onboard` runs of the entry's folder, its ``races`` (each controller's, by the folder of its
    metrics.json, a controller's races on consecutive seeds), every lap checked against the per-tick record."""
    folder, races = Path(entry["folder"]), {name: tuple(names) for name, names in entry["races"].items()}
    records, laps = _onboard_pace_races(root, folder, races)
    finished = {name: sum(bool(lap["success"]) for lap in race_laps) for name, race_laps in laps.items()}
    intervals = [wilson_interval(finished[name], len(laps[name])) for name in races]
    failures = ", ".join(f"{(cause or 'flying').replace('_', ' ')} {count}"
                         for cause, count in sorted(failure_counts(laps["mppi"]).items(), key=str))
    done = [lap["lap_time_s"] for lap in laps["pixelmpc"] if lap["success"]]
    race = records["pixelmpc"]
    speed = race["speed"]
    label = next(label for label, pace in PAPER_PACE_SPEEDS.items() if math.isclose(pace, speed))
    return Row(entry["claim"].format(label=label, controller=flown_preset(race)),
               f"{_share(finished['mppi'], len(laps['mppi']))} -> "
               f"**{_share(finished['pixelmpc'], len(laps['pixelmpc']))}** "
               f"[{intervals[0][0]:.0%}, {intervals[0][1]:.0%}] -> [{intervals[1][0]:.0%}, {intervals[1][1]:.0%}]",
               f"its worst lap {max(done) / statistics.median(done) - 1:+.1%} over its median; nominal's "
               f"failures: {failures or 'none'}",
               "not measured (particle filter only)",
               f"{_loop(race['estimator'], race)}, the surveyed map, AlphaPilot, {speed:g} m/s, "
               f"{len(laps['pixelmpc'])} laps a controller, {_seeds(race['seed'], len(laps['pixelmpc']))}",
               _tables_measured(root, folder), folder, per_tick(root / folder))


def real_time(root: Path, entry: dict) -> Row:
    """The PixelMPC step and the closed-loop tick on two CPU cores (a harness report of ``benchmarks/results/``),
    beside the paper's Table I row on a GPU."""
    path = Path(entry["folder"])
    bench = _json(root / path / "bench.json")
    summary = bench["summary"]
    step = next(r for r in bench["rows"] if r["group"] == "controller" and r["name"].startswith("PixelMPC step (DOF")
                and r.get("rollout") == "batched" and r.get("sample_devices") == bench["device"]["num_devices"])
    mean, two_sigma, most = PAPER["step_ms"]
    return Row(entry["claim"].format(samples=summary["num_samples"], horizon=summary["horizon"]),
               f"**{summary['pixelmpc_step_median_ms']:.2f}** ms; the closed-loop tick "
               f"{summary['loop_tick_median_ms']:.2f} ms, {summary['loop_real_time_factor']:.2f}x real time",
               f"p95 {step['p95_ms']:.2f} ms, slowest {step['max_ms']:.2f} ms of {step['repeats']}",
               f"{mean:.1f} ± {two_sigma:.1f} ms, max {most:.1f} ms (GTX 1060)",
               f"the harness, samples over {bench['device']['num_devices']} CPU devices",
               f"{device_name(bench['device'])}, {stated_date(root / path / 'README.md')}", path, "n/a")


# what reads each kind of row the index lists (``experiments/results/index.json``, ``readme``)
KINDS: dict[str, Callable[[Path, dict], Row]] = {
    "visibility_at_same_lap_time": visibility_at_same_lap_time, "frontier_gain": frontier_gain,
    "courses_gain": courses_gain, "pace_paired_gain": pace_paired_gain,
    "aggressive_paired_gain": aggressive_paired_gain,
    "paper_main_cell": paper_main_cell, "table_iv_filter": table_iv_filter, "table_iv_eskf": table_iv_eskf,
    "onboard_pace": onboard_pace, "nominal_lap": nominal_lap, "dof_accuracy": dof_accuracy, "real_time": real_time,
}


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def row(root: Path, entry: dict) -> Row:
    """The row of one entry of the index's ``readme`` list (its ``kind``, ``folder``, ``claim`` and what its kind
    reads besides), read from the checkout ``root``."""
    if entry["kind"] not in KINDS:
        raise ValueError(f"{entry['folder']}: no row of kind {entry['kind']!r} (kinds: {', '.join(sorted(KINDS))})")
    return KINDS[entry["kind"]](Path(root), entry)


def table(root: Path) -> str:
    """The results table (Markdown) from the rows the index lists (:func:`~experiments.reporting.index.load`), read
    from the result folders under the checkout ``root``."""
    root = Path(root)
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for entry in index.load(root)["readme"]:
        row_ = row(root, entry)
        link = f"[{row_.folder.name}]({row_.folder.as_posix()}/)"
        lines.append("| " + " | ".join(_cell(v) for v in (*row_[:6], link, row_.per_tick)) + " |")
    return "\n".join(lines)


def rewrite_readme(root: Path, check: bool = False) -> tuple[str, str]:
    """(the README as it is, as the table makes it); the README is rewritten unless ``check`` (or it is current)."""
    readme = Path(root) / "README.md"
    old = readme.read_text()
    splice.check_markers(old, BEGIN, END, "README.md")  # refused before the table's seconds of reading
    new = splice.replace_block(old, table(root), BEGIN, END)
    if new != old and not check:
        readme.write_text(new)
    return old, new
