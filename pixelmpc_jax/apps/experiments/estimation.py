"""The paper's state-estimation experiments (Section V-D): Table IV, the straight-lane test, Fig. 6 and Fig. 9.

With the particle filter in the loop (``estimator="pf"``: the controllers act on its mean, fed by the IMU
and the detections of the target gate), nominal MPPI against PixelMPC, at two operating points (Table IV also on the
error-state Kalman filter's estimate, ``estimator="eskf"``, beside the paper's filter, and on the onboard loop,
``"onboard"``: the image detector and the ESKF, :data:`~pixelmpc_jax.apps.racing.presets.LOOPS`):

- the paper's labels (14 and 16 m/s): nominal MPPI and the ``paper`` preset (t_f = 1 s, c_pixel = 9e6);
- the paper's pace (the targets at which our nominal lap matches the paper's, ``presets.PAPER_PACE_SPEEDS``):
  nominal MPPI and both presets;

and measures

- Table IV: success rate, lap time of the successful laps and the failure modes over 25 laps;
- the straight lane at 20 m/s and its pace: the maximum trace of the filter's position covariance over 25 runs;
- Fig. 6 with the filter: the total variation of the attitude; Fig. 9: the trajectories, coloured by that covariance.

Each part writes ``results.json`` (every lap, resumable cell by cell), ``summary.json``, ``REPORT.md`` (ours
beside the paper's figures) and PNG figures into its output directory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.experiments.skeleton import Experiment, failure_counts
from pixelmpc_jax.apps.racing.grid import Cell, fmt
from pixelmpc_jax.apps.racing.presets import LOOPS as RACE_LOOPS
from pixelmpc_jax.apps.racing.presets import PAPER_LABEL_SPEEDS, pace_speed, preset, with_loop
from pixelmpc_jax.platform_info import device_line

# Table IV of the paper: (success rate, lap time mean, lap time 2 sigma) per (controller, target speed).
PAPER_TABLE_IV = {("mppi", 14.0): (0.80, 31.8, 0.7), ("pixelmpc", 14.0): (0.80, 33.0, 0.8),
                  ("mppi", 16.0): (0.52, 29.6, 0.8), ("pixelmpc", 16.0): (0.60, 30.6, 0.7)}
PAPER_SIGMA_MAX = {"mppi": 9.2, "pixelmpc": 5.7}  # straight lane, 20 m/s
RACE_LABELS = PAPER_LABEL_SPEEDS[:2]  # 14 and 16 m/s
STRAIGHT_LABEL = PAPER_LABEL_SPEEDS[2]  # 20 m/s
WHO = ("mppi", "paper", "best")  # nominal MPPI and the two presets


ESTIMATORS = ("pf", "eskf")  # Table IV's filters by default: the paper's particle filter, the error-state Kalman filter
# and the loops Table IV can fly: each filter with the clipped detector, and the onboard loop (the image detector and
# the ESKF, presets.LOOPS["onboard"])
LOOPS = ESTIMATORS + ("onboard",)
ESTIMATOR_NAMES = {"pf": "particle filter", "eskf": "ESKF", "onboard": "onboard loop"}


def _race(who: str, speed: float, estimator: str = "pf", **changes):
    """Nominal MPPI (at the ``paper`` preset's MPPI settings) or a preset, at ``speed``, on the filter (``"onboard"``:
    on the onboard loop)."""
    spec = preset("paper" if who == "mppi" else who)
    spec = with_loop(spec, "onboard") if estimator == "onboard" else spec.replace(estimator=estimator)
    spec = spec.replace(speed=speed, **changes)
    return spec.replace(controller="mppi") if who == "mppi" else spec


def _points(labels, quick: bool, who: tuple = WHO, at_labels: bool = True) -> list[tuple[float, float, tuple]]:
    """(label, our target, who flies it): each label's pace (all three), then each label as the paper named it
    (nominal and ``paper``; not without ``at_labels``), the fastest label first; ``quick``: the pace of the fastest
    label only. Only the controllers of ``who`` (of :data:`WHO`) fly."""
    unknown = [name for name in who if name not in WHO]
    if unknown:
        raise ValueError(f"unknown controller {unknown[0]!r}; Table IV flies {', '.join(WHO)}")
    labels = sorted(labels, reverse=True)
    paces = [(label, pace_speed(label), WHO) for label in labels[:1 if quick else None]]
    points = paces if quick or not at_labels else paces + [(label, label, WHO[:2]) for label in labels]
    return [(label, speed, tuple(name for name in whos if name in who)) for label, speed, whos in points]


def race_cells(labels=RACE_LABELS, quick: bool = False, estimators: tuple = ("pf",), who: tuple = WHO,
               at_labels: bool = True) -> list[Cell]:
    """Table IV's cells on each loop of ``estimators`` (of :data:`LOOPS`), per operating point, for the controllers
    of ``who``; without ``at_labels`` at the paces only."""
    unknown = [e for e in estimators if e not in LOOPS]
    if unknown:
        raise ValueError(f"unknown estimator {unknown[0]!r}; Table IV flies {', '.join(LOOPS)}")
    return [Cell(f"{name}_{speed:g}ms_{estimator}", _race(name, speed, estimator))
            for estimator in estimators for label, speed, whos in _points(labels, quick, who, at_labels)
            for name in whos]


def loop_of(cell: Cell) -> str:
    """The loop of :data:`LOOPS` a Table IV cell flies: ``"onboard"`` where its race flies every setting of the
    onboard loop, else its filter."""
    onboard = all(getattr(cell.spec, field) == value for field, value in RACE_LOOPS["onboard"].items())
    return "onboard" if onboard else cell.spec.estimator


def straight_cells(label: float = STRAIGHT_LABEL, quick: bool = False, who: tuple = WHO) -> list[Cell]:
    """The straight lane (five gates 20 m apart) with the filter, at the label and its pace."""
    return [Cell(f"{name}_straight_{speed:g}ms_pf", _race(name, speed, course="straight", max_time_s=20.0))
            for _, speed, whos in _points((label,), quick, who) for name in whos]


def label_of(cell: Cell) -> float:
    """The paper's label a cell answers: its own target, or the label whose pace it flies."""
    from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEEDS

    return next((label for label, pace in PAPER_PACE_SPEEDS.items() if pace == cell.spec.speed), cell.spec.speed)


