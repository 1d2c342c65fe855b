"""The paper's state-estimation experiments (Section V-D): Table IV, the straight-lane test, Fig. 9.

With the particle filter in the loop (``estimator="pf"``: the controllers act on its mean, fed by the IMU
and the detections of the target gate), nominal MPPI and PixelMPC (t_f = 1 s, c_pixel = 9e6):

- Table IV: success rate and lap time of the successful laps over 25 laps at 14 and 16 m/s;
- the straight lane at 20 m/s: the maximum trace of the filter's position covariance over 25 runs;
- Fig. 9: the trajectories, coloured by that covariance.

Each part writes ``results.json`` (every lap, resumable cell by cell), ``summary.json``, ``REPORT.md`` (ours
beside the paper's figures) and PNG figures into its output directory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.grid import Cell, fmt, load_results, run_grid
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import PixelMPCConfig
from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.strict_json import write_json_atomic

# Table IV of the paper: (success rate, lap time mean, lap time 2 sigma) per (controller, target speed).
PAPER_TABLE_IV = {("mppi", 14.0): (0.80, 31.8, 0.7), ("pixelmpc", 14.0): (0.80, 33.0, 0.8),
                  ("mppi", 16.0): (0.52, 29.6, 0.8), ("pixelmpc", 16.0): (0.60, 30.6, 0.7)}
PAPER_SIGMA_MAX = {"mppi": 9.2, "pixelmpc": 5.7}  # straight lane, 20 m/s
CONTROLLERS = ("mppi", "pixelmpc")
RACE_SPEEDS = (14.0, 16.0)
PAPER_BEST_CELL = PixelMPCConfig(t_f=1.0, c_pixel=9e6)  # the paper's PixelMPC of Table IV
STRAIGHT_SPEED = 20.0


def race_cells(speeds=RACE_SPEEDS) -> list[Cell]:
    """Nominal MPPI and PixelMPC (the paper's t_f = 1, c_pixel = 9e6) with the filter, per speed."""
    return [Cell(f"{controller}_{speed:g}ms_pf", RaceSpec(controller=controller, config=PAPER_BEST_CELL, speed=speed,
                                                          estimator="pf"))
            for speed in speeds for controller in CONTROLLERS]


def straight_cells(speed: float = STRAIGHT_SPEED) -> list[Cell]:
    """Both controllers with the filter on the straight lane (five gates 20 m apart)."""
    return [Cell(f"{controller}_straight_{speed:g}ms_pf",
                 RaceSpec(controller=controller, config=PAPER_BEST_CELL, speed=speed, estimator="pf",
                          course="straight", max_time_s=20.0)) for controller in CONTROLLERS]


def summarise(results: dict, cells: list[Cell]) -> list[dict]:
    rows = []
    for cell in cells:
        res = results.get(cell.name)
        if res is None:
            continue
        laps = res["laps"]
        maxima = np.asarray([lap["max_position_cov_trace"] for lap in laps if lap.get("max_position_cov_trace")
                             is not None])
        errors = np.asarray([lap["mean_position_error_m"] for lap in laps if lap.get("mean_position_error_m")
                             is not None])
        crashes: dict = {}
        for lap in laps:
            if not lap["success"]:
                crashes[lap["crash"]] = crashes.get(lap["crash"], 0) + 1
        paper = PAPER_TABLE_IV.get((cell.spec.controller, cell.spec.speed))
        rows.append({
            "cell": cell.name, "controller": cell.spec.controller, "speed": cell.spec.speed, "course": cell.spec.course,
            "success_rate": res["aggregate"]["success_rate"], "num_laps": len(laps),
            "lap_time_s": res["aggregate"]["lap_time_s"], "gates_passed": res["aggregate"]["gates_passed"],
            "failures": crashes,
            "sigma_max": {"mean": float(maxima.mean()), "two_sigma": float(2 * maxima.std()),
                          "max": float(maxima.max()), "n": int(maxima.size)} if maxima.size else None,
            "mean_position_error_m": float(errors.mean()) if errors.size else None,
            "wall_time_s": res.get("wall_time_s"),
            "paper": {"success_rate": paper[0], "lap_time_s": paper[1:]} if paper else
            {"sigma_max": PAPER_SIGMA_MAX.get(cell.spec.controller)},
        })
    return rows


def markdown_report(race_rows: list[dict], straight_rows: list[dict], device: str) -> str:
    lines = ["# Table IV, the straight lane and Fig. 9: racing on the particle filter's estimate", "",
             f"Device: {device}. Controllers act on the filter's mean (6,400 particles, IMU motion update, "
             "gate-corner sensor update); PixelMPC with t_f = 1 s, c_pixel = 9e6. Lap times are over the "
             "successful laps, mean ± 2σ. The paper's figures (FlightGoggles, 25 laps) beside ours.", "",
             "| controller | target speed | success ours | paper | lap time [s] ours | paper | failures | "
             "mean position error [m] |", "|---|---|---|---|---|---|---|---|"]
    for r in race_rows:
        paper = r["paper"]
        failures = ", ".join(f"{k}: {v}" for k, v in sorted(r["failures"].items(), key=lambda kv: str(kv[0]))) or "-"
        error = f"{r['mean_position_error_m']:.2f}" if r["mean_position_error_m"] is not None else "-"
        lines.append(f"| {r['controller']} | {r['speed']:g} m/s | {r['success_rate'] * 100:.0f}% of {r['num_laps']} | "
                     f"{paper['success_rate'] * 100:.0f}% | {fmt(r['lap_time_s'])} | "
                     f"{paper['lap_time_s'][0]:.1f} ± {paper['lap_time_s'][1]:.1f} | {failures} | {error} |")
    if straight_rows:
        lines += ["", "## Straight lane, 20 m/s: maximum position covariance (trace, m²) per run", "",
                  "| controller | Σ_max ours, mean ± 2σ of the runs' maxima | largest of all runs | paper Σ_max | "
                  "runs completed |", "|---|---|---|---|---|"]
        for r in straight_rows:
            sm = r["sigma_max"] or {}
            lines.append(f"| {r['controller']} | {sm.get('mean', float('nan')):.2f} ± "
                         f"{sm.get('two_sigma', float('nan')):.2f} | {sm.get('max', float('nan')):.2f} | "
                         f"{PAPER_SIGMA_MAX[r['controller']]:.1f} | {r['success_rate'] * 100:.0f}% of "
                         f"{r['num_laps']} |")
    lines += ["", "Fig. 9: `fig9_<cell>.png`, the trajectories of each cell coloured by the trace of the filter's "
              "position covariance."]
    wall = sum(r["wall_time_s"] or 0.0 for r in race_rows + straight_rows)
    lines += ["", f"Wall time of the cells run: {wall / 60:.1f} min."]
    return "\n".join(lines) + "\n"


def plot_fig9(out: Path, cells: list[Cell]) -> list[Path]:
    """One top-down figure per cell: its trajectories coloured by the position covariance trace."""
    from pixelmpc_jax.apps.race import make_course, plot_trajectories

    written = []
    for cell in cells:
        traj_path, cov_path = out / f"trajectories_{cell.name}.npz", out / f"covariances_{cell.name}.npz"
        if not (traj_path.exists() and cov_path.exists()):
            continue
        trajectories = list(np.load(traj_path).values())
        covariances = list(np.load(cov_path).values())
        # states hold the start too: pad each covariance trace by its first value to match
        colours = [np.concatenate([c[:1], c]) if c.size else np.zeros(len(t)) for t, c in zip(trajectories,
                                                                                              covariances)]
        path = out / f"fig9_{cell.name}.png"
        plot_trajectories(make_course(cell.spec.course), trajectories, path,
                          title=f"{cell.spec.controller} with the particle filter, {cell.spec.speed:g} m/s, "
                                f"{len(trajectories)} runs", colour_by=colours,
                          colour_label="position covariance trace [m²]")
        written.append(path)
    return written


def estimation_experiment(out: Path, laps: int = 25, quick: bool = False, progress: bool = True,
                          dof_params=None, straight: bool = True, run: bool = True) -> dict:
    """Table IV (14 and 16 m/s; ``quick``: 16 m/s only), the straight lane and Fig. 9 into ``out``; with
    ``run=False`` only the report of the cells already finished in ``out`` is written."""
    out = Path(out)
    cells = race_cells((16.0,) if quick else RACE_SPEEDS)
    lanes = straight_cells() if straight else []
    interrupted = False
    if run:
        try:
            results = run_grid(cells + lanes, out, laps=laps, progress=progress, dof_params=dof_params)
        except KeyboardInterrupt:
            results = load_results(out)  # write the finished cells' report, then stop
            interrupted = True
    else:
        results = load_results(out)
    race_rows, straight_rows = summarise(results, cells), summarise(results, lanes)
    missing = [cell.name for cell in cells + lanes if cell.name not in results]
    report = markdown_report(race_rows, straight_rows, device_line())
    if missing:
        report += f"\nNot yet run (the experiment resumes with them): {', '.join(missing)}.\n"
    figures = plot_fig9(out, cells + lanes)
    report += "".join(f"\n![{path.stem}]({path.name})\n" for path in figures)
    write_json_atomic(out / "summary.json", {"table_iv": race_rows, "straight_lane": straight_rows})
    (out / "REPORT.md").write_text(report)
    if interrupted:
        raise KeyboardInterrupt(f"interrupted: {len(missing)} cell(s) not finished; run again to resume")
    return {"table_iv": race_rows, "straight_lane": straight_rows}
