"""The paper's visibility experiments (Tables II and III, Fig. 6 with ground truth): grid, report, figures.

Each report writes ``results.json`` (every lap), ``summary.json`` (the tables' cells), ``REPORT.md``
(ours beside the paper's figures) and PNG figures into its output directory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.experiments.frontier import gains_against, nominal_cell
from pixelmpc_jax.apps.experiments.skeleton import Experiment
from pixelmpc_jax.apps.racing.grid import Cell, fmt
from pixelmpc_jax.apps.racing.presets import PAPER_NOMINAL_LAP_S, PAPER_PACE_SPEEDS, PRESETS, preset
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.platform_info import device_line

# The paper's Tables II and III (14 m/s, 10 races per cell, mean +- 2 sigma), keyed by (t_f, c_pixel).
PAPER_VIS_BELOW_50 = {(0.0, 0.0): (13.6, 3.6), (1.0, 3e6): (3.6, 0.6), (1.0, 6e6): (1.9, 0.6), (1.0, 9e6): (1.5, 0.2),
                      (2.0, 3e6): (3.1, 0.9), (2.0, 6e6): (2.0, 0.6), (2.0, 9e6): (1.9, 1.2)}
PAPER_VIS_ZERO = {(0.0, 0.0): (3.6, 1.1), (1.0, 3e6): (1.0, 0.3), (1.0, 6e6): (1.1, 0.5), (1.0, 9e6): (0.2, 0.1),
                  (2.0, 3e6): (0.7, 0.4), (2.0, 6e6): (0.6, 0.2), (2.0, 9e6): (0.2, 0.1)}
PAPER_LAP_TIME = {(0.0, 0.0): (31.8, 1.0), (1.0, 3e6): (32.7, 0.4), (1.0, 6e6): (33.2, 0.2), (1.0, 9e6): (33.5, 0.2),
                  (2.0, 3e6): (33.2, 0.1), (2.0, 6e6): (34.2, 0.3), (2.0, 9e6): (34.0, 0.5)}
PAPER_ACCELERATION_CHANGE = -0.29  # "29% decrease in linear and angular accelerations in mean"

CALIBRATION_NOTE = (
    "Our pixel cost per step is c_pixel x 3e-5 x L1(uv - centre) with each axis clipped to 1 image size "
    "(`ControllerConfig.pixel_cost_scale`, `pixel_error_clip`). The paper's cost units are not recoverable, so "
    "the scale was chosen so that the paper's best cell (t_f = 1 s, c_pixel = 9e6) costs about the lap time "
    "the paper's does (+5 %): 4-lap probes gave +7 % at 3e-5 and +25 % at 1e-4. In this world the target "
    "gate cannot stay in view at cruise speed: with FlightGoggles' drag (0.1 |v| v, 1 kg) holding 14 m/s "
    "needs a 63 deg pitch and even 8.3 m/s needs 35 deg, the camera's half vertical field of view, so the "
    "gate ahead leaves the top of the image. Our nominal MPPI flies the course at 10.5 m/s on average "
    "(21.8 s laps; the paper's took 31.8 s, about 7.4 m/s), so keeping the gate in view costs speed: probes "
    "with the exact projection pixel model traded -15 % time below 50 % visibility for +25 % lap time "
    "(scale 1e-4) and -41 % for +19 % with a dead zone of 0.3 (scale 5e-4, one of four laps missed a gate).")

T_F_VALUES = (1.0, 2.0)
C_PIXEL_VALUES = (3e6, 6e6, 9e6)
LABEL_SPEED = 14.0  # the paper's Tables II and III were flown at this target
OPERATING_POINTS = {"label": LABEL_SPEED, "pace": PAPER_PACE_SPEEDS[LABEL_SPEED]}  # name -> our target speed


def grid_cell_name(pixel_model: str, t_f: float, c_pixel: float, speed: float) -> str:
    return f"pixelmpc_{pixel_model}_tf{t_f:g}_c{c_pixel:.0e}_v{speed:g}"


def visibility_cells(pixel_model: str = "dof", speed: float = LABEL_SPEED, t_f_values=T_F_VALUES,
                     c_pixel_values=C_PIXEL_VALUES, best: bool = True) -> list[Cell]:
    """Nominal MPPI, PixelMPC over the t_f x c_pixel grid (the ``paper`` preset is its t_f 1, c_pixel 9e6 cell with
    the DOF) and, with ``best``, the ``best`` preset, all at the target ``speed``."""
    cells = [nominal_cell(speed)]
    for t_f in t_f_values:
        for c_pixel in c_pixel_values:
            config = ControllerConfig(t_f=t_f, c_pixel=c_pixel, pixel_model=pixel_model)
            cells.append(Cell(grid_cell_name(pixel_model, t_f, c_pixel, speed),
                              RaceSpec(controller="pixelmpc", config=config, speed=speed)))
    if best:
        cells.append(Cell(f"best_v{speed:g}", preset("best").replace(speed=speed)))
    return cells


def preset_of(spec: RaceSpec) -> str | None:
    """The preset (of :data:`PRESETS`) whose race ``spec`` is, at any target speed; None for other cells."""
    for name in PRESETS:
        if spec.replace(speed=LABEL_SPEED).key() == preset(name).replace(speed=LABEL_SPEED).key():
            return name
    return None


def pixel_settings(spec: RaceSpec) -> dict:
    """The cell's t_f, c_pixel and pixel model as the tables print them (0, 0 and None for nominal MPPI)."""
    if spec.controller != "pixelmpc":
        return {"t_f": 0.0, "c_pixel": 0.0, "pixel_model": None}
    return {"t_f": spec.config.t_f, "c_pixel": spec.config.c_pixel, "pixel_model": spec.config.pixel_model}