def who_of(cell: Cell) -> str:
    return cell.name.split("_", 1)[0]


def _view(agg: dict) -> dict:
    keys = ("share_target_in_view", "mean_target_angle_deg", "time_vis_below_50_s", "time_vis_zero_s",
            "total_variation_roll", "total_variation_pitch", "total_variation_yaw")
    return {key: agg.get(key) for key in keys}


def summarise(results: dict, cells: list[Cell]) -> list[dict]:
    """One row per finished cell: success, lap time, failure modes, covariance maxima, the view; the paper's
    figures at the cell's label (``paper`` preset against the paper's PixelMPC)."""
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
        who, label = who_of(cell), label_of(cell)
        paper = PAPER_TABLE_IV.get(("mppi" if who == "mppi" else "pixelmpc", label))  # the paper's PixelMPC for both
        rms = [lap["rms_position_error_m"] ** 2 for lap in laps if lap.get("rms_position_error_m") is not None]
        rows.append({
            "cell": cell.name, "who": who, "controller": cell.spec.controller, "speed": cell.spec.speed,
            "estimator": loop_of(cell),
            "label": label, "point": "label" if label == cell.spec.speed else "pace", "course": cell.spec.course,
            "success_rate": res["aggregate"]["success_rate"], "num_laps": len(laps),
            "lap_time_s": res["aggregate"]["lap_time_s"], "gates_passed": res["aggregate"]["gates_passed"],
            "failures": failure_counts(laps), **_view(res["aggregate"]),
            "sigma_max": {"mean": float(maxima.mean()), "two_sigma": float(2 * maxima.std()),
                          "max": float(maxima.max()), "n": int(maxima.size)} if maxima.size else None,
            "mean_position_error_m": float(errors.mean()) if errors.size else None,
            "rms_position_error_m": float(np.sqrt(np.mean(rms))) if rms else None,
            "wall_time_s": res.get("wall_time_s"),
            "paper": {"success_rate": paper[0], "lap_time_s": paper[1:]} if paper else
            {"sigma_max": PAPER_SIGMA_MAX.get("mppi" if who == "mppi" else "pixelmpc")
             if cell.spec.course == "straight" else None},
        })
    return rows


NAMES = {"mppi": "nominal MPPI", "paper": "PixelMPC, `paper`", "best": "PixelMPC, `best`"}


