"""The paper's visibility experiments (Tables II and III, Fig. 8): grid, report, figures.

Each report writes ``results.json`` (every lap), ``summary.json`` (the tables' cells), ``REPORT.md``
(ours beside the paper's figures) and PNG figures into its output directory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.grid import Cell, fmt, load_results, run_grid
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import PixelMPCConfig
from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.strict_json import write_json_atomic

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
    "(`PixelMPCConfig.pixel_cost_scale`, `pixel_error_clip`). The paper's cost units are not recoverable, so "
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


def visibility_cells(pixel_model: str = "dof", speed: float = 14.0, t_f_values=T_F_VALUES,
                     c_pixel_values=C_PIXEL_VALUES) -> list[Cell]:
    """Nominal MPPI, then PixelMPC over the t_f x c_pixel grid."""
    cells = [Cell("mppi", RaceSpec(controller="mppi", speed=speed))]
    for t_f in t_f_values:
        for c_pixel in c_pixel_values:
            config = PixelMPCConfig(t_f=t_f, c_pixel=c_pixel, pixel_model=pixel_model)
            cells.append(Cell(f"pixelmpc_{pixel_model}_tf{t_f:g}_c{c_pixel:.0e}",
                              RaceSpec(controller="pixelmpc", config=config, speed=speed)))
    return cells


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


def summarise(results: dict, cells: list[Cell]) -> list[dict]:
    """One row per cell: our aggregates and the paper's figures."""
    rows = []
    for cell in cells:
        res = results.get(cell.name)
        if res is None:
            continue
        agg, spec = res["aggregate"], cell.spec
        rows.append({
            "cell": cell.name, **pixel_settings(spec),
            "success_rate": agg["success_rate"], "num_laps": agg["num_laps"],
            "time_vis_below_50_s": agg["time_vis_below_50_s"], "time_vis_zero_s": agg["time_vis_zero_s"],
            "lap_time_s": agg["lap_time_s"], "mean_linear_acc": agg["mean_linear_acc"],
            "mean_angular_acc": agg["mean_angular_acc"], "total_variation_roll": agg["total_variation_roll"],
            "total_variation_pitch": agg["total_variation_pitch"], "total_variation_yaw": agg["total_variation_yaw"],
            "wall_time_s": res.get("wall_time_s"),
            "paper": {"time_vis_below_50_s": PAPER_VIS_BELOW_50.get(_table_key(spec)),
                      "time_vis_zero_s": PAPER_VIS_ZERO.get(_table_key(spec)),
                      "lap_time_s": PAPER_LAP_TIME.get(_table_key(spec))},
        })
    return rows