def _table_key(spec: RaceSpec) -> tuple[float, float]:
    """(t_f, c_pixel): the key of the paper's tables (0, 0 for nominal MPPI)."""
    settings = pixel_settings(spec)
    return settings["t_f"], settings["c_pixel"]


def _paper(table: dict, t_f: float, c_pixel: float) -> str:
    value = table.get((t_f, c_pixel))
    return f"{value[0]:.1f} ± {value[1]:.1f}" if value else "-"


def _aggregates(agg: dict) -> dict:
    keys = ("time_vis_below_50_s", "time_vis_zero_s", "time_vis_below_50_after_seen_s", "time_vis_zero_after_seen_s",
            "lap_time_s", "mean_linear_acc", "mean_angular_acc",
            "total_variation_roll", "total_variation_pitch", "total_variation_yaw", "share_target_in_view",
            "mean_target_angle_deg")
    return {key: agg.get(key) for key in keys}


def summarise(results: dict, cells: list[Cell], gains: dict | None = None) -> list[dict]:
    """One row per cell: its target speed, preset, our aggregates, its frontier row from ``gains`` (``{cell name:
    frontier.build's row}``: avoidable time, frontier gain and its interval) and the paper's figures."""
    rows = []
    for cell in cells:
        res = results.get(cell.name)
        if res is None:
            continue
        agg, spec = res["aggregate"], cell.spec
        gain = (gains or {}).get(cell.name) or {}
        rows.append({
            "cell": cell.name, "speed": spec.speed, "preset": preset_of(spec), **pixel_settings(spec),
            "success_rate": agg["success_rate"], "num_laps": agg["num_laps"], **_aggregates(agg),
            "avoidable_s": gain.get("avoidable_s"), "frontier_gain": gain.get("frontier_gain"),
            "frontier_gain_interval": gain.get("frontier_gain_interval"), "wall_time_s": res.get("wall_time_s"),
            "paper": {"time_vis_below_50_s": PAPER_VIS_BELOW_50.get(_table_key(spec)),
                      "time_vis_zero_s": PAPER_VIS_ZERO.get(_table_key(spec)),
                      "lap_time_s": PAPER_LAP_TIME.get(_table_key(spec))},
        })
    return rows


def _gain(row: dict) -> str:
    if row["frontier_gain"] is None:
        return "-" if row["c_pixel"] == 0 else "not bracketed"
    interval = row.get("frontier_gain_interval")
    return f"{row['frontier_gain']:.2f}" + (" [{:.2f}, {:.2f}]".format(*interval) if interval else "")


def _name(row: dict) -> str:
    if row["c_pixel"] == 0:
        return "nominal MPPI"
    return f"**{row['preset']}**" if row["preset"] else row["cell"].rsplit("_v", 1)[0].replace("pixelmpc_", "")