def _race_line(r: dict) -> str:
    paper = r["paper"]
    failures = ", ".join(f"{k}: {v}" for k, v in sorted(r["failures"].items(), key=lambda kv: str(kv[0]))) or "-"
    error = f"{r['mean_position_error_m']:.2f}" if r["mean_position_error_m"] is not None else "-"
    rms = f"{r['rms_position_error_m']:.3f}" if r.get("rms_position_error_m") is not None else "-"
    view = r["share_target_in_view"] or {}
    in_view = f"{100 * view['mean']:.1f}" if view.get("mean") is not None else "-"
    theirs = (f"{paper['success_rate'] * 100:.0f}% | {paper['lap_time_s'][0]:.1f} ± {paper['lap_time_s'][1]:.1f}"
              if paper.get("success_rate") is not None else "- | -")
    succeeded = round(r["success_rate"] * r["num_laps"])
    estimator = ESTIMATOR_NAMES.get(r.get("estimator", "pf"), r.get("estimator"))
    return (f"| {NAMES[r['who']]} | {estimator} | {r['label']:g} m/s | {r['speed']:g} m/s | "
            f"{succeeded}/{r['num_laps']} "
            f"({r['success_rate'] * 100:.0f}%) | {theirs.split(' | ')[0]} | {fmt(r['lap_time_s'])} | "
            f"{theirs.split(' | ')[1]} | {failures} | {fmt(r['time_vis_below_50_s'])} | {in_view} | "
            f"{fmt(r['mean_target_angle_deg'])} | {error} | {rms} |")