def markdown_report(rows: list[dict], title: str, device: str, notes: str = "") -> str:
    lines = [f"# {title}", "", f"Device: {device}. Mean ± 2σ over the laps of each cell; the paper's figures "
             "(FlightGoggles, 10 races per cell at 14 m/s) beside ours.", ""]
    if notes:
        lines += [notes, ""]
    lines += ["| t_f [s] | c_pixel | vis < 50 % [s] ours | paper | vis = 0 % [s] ours | paper | lap time [s] ours "
              "| paper | success |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['t_f']:g} | {r['c_pixel']:.0e} | {fmt(r['time_vis_below_50_s'])} | "
            f"{_paper(PAPER_VIS_BELOW_50, r['t_f'], r['c_pixel'])} | {fmt(r['time_vis_zero_s'])} | "
            f"{_paper(PAPER_VIS_ZERO, r['t_f'], r['c_pixel'])} | {fmt(r['lap_time_s'])} | "
            f"{_paper(PAPER_LAP_TIME, r['t_f'], r['c_pixel'])} | {r['success_rate'] * 100:.0f}% of {r['num_laps']} |")
    nominal = next((r for r in rows if r["c_pixel"] == 0.0), None)
    if nominal:
        lines += ["", "## Fig. 8: smoothness (total variation of the attitude, mean accelerations)", "",
                  "| cell | TV roll [rad] | TV pitch [rad] | TV yaw [rad] | mean lin. acc [m/s²] | change | "
                  "mean ang. acc [rad/s²] | change |", "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lin = r["mean_linear_acc"]["mean"] / nominal["mean_linear_acc"]["mean"] - 1.0
            ang = r["mean_angular_acc"]["mean"] / nominal["mean_angular_acc"]["mean"] - 1.0
            lines.append(f"| {r['cell']} | {fmt(r['total_variation_roll'])} | {fmt(r['total_variation_pitch'])} | "
                         f"{fmt(r['total_variation_yaw'])} | {fmt(r['mean_linear_acc'], 2)} | {lin:+.0%} | "
                         f"{fmt(r['mean_angular_acc'], 2)} | {ang:+.0%} |")
        lines += ["", f"The paper reports a {PAPER_ACCELERATION_CHANGE:+.0%} change in mean linear and angular "
                  "acceleration for PixelMPC against nominal MPPI."]
    wall = sum(r["wall_time_s"] or 0.0 for r in rows)
    lines += ["", f"Wall time of the cells run: {wall / 60:.1f} min."]
    return "\n".join(lines) + "\n"


def plot_visibility(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    labels = ["MPPI" if r["c_pixel"] == 0 else f"tf={r['t_f']:g}\nc={r['c_pixel']:.0e}" for r in rows]
    x = np.arange(len(rows))
    for ax, key, paper, name in zip(axes, ("time_vis_below_50_s", "time_vis_zero_s", "lap_time_s"),
                                    (PAPER_VIS_BELOW_50, PAPER_VIS_ZERO, PAPER_LAP_TIME),
                                    ("time with visibility < 50 % [s]", "time with visibility = 0 % [s]",
                                     "lap time [s]")):
        ours = [r[key]["mean"] or 0.0 for r in rows]
        err = [r[key]["two_sigma"] or 0.0 for r in rows]
        theirs = [(paper.get((r["t_f"], r["c_pixel"])) or (np.nan, 0.0)) for r in rows]
        ax.bar(x - 0.2, ours, 0.4, yerr=err, label="ours", capsize=3)
        ax.bar(x + 0.2, [t[0] for t in theirs], 0.4, yerr=[t[1] for t in theirs], label="paper", capsize=3,
               alpha=0.6)
        ax.set_xticks(x, labels, fontsize=7)
        ax.set_title(name, fontsize=10)
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_smoothness(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.8))
    width = 0.8 / max(len(rows), 1)
    for i, r in enumerate(rows):
        means = [r[f"total_variation_{a}"]["mean"] for a in ("roll", "pitch", "yaw")]
        errs = [r[f"total_variation_{a}"]["two_sigma"] for a in ("roll", "pitch", "yaw")]
        label = "MPPI" if r["c_pixel"] == 0 else f"PixelMPC tf={r['t_f']:g} c={r['c_pixel']:.0e}"
        ax.bar(np.arange(3) + i * width, means, width, yerr=errs, capsize=2, label=label)
    ax.set_xticks(np.arange(3) + 0.4 - width / 2, ["roll", "pitch", "yaw"])
    ax.set_ylabel("total variation [rad]")
    ax.set_title("Fig. 8: total variation of the attitude per lap (mean ± 2σ)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def visibility_report(out: Path, cells: list[Cell], results: dict, pixel_model: str = "dof") -> list[dict]:
    """Write summary.json, REPORT.md and the figures from the cells finished so far in ``results``."""
    out = Path(out)
    rows = summarise(results, cells)
    missing = [cell.name for cell in cells if cell.name not in results]
    title = f"Tables II-III and Fig. 8: visibility and lap time, PixelMPC ({pixel_model} pixel model)"
    notes = CALIBRATION_NOTE
    if missing:
        notes += f"\n\nNot yet run (the grid resumes with them): {', '.join(missing)}."
    write_json_atomic(out / "summary.json", rows)
    (out / "REPORT.md").write_text(markdown_report(rows, title, device_line(), notes=notes))
    if rows:
        plot_visibility(rows, out / "visibility.png", title)
        plot_smoothness(rows, out / "smoothness.png")
        with open(out / "REPORT.md", "a") as report:
            report.write("\n![visibility and lap time](visibility.png)\n\n![Fig. 8](smoothness.png)\n")
    return rows


def visibility_experiment(out: Path, laps: int = 10, pixel_model: str = "dof", quick: bool = False,
                          progress: bool = True, dof_params=None, run: bool = True) -> list[dict]:
    """Tables II/III and Fig. 8 (``pixel_model="projection"`` for the PAMPC-style comparison); with
    ``run=False`` only the report of the cells already finished in ``out`` is written."""
    out = Path(out)
    cells = visibility_cells(pixel_model)
    if quick:
        cells = [cells[0], cells[3]]  # nominal and the paper's best setting (t_f = 1, c_pixel = 9e6)
    if run:
        try:
            results = run_grid(cells, out, laps=laps, progress=progress, dof_params=dof_params)
        except KeyboardInterrupt:
            visibility_report(out, cells, load_results(out), pixel_model)  # the finished cells' report
            raise
    else:
        results = load_results(out)
    return visibility_report(out, cells, results, pixel_model)