def _point_table(rows: list[dict]) -> list[str]:
    """One operating point's Tables II/III rows: ours beside the paper's, the view metrics and the frontier gain."""
    lines = ["| cell | t_f [s] | c_pixel | vis < 50 % [s] from the target | paper's rule | paper | vis = 0 % [s] "
             "from the target | paper's rule | paper | lap time [s] ours | paper | lap vs nominal | in view [%] | "
             "angle to target [deg] | avoidable [s] | frontier gain [90 %] | laps done |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    nominal = next((r for r in rows if r["c_pixel"] == 0.0), None)
    for r in rows:
        change = "-"
        if nominal and r["lap_time_s"]["mean"] is not None and nominal["lap_time_s"]["mean"]:
            change = f"{r['lap_time_s']['mean'] / nominal['lap_time_s']['mean'] - 1:+.1%}"
        view = r["share_target_in_view"] or {}
        in_view = f"{100 * view['mean']:.1f}" if view.get("mean") is not None else "-"
        avoidable = f"{r['avoidable_s']:.2f}" if r["avoidable_s"] is not None else "-"
        lines.append(
            f"| {_name(r)} | {r['t_f']:g} | {r['c_pixel']:.0e} | {fmt(r['time_vis_below_50_s'])} | "
            f"{fmt(r['time_vis_below_50_after_seen_s'])} | {_paper(PAPER_VIS_BELOW_50, r['t_f'], r['c_pixel'])} | "
            f"{fmt(r['time_vis_zero_s'])} | {fmt(r['time_vis_zero_after_seen_s'])} | "
            f"{_paper(PAPER_VIS_ZERO, r['t_f'], r['c_pixel'])} | {fmt(r['lap_time_s'])} | "
            f"{_paper(PAPER_LAP_TIME, r['t_f'], r['c_pixel'])} | {change} | {in_view} | "
            f"{fmt(r['mean_target_angle_deg'])} | {avoidable} | {_gain(r)} | "
            f"{round(r['success_rate'] * r['num_laps'])}/{r['num_laps']} |")
    return lines


def _smoothness_table(rows: list[dict]) -> list[str]:
    """Fig. 6's figures per cell; the accelerations' change is against nominal MPPI at the same target."""
    nominal = {r["speed"]: r for r in rows if r["c_pixel"] == 0.0}
    lines = ["| cell | target [m/s] | TV roll [rad] | TV pitch [rad] | TV yaw [rad] | mean lin. acc [m/s²] | change | "
             "mean ang. acc [rad/s²] | change |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        base = nominal.get(r["speed"])
        lin = f"{r['mean_linear_acc']['mean'] / base['mean_linear_acc']['mean'] - 1.0:+.0%}" if base else "-"
        ang = f"{r['mean_angular_acc']['mean'] / base['mean_angular_acc']['mean'] - 1.0:+.0%}" if base else "-"
        lines.append(f"| {_name(r)} | {r['speed']:g} | {fmt(r['total_variation_roll'])} | "
                     f"{fmt(r['total_variation_pitch'])} | {fmt(r['total_variation_yaw'])} | "
                     f"{fmt(r['mean_linear_acc'], 2)} | {lin} | {fmt(r['mean_angular_acc'], 2)} | {ang} |")
    return lines


def markdown_report(rows: list[dict], title: str, device: str, notes: str = "") -> str:
    """Tables II/III at each operating point (the paper's label, then its pace), then Fig. 6's smoothness."""
    lines = [f"# {title}", "", f"Device: {device}. Mean ± 2σ over the laps of each cell; the paper's figures "
             "(FlightGoggles, 10 races per cell at its 14 m/s label) beside ours at both operating points. "
             "**paper** is the `paper` preset (the paper's L1 cost, DOF and weights), **best** the `best` preset. "
             "In view: the share of flight time with the target gate in the image; angle to target: the mean angle "
             "between the optical axis and the gate's centre. Time below 50 % and at 0 % counts every tick a gate is "
             "the target, from the tick the previous gate is passed; the paper's rule (only after the gate was first "
             "seen while being the target, as the paper counts) stands beside it for the comparison with the paper's "
             "figures only. Avoidable: time below 50 % visibility less the part no attitude avoids (capped per gate "
             "at the ticks the target speed needs to fly through it); frontier gain: nominal MPPI flown slower at "
             "the cell's lap time over the cell's avoidable time, with its 90 % bootstrap interval "
             "(`frontier.gain_interval`).", ""]
    if notes:
        lines += [notes, ""]
    for point, speed in OPERATING_POINTS.items():
        point_rows = [r for r in rows if r["speed"] == speed]
        if not point_rows:
            continue
        what = ("the paper's label" if point == "label" else
                f"the paper's pace (our nominal lap matches the paper's {PAPER_NOMINAL_LAP_S[LABEL_SPEED]:g} s)")
        lines += [f"## At {speed:g} m/s: {what}", "", *_point_table(point_rows), ""]
    if rows:
        lines += ["## Fig. 6 with ground truth: total variation of the attitude, mean accelerations", "",
                  *_smoothness_table(rows), "",
                  f"The paper reports a {PAPER_ACCELERATION_CHANGE:+.0%} change in mean linear and angular "
                  "acceleration for PixelMPC against nominal MPPI (change: against nominal MPPI at the same target)."]
    wall = sum(r["wall_time_s"] or 0.0 for r in rows)
    lines += ["", f"Wall time of the cells flown here (cells shared with another part count there): {wall / 60:.1f} "
              "min."]
    return "\n".join(lines) + "\n"


def plot_visibility(rows: list[dict], path: Path, title: str) -> None:
    """Tables II/III as bars, one group per operating point: the time below 50 % and at 0 % under this measure
    (from the target) and under the paper's rule (after first seen) beside the paper's, and the lap time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    labels = [f"{_name(r).strip('*')}\n{r['speed']:g} m/s" if r["preset"] or r["c_pixel"] == 0 else
              f"tf={r['t_f']:g} c={r['c_pixel']:.0e}\n{r['speed']:g} m/s" for r in rows]
    x = np.arange(len(rows))
    panels = ((("time_vis_below_50_s", "time_vis_below_50_after_seen_s"), PAPER_VIS_BELOW_50,
               "time with visibility < 50 % [s]"),
              (("time_vis_zero_s", "time_vis_zero_after_seen_s"), PAPER_VIS_ZERO, "time with visibility = 0 % [s]"),
              (("lap_time_s",), PAPER_LAP_TIME, "lap time [s]"))
    for ax, (keys, paper, name) in zip(axes, panels):
        width = 0.8 / (len(keys) + 1)
        for k, (key, label) in enumerate(zip(keys, ("ours, from the target", "ours, the paper's rule"))):
            ours = [r[key]["mean"] or 0.0 for r in rows]
            err = [r[key]["two_sigma"] or 0.0 for r in rows]
            ax.bar(x - 0.4 + (k + 0.5) * width, ours, width, yerr=err, capsize=3,
                   label=label if len(keys) > 1 else "ours")
        theirs = [(paper.get((r["t_f"], r["c_pixel"])) if r["preset"] != "best" else None) or (np.nan, 0.0)
                  for r in rows]
        ax.bar(x + 0.4 - 0.5 * width, [t[0] for t in theirs], width, yerr=[t[1] for t in theirs],
               label="paper (14 m/s, its rule)" if len(keys) > 1 else "paper (14 m/s)", capsize=3, alpha=0.6,
               color="tab:green")
        ax.set_xticks(x, labels, fontsize=6, rotation=90)
        ax.set_title(name, fontsize=10)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_smoothness(rows: list[dict], path: Path, title: str = "Fig. 6: total variation of the attitude per lap "
                    "(mean ± 2σ)") -> None:
    """Fig. 6: the total variation of roll, pitch and yaw per lap, one bar per cell."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / max(len(rows), 1)
    for i, r in enumerate(rows):
        means = [r[f"total_variation_{a}"]["mean"] for a in ("roll", "pitch", "yaw")]
        errs = [r[f"total_variation_{a}"]["two_sigma"] for a in ("roll", "pitch", "yaw")]
        label = r.get("label") or f"{_name(r).strip('*')} {r['speed']:g} m/s"
        ax.bar(np.arange(3) + i * width, means, width, yerr=errs, capsize=2, label=label)
    ax.set_xticks(np.arange(3) + 0.4 - width / 2, ["roll", "pitch", "yaw"])
    ax.set_ylabel("total variation [rad]")
    ax.set_title(title)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# The paper's main cell (its best: t_f 1 s, c_pixel 9e6, the ``paper`` preset) as the one point of the grid.
MAIN_T_F, MAIN_C_PIXEL = (1.0,), (9e6,)


def table_cells(pixel_model: str = "dof", quick: bool = False, main: bool = False) -> list[Cell]:
    """The cells of Tables II/III at both operating points (``main``: nominal, ``paper`` and ``best`` only;
    ``quick``: those at the pace only)."""
    if quick:
        pace = OPERATING_POINTS["pace"]
        return visibility_cells(pixel_model, pace, t_f_values=MAIN_T_F, c_pixel_values=MAIN_C_PIXEL)
    grid_point = {"t_f_values": MAIN_T_F, "c_pixel_values": MAIN_C_PIXEL} if main else {}
    return [cell for speed in OPERATING_POINTS.values() for cell in visibility_cells(pixel_model, speed, **grid_point)]


def _title(pixel_model: str) -> str:
    return f"Tables II-III and Fig. 6: visibility and lap time, PixelMPC ({pixel_model} pixel model)"


def tables_report(rows: list[dict], missing: list[str], pixel_model: str = "dof") -> str:
    """REPORT.md of the rows (:func:`markdown_report`), with the calibration note and the cells not yet run."""
    notes = CALIBRATION_NOTE
    if missing:
        notes += f"\n\nNot yet run (the grid resumes with them): {', '.join(missing)}."
    return markdown_report(rows, _title(pixel_model), device_line(), notes=notes)


def tables_figures(rows: list[dict], out: Path, pixel_model: str = "dof") -> str:
    """Draw ``visibility.png`` and ``smoothness.png`` (none without rows); returns the report's links to them."""
    if not rows:
        return ""
    plot_visibility(rows, out / "visibility.png", _title(pixel_model))
    plot_smoothness(rows, out / "smoothness.png")
    return "\n![visibility and lap time](visibility.png)\n\n![Fig. 6](smoothness.png)\n"


def tables_experiment(cells: list[Cell], pixel_model: str = "dof", gains=None, also_flown=()) -> Experiment:
    """Tables II/III and Fig. 6 over ``cells`` as an experiment: one row per finished cell (:func:`summarise`, with
    the frontier gains ``gains(results)`` returns, None without them) in ``summary.json``, ``REPORT.md`` and
    ``visibility.png``, ``smoothness.png``. The cells ``also_flown`` (the frontier's nominal points) are flown into
    the same folder but make no row."""
    return Experiment(
        tuple(cells) + tuple(also_flown),
        summarise=lambda results: summarise(results, cells, gains(results) if gains else None),
        report=lambda rows, missing: tables_report(rows, missing, pixel_model),
        plot=lambda rows, out: tables_figures(rows, out, pixel_model), record=lambda rows: rows)


def visibility_experiment(out: Path, laps: int = 10, pixel_model: str = "dof", quick: bool = False,
                          progress: bool = True, dof_params=None, run: bool = True, seed: int = 0, reuse=(),
                          frontier_dir: Path | None = None, frontier_speeds=(), main: bool = False,
                          executor=None) -> list[dict]:
    """Tables II/III and Fig. 6 at the paper's label and its pace (``pixel_model="projection"`` for the PAMPC-style
    comparison; ``main``: the paper's main cell only, :func:`table_cells`), laps from ``seed``, flown and written by
    :func:`~pixelmpc_jax.apps.experiments.skeleton.run`. Cells a folder in ``reuse`` already holds are copied, not
    flown. The frontier gains are read against nominal MPPI at ``frontier_speeds`` in ``frontier_dir`` (flown with
    the same laps and seed); with ``frontier_speeds`` and no ``frontier_dir``, those points are flown into ``out``
    itself; no gains without either. With ``run=False`` only the report of the cells already finished in ``out`` is
    written.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    cells = table_cells(pixel_model, quick, main)
    names = {cell.name for cell in cells}
    also_flown = () if frontier_dir else tuple(nominal_cell(v) for v in frontier_speeds
                                               if nominal_cell(v).name not in names)
    gains_dir = frontier_dir if frontier_dir else (out if frontier_speeds else None)

    def gains(results: dict) -> dict:
        return gains_against(results, cells, gains_dir, frontier_speeds, laps, seed)

    experiment = tables_experiment(cells, pixel_model, gains if gains_dir else None, also_flown)
    return skeleton.run(experiment, out, laps, seed, progress, dof_params, reuse, flies=run, executor=executor)
