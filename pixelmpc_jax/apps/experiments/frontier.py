"""The speed frontier: perception-aware control measured against simply flying slower (issue 15).

Nominal MPPI flies the course at several target speeds; each speed gives a point (lap time, avoidable
low-visibility time), where the avoidable time is the time with the target gate's visibility below 50 %, counted
at every tick a gate is the target, less the capped part no attitude could avoid (``time_vis_avoidable_s``, see
:func:`~pixelmpc_jax.sim.metrics.visibility_masks`). The points, sorted by lap
time and joined linearly, are the frontier: what flying slower buys. A PixelMPC cell is worth having when
it keeps the gate in view better than the frontier at its own lap time; its ``frontier_gain`` is the
frontier's avoidable time at the cell's lap time over the cell's (above 1: better than flying slower). Beside it,
each row holds nominal MPPI's raw time below 50 % (nothing excused), share of time with the target in view and
mean angle to the target at the same lap time (``frontier_<figure>``), to hold the cell's own against.
The frontier is never extrapolated: a cell whose lap time lies outside the nominal lap times gets no gain
and the report names the nominal speed to add. All per-lap figures are means over the *completed* laps (a
lost lap also ends its low visibility early); a cell that lost laps is flagged, and every point reports its tail
(:func:`~pixelmpc_jax.sim.metrics.lap_tail`: the worst lap against the median, the laps more than 10 % over it).

Beside that gain (the joined means), each cell's ``gains`` hold the headline one, **paired**: each lap against its
own seed's nominal laps, and a local linear fit, each with a bootstrap interval over seeds
(:func:`~pixelmpc_jax.apps.experiments.gains.frontier_gains`); a claim's bars apply to the smallest of the three.
Pairing wants nominal speeds close together (``--speeds 6:9:0.25``): the report gives the widest lap-time gap
between the nominal laps that bracket a paired lap.

Files in ``out``: ``results.json`` (the grid, resumable per cell), ``frontier.json`` (strict JSON),
``REPORT.md``, ``frontier.png`` and ``laps.png`` (every lap, :mod:`~pixelmpc_jax.apps.experiments.lap_picture`).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.experiments import gains as gains_lib
from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.experiments.gains import AVOIDABLE_FLOOR_S, BOOTSTRAP_DRAWS, BOOTSTRAP_LEVEL
from pixelmpc_jax.apps.experiments.skeleton import Experiment
from pixelmpc_jax.apps.racing import grid
from pixelmpc_jax.apps.racing.frontier_curve import SAME_LAP_TIME_FIGURES, curve, interpolate, summarise
from pixelmpc_jax.apps.racing.presets import with_loop
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.sim.metrics import LOSS_CAUSES, PHASES, tail_columns
from pixelmpc_jax.strict_json import json_safe
from pixelmpc_jax.timing import LAP_TIME_LIMIT_S

PAPER_LAP_TIME_S = 31.8  # the paper's nominal lap at its "14 m/s" label: its pace
# 42.5 s .. 21.9 s laps: brackets the cells slowed to ~40 s at the pace and the 14 m/s label's cells (22-26 s); 8.5
# and 9.1 m/s are the paper's 14 and 16 m/s paces (presets.PAPER_PACE_SPEEDS), so the tables' nominal cells are here
DEFAULT_SPEEDS = (6.0, 7.0, 8.0, 8.5, 9.1, 10.0, 12.0, 14.0)
QUICK_SPEEDS = (6.0, 8.0, 8.5, 10.0)  # 42.5 s .. 27 s: brackets the paper's pace and slowed cells to ~40 s


@dataclasses.dataclass(frozen=True)
class FrontierSpec:
    """A frontier run: nominal MPPI at ``nominal_speeds`` and the PixelMPC ``cells``, ``laps`` laps each."""

    nominal_speeds: tuple = DEFAULT_SPEEDS
    cells: tuple = ()
    laps: int = 10


def pixel_cell(model: str, cost: str = "l1", c_pixel: float = 9e6, speed: float = 8.0, t_f: float = 1.0,
               config: ControllerConfig | None = None) -> grid.Cell:
    """A PixelMPC grid cell named after its pixel model, pixel cost, weight and speed; ``config`` holds any further
    settings (its other fields different from the defaults are named in the cell's name too)."""
    config = dataclasses.replace(config or ControllerConfig(), pixel_model=model, pixel_cost=cost, c_pixel=c_pixel,
                                 t_f=t_f)
    spec = RaceSpec("pixelmpc", config=config, speed=speed)
    extra = "".join(f"_{k.replace('.', '-')}{v:g}" if isinstance(v, float) else f"_{k.replace('.', '-')}{v}"
                    for k, v in sorted(cell_settings(spec).items()) if k != "pixel_cost")
    weight = f"{c_pixel:.0e}".replace("e+0", "e").replace("e+", "e")  # 9e6
    return grid.Cell(f"pixelmpc_{model}_{cost}_c{weight}_tf{t_f:g}_v{speed:g}{extra}", spec)


def cell_settings(spec: RaceSpec) -> dict:
    """The controller settings of a cell other than its defaults, less those a frontier row reports in columns of
    their own (pixel model, weight, t_f)."""
    return {k: v for k, v in spec.changed_settings().items() if k not in ("pixel_model", "c_pixel", "t_f")}


BORDER_C_PIXEL = {"projection": 9e6, "dof": 3e7}  # the weights the 4-lap sweep at 8 m/s chose (docs/results.md)


def border_cells() -> tuple:
    """The border cost at each pixel model's weight of the 4-lap sweep (projection 9e6, DOF 3e7), 8 m/s, t_f 1."""
    return tuple(pixel_cell(model, "border", BORDER_C_PIXEL[model]) for model in ("projection", "dof"))


def preset_cells(speed: float) -> tuple:
    """The ``paper`` and ``best`` presets at ``speed``, and the border cost with the exact projection pixel model
    (the reference: a pixel model that knows where the gate is)."""
    from pixelmpc_jax.apps.racing.presets import preset

    return (grid.Cell(f"paper_v{speed:g}", preset("paper").replace(speed=speed)),
            grid.Cell(f"best_v{speed:g}", preset("best").replace(speed=speed)),
            pixel_cell("projection", "border", 9e6, speed=speed))


def ceiling_cells(speed: float) -> tuple:
    """The ``best`` preset at ``speed`` and the exact projection flying every other setting of it: the ceiling of
    knowing where the gate is, against which the preset's learned pixel model is measured."""
    return _best_beside(speed, "projection", pixel_model="projection")


def partial_target_cells(speed: float) -> tuple:
    """The ``best`` preset at ``speed`` and the same race with its target's pixel from the detector even while the
    detector reports the gate cut by the image border (``partial_target="detected"``, the preset's before it took
    the map's pixel there against the tail's lost gates; docs/results.md)."""
    return _best_beside(speed, "partial_detected", partial_target="detected")


def _best_beside(speed: float, name: str, **changes) -> tuple:
    """The ``best`` preset at ``speed`` (cell ``best_v<speed>``) and the same race with the controller settings
    ``changes`` (cell ``best_<name>_v<speed>``)."""
    from pixelmpc_jax.apps.racing.presets import preset

    best = preset("best").replace(speed=speed)
    other = best.replace(config=dataclasses.replace(best.config, **changes))
    return grid.Cell(f"best_v{speed:g}", best), grid.Cell(f"best_{name}_v{speed:g}", other)


def default_cells() -> tuple:
    """The paper's L1 cost at c_pixel 9e6 and the border cost at the sweep's weight, each with the projection and
    the DOF, 8 m/s."""
    return tuple(pixel_cell(model, "l1") for model in ("projection", "dof")) + border_cells()


def default_spec() -> FrontierSpec:
    return FrontierSpec(DEFAULT_SPEEDS, default_cells(), laps=10)


def quick_spec() -> FrontierSpec:
    """Four nominal speeds around the paper's pace and the border-cost cells (projection, DOF), 4 laps."""
    return FrontierSpec(QUICK_SPEEDS, border_cells(), laps=4)


def nominal_cell(speed: float, max_time_s: float = LAP_TIME_LIMIT_S) -> grid.Cell:
    return grid.Cell(f"nominal_{speed:g}", RaceSpec("mppi", speed=float(speed), max_time_s=max_time_s))


def suggest_speed(nominal: list[dict], lap_time: float) -> float | None:
    """A nominal target speed to add so that ``lap_time`` is bracketed (lap time taken as inversely
    proportional to the target speed from the nearest nominal point, rounded outward to 0.5 m/s)."""
    points = sorted((p["lap_time_s"], p["speed"]) for p in nominal if p["lap_time_s"] is not None)
    if not points:
        return None
    if lap_time > points[-1][0]:
        return max(0.5, math.floor(2 * points[-1][1] * points[-1][0] / lap_time) / 2)
    return math.ceil(2 * points[0][1] * points[0][0] / lap_time) / 2


def lap_pairs(result: dict) -> np.ndarray:
    """(L, 2) lap time and avoidable low-visibility time of each completed lap of one cell's results."""
    return np.asarray([(lap["lap_time_s"], lap["time_vis_avoidable_s"])
                       for lap in result.get("laps", []) if lap.get("success") and lap.get("lap_time_s") is not None
                       and lap.get("time_vis_avoidable_s") is not None], np.float64).reshape(-1, 2)


def gain_interval(cell: np.ndarray, nominal: list[np.ndarray], draws: int = BOOTSTRAP_DRAWS,
                  level: float = BOOTSTRAP_LEVEL, seed: int = 0) -> tuple[float, float] | None:
    """A percentile bootstrap interval of the frontier gain: every draw resamples, with replacement, the cell's
    completed laps and each nominal point's completed laps (``(L, 2)`` lap time, avoidable s), takes their
    means, interpolates the nominal frontier at the cell's mean lap time and divides; draws where the frontier
    does not bracket the cell are dropped. None when fewer than half the draws bracket it."""
    if len(cell) == 0 or any(len(point) == 0 for point in nominal) or len(nominal) < 2:
        return None
    rng = np.random.default_rng(seed)

    def resampled_means(laps: np.ndarray) -> np.ndarray:  # (draws, 2)
        return laps[rng.integers(0, len(laps), (draws, len(laps)))].mean(axis=1)

    cell_means = resampled_means(cell)
    points = np.stack([resampled_means(point) for point in nominal], axis=1)  # (draws, P, 2)
    gains = []
    for (lap_time, avoidable), frontier in zip(cell_means, points):
        order = np.argsort(frontier[:, 0])
        xs, ys = frontier[order, 0], frontier[order, 1]
        if xs[0] <= lap_time <= xs[-1]:
            gains.append(float(np.interp(lap_time, xs, ys)) / max(avoidable, AVOIDABLE_FLOOR_S))
    if len(gains) < draws / 2:
        return None
    tail = 100 * (1 - level) / 2
    return float(np.percentile(gains, tail)), float(np.percentile(gains, 100 - tail))


def against_nominal(result: dict, nominal: list[dict], nominal_results: list[dict]) -> dict:
    """One cell's race ``result`` (:func:`summarise`'s figures) held against the nominal points ``nominal`` (each
    ``{"speed", **summarise(...)}``) at its own lap time: ``bracketed``, ``frontier_avoidable_s``, ``frontier_gain``,
    ``frontier_<figure>`` of :data:`SAME_LAP_TIME_FIGURES`, ``frontier_gain_interval`` (:func:`gain_interval` over
    the cell's and the points' laps, ``nominal_results`` being the points' race results in the bootstrap's order) and
    ``suggested_nominal_speed``."""
    row = summarise(result)
    frontier = interpolate(nominal, row["lap_time_s"])
    row["bracketed"] = frontier is not None
    row["frontier_avoidable_s"] = frontier
    row["frontier_gain"] = None
    if frontier is not None and row["avoidable_s"] is not None:
        row["frontier_gain"] = frontier / max(row["avoidable_s"], AVOIDABLE_FLOOR_S)
    for figure in SAME_LAP_TIME_FIGURES:
        row[f"frontier_{figure}"] = interpolate(nominal, row["lap_time_s"], figure)
    row["frontier_gain_interval"] = gain_interval(lap_pairs(result), [lap_pairs(point) for point in nominal_results])
    row["suggested_nominal_speed"] = (None if row["bracketed"] or row["lap_time_s"] is None
                                      else suggest_speed(nominal, row["lap_time_s"]))
    return row


def build(results: dict, nominal_speeds, cells, laps: int, seed: int, max_time_s: float = LAP_TIME_LIMIT_S) -> dict:
    """The frontier from the grid's results (``{cell name: race results}``); cells not run yet are listed
    under ``missing``."""
    nominal, nominal_laps, missing = [], [], []
    for speed in nominal_speeds:
        cell = nominal_cell(speed, max_time_s)
        if cell.name not in results:
            missing.append(cell.name)
            continue
        nominal.append({"name": cell.name, "speed": float(speed),
                        "estimator": results[cell.name].get("config", {}).get("estimator", "truth"),
                        **summarise(results[cell.name])})
        nominal_laps.append(gains_lib.completed_laps(results[cell.name]))
    nominal.sort(key=lambda p: p["speed"])
    nominal_results = [results[nominal_cell(v, max_time_s).name] for v in nominal_speeds
                       if nominal_cell(v, max_time_s).name in results]
    rows = []
    for cell in cells:
        if cell.name not in results:
            missing.append(cell.name)
            continue
        spec = cell.spec
        row = {"name": cell.name, "pixel_model": spec.config.pixel_model, "speed": spec.speed,
               "t_f": spec.config.t_f, "c_pixel": spec.config.c_pixel, "options": cell_settings(spec),
               "estimator": spec.estimator, **against_nominal(results[cell.name], nominal, nominal_results)}
        row["gains"] = gains_lib.frontier_gains(gains_lib.completed_laps(results[cell.name]), nominal_laps)
        rows.append(row)
    from pixelmpc_jax.platform_info import device_description

    return {"nominal": nominal, "cells": rows, "paper_lap_time_s": PAPER_LAP_TIME_S,
            "paper_pace": interpolate(nominal, PAPER_LAP_TIME_S, "speed"), "missing": missing,
            "measured": {"laps": laps, "seeds": [seed, seed + laps - 1], "device": device_description(),
                         "written": datetime.datetime.now().isoformat(timespec="seconds"),
                         "avoidable_floor_s": AVOIDABLE_FLOOR_S,
                         "gain_interval": f"{BOOTSTRAP_LEVEL:.0%} percentile bootstrap over the cell's and each "
                                          f"nominal point's completed laps, {BOOTSTRAP_DRAWS} draws",
                         "gains": f"paired: each lap on its own seed's nominal laps joined by lap time (out of their "
                                  f"range: left out); joined means; a line fitted to nominal's laps within "
                                  f"{gains_lib.LOCAL_FIT_HALF_WIDTH_S:g} s of the cell's mean lap time. Intervals: "
                                  f"{BOOTSTRAP_LEVEL:.0%} percentile bootstrap over seeds, {BOOTSTRAP_DRAWS} draws, "
                                  f"generator seed {gains_lib.BOOTSTRAP_SEED}"}}


def gains_against(results: dict, cells, frontier_dir: Path, nominal_speeds, laps: int, seed: int = 0) -> dict:
    """``{cell name: frontier row}`` (:func:`build`'s: avoidable time, frontier gain, its interval) of the PixelMPC
    ``cells`` in ``results`` against the nominal points at ``nominal_speeds`` finished in ``frontier_dir`` with the
    same ``laps`` and ``seed`` (the points not flown there are left out)."""
    nominal = grid.current_results([nominal_cell(v) for v in nominal_speeds], frontier_dir, laps, seed)
    speeds = [v for v in nominal_speeds if nominal_cell(v).name in nominal]
    pixel = [cell for cell in cells if cell.spec.controller == "pixelmpc" and cell.name in results]
    built = build({**results, **nominal}, speeds, pixel, laps, seed)
    return {row["name"]: row for row in built["cells"]}


def frontier_figure(frontier: dict, out: Path) -> str:
    """Draw ``frontier.png`` (the report links it) and, from the grid's ``results.json``, ``laps.png``: every lap
    of the frontier's points (:mod:`~pixelmpc_jax.apps.experiments.lap_picture`); returns the latter's link."""
    from pixelmpc_jax.apps.experiments import lap_picture

    plot(frontier, Path(out) / "frontier.png")
    names = {p["name"] for p in frontier["nominal"] + frontier["cells"]}
    races = lap_picture.folder_races(out, names) if (Path(out) / "results.json").is_file() else []
    if not races:
        return ""
    lap_picture.plot_laps(races, Path(out) / "laps.png", title="every lap of the frontier's points")
    return "\n![every lap: avoidable time and share in view against lap time](laps.png)\n"


def frontier_experiment(nominal_speeds, cells, laps: int, seed: int, max_time_s: float = LAP_TIME_LIMIT_S,
                        course: str | None = None, camera_tilt_deg: float | None = None,
                        loop: str | None = None) -> Experiment:
    """Nominal MPPI at each of ``nominal_speeds`` (episodes of at most ``max_time_s``) and every PixelMPC cell as an
    experiment: the frontier (:func:`build`) in ``frontier.json``, ``REPORT.md`` and ``frontier.png``. ``course`` (a
    name or a course file) flies every cell on that course instead of the cells' own; ``camera_tilt_deg`` every
    cell, nominal MPPI's too, with that camera (``RaceSpec.camera_tilt_deg``); ``loop`` (a name of
    :data:`~pixelmpc_jax.apps.racing.presets.LOOPS`) every cell, nominal MPPI's too, on that loop (``"onboard"``:
    the image detector, the ESKF, the gate switch from the estimate and the surveyed map)."""
    all_cells = [nominal_cell(speed, max_time_s) for speed in nominal_speeds] + list(cells)
    overrides = {name: value for name, value in (("course", course), ("camera_tilt_deg", camera_tilt_deg))
                 if value is not None}
    if overrides:
        all_cells = [dataclasses.replace(cell, spec=cell.spec.replace(**overrides)) for cell in all_cells]
    if loop is not None:
        all_cells = [dataclasses.replace(cell, spec=with_loop(cell.spec, loop)) for cell in all_cells]
    cells = all_cells[len(nominal_speeds):]
    return Experiment(tuple(all_cells),
                      summarise=lambda results: build(results, nominal_speeds, cells, laps, seed, max_time_s),
                      report=lambda frontier, missing: report(frontier), plot=frontier_figure, record=json_safe,
                      record_file="frontier.json")


def run_frontier(nominal_speeds, cells, out: Path, laps: int = 10, seed: int = 0, progress: bool = True,
                 dof_params=None, max_time_s: float = LAP_TIME_LIMIT_S, course: str | None = None,
                 camera_tilt_deg: float | None = None, reuse=(), loop: str | None = None, executor=None) -> dict:
    """Fly the frontier (:func:`frontier_experiment`) into ``out`` with
    :func:`~pixelmpc_jax.apps.experiments.skeleton.run` (resumable per cell) and write ``frontier.json``,
    ``REPORT.md`` and ``frontier.png``; returns the frontier. Only the cells of this run (settings, laps, seed,
    weights) count. Interrupted (Ctrl-C), the finished cells are kept, the outputs are written from them, and the
    KeyboardInterrupt is raised again. A cell whose race a finished cell of a grid folder in ``reuse`` already flew
    (the same settings, laps and seed, e.g. a tune validation's nominal points) is copied from there.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    experiment = frontier_experiment(nominal_speeds, cells, laps, seed, max_time_s, course, camera_tilt_deg, loop)
    return skeleton.run(experiment, out, laps, seed, progress, dof_params, reuse, executor=executor)


def _f(value, digits: int = 2, sigma=None) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" + ("" if sigma is None else f" ± {sigma:.{digits}f}")


def _percent(share: float | None) -> str:
    return "-" if share is None else f"{100 * share:.1f}"


def _done(p: dict) -> str:
    return f"{p['laps_completed']}/{p['laps']}"


def _tail(p: dict) -> str:
    """The three tail columns of a point: laps finished, the worst lap against the median, the slow laps."""
    return " | ".join(tail_columns(p["tail"]))


def _with_interval(entry: dict | None) -> str:
    if not entry or entry.get("gain") is None:
        return "-"
    interval = entry.get("interval")
    return f"{entry['gain']:.2f}" + (" [{:.2f}, {:.2f}]".format(*interval) if interval else "")


def gains_table(cells: list[dict]) -> list[str]:
    """Markdown lines: each cell's gain three ways (:mod:`~pixelmpc_jax.apps.experiments.gains`) and the smallest,
    with the laps paired and out of their seed's range."""
    lines = ["", "## The gain three ways", "",
             "Paired (the headline): each completed lap against its own seed's nominal laps, joined by lap time, at "
             "the lap's time; a lap outside its seed's nominal lap times is left out (out of range). Joined means: "
             "the frontier gain above. Local fit: a line through nominal's laps near the cell's mean lap time. "
             "Intervals: bootstrap over seeds. Widest gap: the largest lap-time gap between the two nominal laps "
             "that bracket a paired lap (a dense frontier keeps it small). A claim's bars apply to the smallest.", "",
             "| cell | paired gain | laps paired (out of range) | widest gap [s] | joined means | local fit "
             "| smallest |", "|---|---|---|---|---|---|---|"]
    for c in cells:
        g = c.get("gains")
        if not g:
            continue
        least = g["smallest"]
        smallest = "-" if least is None else f"{_with_interval(least)} ({least['construction'].replace('_', ' ')})"
        lines.append(f"| {c['name']} | {_with_interval(g['paired'])} | {g['laps_paired']} "
                     f"({g['laps_out_of_range']}) | {_f(g['widest_gap_s'], 1)} | {_with_interval(g['joined_means'])} "
                     f"| {_with_interval(g['local_fit'])} | {smallest} |")
    return lines


def report(frontier: dict) -> str:
    """Markdown: the nominal frontier, the PixelMPC cells against it, the causes, how it was measured."""
    causes = " | ".join(LOSS_CAUSES)
    lines = ["# The speed frontier: PixelMPC against flying slower", "",
             "Low visibility counts at every tick a gate is the target, from the tick the previous gate is passed. "
             "Avoidable: that time with visibility < 50 % less the part no attitude could avoid, capped per gate at "
             "the ticks the target speed needs to fly through it; raw: nothing excused. Means ± 2σ over the "
             "completed laps. Frontier gain: the nominal curve's avoidable time at the cell's lap time over the "
             "cell's (above 1: better than flying slower). In view: share of flown time with the target in the "
             "image; angle: mean angle between the optical axis and the target's centre. Nominal's figures at the "
             "cell's lap time stand in brackets.", "",
             "## Nominal MPPI", "", "| target [m/s] | laps done | worst lap vs median | laps > 10 % over median "
             "| lap time [s] | raw vis < 50 % [s] | avoidable [s] | in view [%] | angle [deg] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for p in frontier["nominal"]:
        lines.append(f"| {p['speed']:g} | {_tail(p)} | {_f(p['lap_time_s'], 1, p['lap_time_two_sigma_s'])} | "
                     f"{_f(p['vis_below_50_s'])} | {_f(p['avoidable_s'], 2, p['avoidable_two_sigma_s'])} | "
                     f"{_percent(p.get('share_target_in_view'))} | {_f(p.get('mean_target_angle_deg'), 1)} |")
    pace = frontier["paper_pace"]
    lines += ["", f"Paper's pace (nominal lap of {frontier['paper_lap_time_s']:g} s): "
              + (f"{pace:.2f} m/s." if pace is not None else "not bracketed by the nominal speeds."), "",
              "## PixelMPC cells", "",
              "| cell | model | options | target [m/s] | laps done | worst lap vs median | laps > 10 % over median "
              "| lap time [s] | raw vis < 50 % [s] (nominal) | in view [%] (nominal) | angle [deg] (nominal) "
              "| avoidable [s] | frontier at its lap time [s] | frontier gain |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in frontier["cells"]:
        options = ", ".join(f"{k}={v}" for k, v in c["options"].items()) or "-"
        gain = _f(c["frontier_gain"]) if c["bracketed"] else "not bracketed"
        if c["bracketed"] and c.get("frontier_gain_interval"):
            gain += " [{:.2f}, {:.2f}]".format(*c["frontier_gain_interval"])
        if c["frontier_gain"] is not None and c["avoidable_s"] < AVOIDABLE_FLOOR_S:
            gain += " (no avoidable time: over the floor)"
        if c["frontier_gain"] is not None and not c["all_laps_completed"]:
            gain += " (laps lost)"
        lines.append(f"| {c['name']} | {c['pixel_model']} | {options} | {c['speed']:g} | {_tail(c)} | "
                     f"{_f(c['lap_time_s'], 1, c['lap_time_two_sigma_s'])} | "
                     f"{_f(c['vis_below_50_s'])} ({_f(c.get('frontier_vis_below_50_s'))}) | "
                     f"{_percent(c.get('share_target_in_view'))} "
                     f"({_percent(c.get('frontier_share_target_in_view'))}) | "
                     f"{_f(c.get('mean_target_angle_deg'), 1)} ({_f(c.get('frontier_mean_target_angle_deg'), 1)}) | "
                     f"{_f(c['avoidable_s'], 2, c['avoidable_two_sigma_s'])} | {_f(c['frontier_avoidable_s'])} | "
                     f"{gain} |")
    for c in frontier["cells"]:
        if c["lap_time_s"] is None:
            lines += ["", f"`{c['name']}` completed no lap: no lap time, no gain."]
        elif not c["bracketed"]:
            lines += ["", f"`{c['name']}` (lap {c['lap_time_s']:.1f} s) lies outside the nominal lap times: add a "
                      f"nominal speed of about {c['suggested_nominal_speed']:g} m/s (`--speeds`)."]
        if c["lap_time_s"] is not None and not c["all_laps_completed"]:
            lines += ["", f"`{c['name']}` lost laps: its figures are over the completed laps only (a lost lap also "
                      "ends its low visibility early)."]
    lines += gains_table(frontier["cells"])
    lines += ["", "## Where the low-visibility time goes (s per lap)", "", f"| point | {causes} |",
              "|---|" + "---|" * len(LOSS_CAUSES)]
    for p in frontier["nominal"] + frontier["cells"]:
        label = f"nominal {p['speed']:g} m/s" if p["name"].startswith("nominal_") else p["name"]
        lines.append(f"| {label} | " + " | ".join(_f(p["causes"].get(k)) for k in LOSS_CAUSES) + " |")
    lines += ["", "## When the avoidable time falls, from the tick its gate became the target (s per lap)", "",
              "| point | first second | 1-2 s | later |", "|---|---|---|---|"]
    for p in frontier["nominal"] + frontier["cells"]:
        label = f"nominal {p['speed']:g} m/s" if p["name"].startswith("nominal_") else p["name"]
        lines.append(f"| {label} | " + " | ".join(_f((p.get("phases") or {}).get(k)) for k in PHASES) + " |")
    m, d = frontier["measured"], frontier["measured"]["device"]
    # a point whose record names no estimator (nominal MPPI's, before frontiers flew other loops) flew the truth
    states = sorted({"ground-truth" if c.get("estimator", "truth") == "truth" else c["estimator"]
                     for c in frontier["cells"] + frontier["nominal"]})
    lines += ["", "## How it was measured", "",
              f"{m['laps']} laps per point (seeds {m['seeds'][0]}-{m['seeds'][1]}), "
              f"{' and '.join(states)} state, on "
              f"{d['platform']} ({d['device_kind']}; CPU {d['cpu_model']}, {d['cpu_count']} cores; jax {d['jax']}), "
              f"written {m['written']}. A cell with no avoidable time is divided by {m['avoidable_floor_s']:g} s. "
              f"The gain's interval: {m.get('gain_interval', 'none')}.",
              "", "![avoidable low-visibility time against lap time](frontier.png)"]
    if frontier["missing"]:
        lines += ["", f"Not yet run (the experiment resumes with them): {', '.join(frontier['missing'])}."]
    return "\n".join(lines) + "\n"


def plot(frontier: dict, path: Path) -> None:
    """Avoidable low-visibility time against lap time: the nominal curve, the frontier / 1.5, the cells."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    xs, ys = curve(frontier["nominal"], "avoidable_s")
    if len(xs):
        ax.plot(xs, ys, "k-s", ms=5, label="nominal MPPI (flying slower)")
        ax.plot(xs, ys / 1.5, "k--", lw=1, label="frontier / 1.5")
        for p in frontier["nominal"]:
            if p["lap_time_s"] is not None and p["avoidable_s"] is not None:
                ax.annotate(f"{p['speed']:g} m/s", (p["lap_time_s"], p["avoidable_s"]), fontsize=7,
                            xytext=(4, 4), textcoords="offset points")
    markers = {"projection": "o", "dof": "^"}
    for c in frontier["cells"]:
        if c["lap_time_s"] is None or c["avoidable_s"] is None:
            continue
        label = c["name"] + ("" if c["all_laps_completed"] else f" ({_done(c)} laps; faded)")
        alpha = 1.0 if c["all_laps_completed"] else 0.35  # lost laps end their low visibility early: faded
        bars = ax.errorbar(c["lap_time_s"], c["avoidable_s"], xerr=c["lap_time_two_sigma_s"],
                           yerr=c["avoidable_two_sigma_s"], fmt=markers.get(c["pixel_model"], "D"), capsize=3,
                           label=label, alpha=alpha)
        ax.annotate(c["name"], (c["lap_time_s"], c["avoidable_s"]), fontsize=6, xytext=(4, -10),
                    textcoords="offset points", color=bars[0].get_color(), alpha=alpha)
    ax.axvline(frontier["paper_lap_time_s"], color="grey", ls=":", lw=1, label="paper's nominal lap")
    ax.set(xlabel="lap time [s]", ylabel="avoidable time with visibility < 50 % [s per lap]",
           title="PixelMPC against flying slower (mean ± 2σ)")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