def _straight_lines(rows: list[dict]) -> list[str]:
    lines = ["", "## Straight lane: maximum position covariance (trace, m²) per run", "",
             "| controller | label | target | Σ_max ours, mean ± 2σ of the runs' maxima | largest of all runs | "
             "paper Σ_max (20 m/s) | runs completed |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        sm = r["sigma_max"] or {}
        theirs = r["paper"].get("sigma_max")
        lines.append(f"| {NAMES[r['who']]} | {r['label']:g} m/s | {r['speed']:g} m/s | "
                     f"{sm.get('mean', float('nan')):.2f} ± {sm.get('two_sigma', float('nan')):.2f} | "
                     f"{sm.get('max', float('nan')):.2f} | {theirs if theirs is not None else '-'} | "
                     f"{round(r['success_rate'] * r['num_laps'])}/{r['num_laps']} |")
    return lines


def _smoothness_lines(rows: list[dict]) -> list[str]:
    lines = ["", "## Fig. 6 with the filter: total variation of the attitude per lap", "",
             "| controller | filter | target | TV roll [rad] | TV pitch [rad] | TV yaw [rad] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {NAMES[r['who']]} | {ESTIMATOR_NAMES[r['estimator']]} | {r['speed']:g} m/s | "
                     f"{fmt(r['total_variation_roll'])} | "
                     f"{fmt(r['total_variation_pitch'])} | {fmt(r['total_variation_yaw'])} |")
    return lines + ["", "The same figures with ground truth are in the Tables II-III part."]


def markdown_report(race_rows: list[dict], straight_rows: list[dict], device: str) -> str:
    lines = ["# Table IV, the straight lane, Fig. 6 and Fig. 9: racing on a filter's estimate", "",
             f"Device: {device}. Controllers act on the filter's mean: the paper's particle filter (6,400 particles, "
             "IMU motion update, gate-corner sensor update) and, in Table IV, the error-state Kalman filter (ESKF: "
             "IMU propagation with bias states, a gated, robustly weighted update per gate corner); on the onboard "
             "loop the ESKF is fed by the image detector (each tick's frame rendered and searched by OpenCV). On every "
             "loop the controller's target moves on when the estimate crosses the map's gate plane. At each paper "
             "label (14, 16 m/s) nominal MPPI and the `paper` preset fly "
             "the label itself and, with the `best` preset, its pace (the target at which our nominal lap matches "
             "the paper's). Lap times are over the successful laps, mean ± 2σ; vis < 50 %, in view (share of flight "
             "time with the target in the image) and the angle to the target over all laps. The paper's figures "
             "(FlightGoggles, 25 laps, its PixelMPC t_f = 1 s, c_pixel = 9e6) beside ours at the label they answer.",
             "", "| controller | filter | label | target | success ours | paper | lap time [s] ours | paper | "
             "failures | vis < 50 % [s] | in view [%] | angle to target [deg] | mean position error [m] | "
             "RMS position error [m] |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [_race_line(r) for r in race_rows]
    if straight_rows:
        lines += _straight_lines(straight_rows)
    if race_rows:
        lines += _smoothness_lines(race_rows)
    lines += ["", "Fig. 9: `fig9_<cell>.png`, the trajectories of each cell coloured by the trace of the filter's "
              "position covariance."]
    wall = sum(r["wall_time_s"] or 0.0 for r in race_rows + straight_rows)
    lines += ["", f"Wall time of the cells flown here: {wall / 60:.1f} min."]
    return "\n".join(lines) + "\n"


def plot_fig9(out: Path, cells: list[Cell]) -> list[Path]:
    """One top-down figure per cell: its trajectories coloured by the position covariance trace."""
    from pixelmpc_jax.apps.racing.race import plot_coloured_trajectories
    from pixelmpc_jax.world.course import make_course

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
        plot_coloured_trajectories(make_course(cell.spec.course), trajectories, path,
                                   title=f"{cell.spec.controller} with the {ESTIMATOR_NAMES[loop_of(cell)]}, "
                                         f"{cell.spec.speed:g} m/s, {len(trajectories)} runs", colour_by=colours,
                                   colour_label="position covariance trace [m²]")
        written.append(path)
    return written


def estimation_report(summary: dict, missing: list[str]) -> str:
    """REPORT.md of the summary (:func:`markdown_report`) and the cells not yet run."""
    report = markdown_report(summary["table_iv"], summary["straight_lane"], device_line())
    if missing:
        report += f"\nNot yet run (the experiment resumes with them): {', '.join(missing)}.\n"
    return report


def estimation_figures(summary: dict, out: Path, cells: list[Cell]) -> str:
    """Draw Fig. 6 with the filter (``fig6_pf.png``, with race rows) and Fig. 9 of ``cells``; returns the report's
    links to them."""
    from pixelmpc_jax.apps.experiments.paper import plot_smoothness

    text = ""
    race_rows = summary["table_iv"]
    if race_rows:
        plot_smoothness([{**r, "label": f"{NAMES[r['who']].replace('`', '')} {r['speed']:g} m/s"
                                         f"{'' if r['estimator'] == 'pf' else ', ' + ESTIMATOR_NAMES[r['estimator']]}"}
                         for r in race_rows],
                        out / "fig6_pf.png", "Fig. 6 with the filter: total variation of the attitude per lap "
                        "(mean ± 2σ)")
        text += "\n![Fig. 6 with the filter](fig6_pf.png)\n"
    return text + "".join(f"\n![{path.stem}]({path.name})\n" for path in plot_fig9(out, cells))


def estimation_experiment(out: Path, laps: int = 25, quick: bool = False, progress: bool = True,
                          dof_params=None, straight: bool = True, run: bool = True, seed: int = 0,
                          reuse=(), estimators: tuple = ESTIMATORS, who: tuple = WHO, at_labels: bool = True,
                          labels: tuple = RACE_LABELS, executor=None) -> dict:
    """Table IV at the labels and the paces (``quick``: the 16 m/s pace only), the straight lane, Fig. 6 and Fig. 9
    into ``out``, laps from ``seed``, flown and written by :func:`~pixelmpc_jax.apps.experiments.skeleton.run`;
    cells a folder in ``reuse`` holds are copied, not flown. With ``run=False`` only the report of the cells already
    finished in ``out`` is written. Table IV flies on each loop of ``estimators`` (of :data:`LOOPS`: a filter, or the
    onboard loop); the straight lane on the particle filter (the paper's figures it answers are the particle
    filter's). Table IV flies the paper's ``labels`` (of :data:`RACE_LABELS`) at their paces and, with ``at_labels``,
    at their own targets. Only the controllers of ``who`` fly: a run split over processes by controller or by label
    joins with ``reuse``.
    ``executor``: where the cells fly (:mod:`~pixelmpc_jax.apps.racing.executor`; None: in this process)."""
    cells = race_cells(labels, quick=quick, estimators=estimators, who=who, at_labels=at_labels)
    lanes = straight_cells(quick=quick, who=who) if straight else []
    experiment = Experiment(
        tuple(cells + lanes),
        summarise=lambda results: {"table_iv": summarise(results, cells), "straight_lane": summarise(results, lanes)},
        report=estimation_report, plot=lambda summary, folder: estimation_figures(summary, folder, cells + lanes),
        record=lambda summary: summary)
    return skeleton.run(experiment, out, laps, seed, progress, dof_params, reuse, flies=run, executor=executor)
