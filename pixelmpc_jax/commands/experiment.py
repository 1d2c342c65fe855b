"""``pixelmpc experiment NAME``: one experiment on its own, resumable per cell (``pixelmpc reproduce`` runs the
paper's into one report): the paper's tables, the speed frontier, the robustness grid and the probes. The
``experiments/`` scripts call these jobs."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import re
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.apps.experiments.reproduce import SEED
from pixelmpc_jax.apps.racing.presets import LOOPS
from pixelmpc_jax.arguments import SEED_MAX
from pixelmpc_jax.control.pixelmpc import C_PIXEL_RANGE, T_F_RANGE
from pixelmpc_jax.settings import CAMERA_TILT_RANGE

# frontier --cells: both pixel costs and models, the border cost alone, the best preset beside the exact projection,
# the best preset beside its target's pixel from the detector for a gate cut by the image border, or none (nominal
# MPPI's points alone, for another run's --reuse)
FRONTIER_CELLS = ("all", "border", "preset", "partial", "none")
# the experiments that fly cells: each takes --executor/--workers, and a grid file may name each
FLYING = ("table2", "table4", "robustness", "fault-curves", "frontier", "margin-probe", "speed-probe")
GRID_FILE_REFUSED = ("executor", "workers")  # where the cells fly is the command line's, not the file's


def add_experiment(sub) -> None:
    """``pixelmpc experiment``: its jobs as sub-commands."""
    p = sub.add_parser("experiment", help="one experiment on its own, resumable: table2, table4, robustness, "
                                          "fault-curves, frontier, margin-probe, speed-probe; run flies a grid "
                                          "file's; lap-picture draws the laps of result folders; "
                                          "detector-agreement compares the detectors on their frames")
    jobs = p.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    for add in (_add_table2, _add_table4, _add_robustness, _add_fault_curves, _add_frontier, _add_margin_probe,
                _add_speed_probe, _add_lap_picture, _add_detector_agreement):
        add(jobs)
    for name in FLYING:
        _add_executor_flags(jobs.choices[name], default=None)
    _add_run(jobs)


def _engine(text: str) -> str:
    """An argparse type: where a grid's cells fly (:func:`~pixelmpc_jax.apps.racing.executor.make_executor`): local,
    dask-local:N, dask://HOST:PORT or tcp://HOST:PORT; a Dask engine only where dask's distributed is installed."""
    from pixelmpc_jax.apps.racing.executor import CLUSTER_EXTRA, parse_engine

    try:
        kind, _ = parse_engine(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    if kind != "local":
        import importlib.util

        if importlib.util.find_spec("distributed") is None:
            raise argparse.ArgumentTypeError(f"{text} needs dask's distributed scheduler: {CLUSTER_EXTRA}")
    return text


def _add_executor_flags(p, default: str | None) -> None:
    """``--executor`` and ``--workers``: where an experiment's cells fly (:mod:`pixelmpc_jax.apps.racing.executor`)."""
    in_process = "in this process, one after another" if default is None else "a pool of pinned local processes"
    p.add_argument("--executor", type=_engine, default=default, metavar="local|dask-local:N|dask://HOST:PORT",
                   help="where the cells fly: local, a pool of processes each pinned to a core of its own; "
                        "dask-local:N, a local Dask cluster of N workers; dask://HOST:PORT, a Dask scheduler's "
                        f"workers (Dask: pip install 'pixelmpc-jax[cluster]'). Default: {in_process}. This process "
                        "writes every finished cell, so a run resumes the same on any executor")
    p.add_argument("--workers", type=arg.positive_int, default=None, metavar="N",
                   help="processes of the local pool (default: one per usable core, at most one per cell; 1 flies "
                        "in this process)")


def _executor(args) -> dict:
    """``{"executor": the executor --executor / --workers name}`` for the experiment's function; empty when neither
    is given, so that a run without them calls the experiment as before executors (its cells in this process)."""
    if args.executor is None and args.workers is None:
        return {}
    from pixelmpc_jax.apps.racing.executor import make_executor

    return {"executor": make_executor(args.executor, args.workers)}


def _add_out(p, default: str | None, help: str) -> None:
    """``--out``: the output folder, ``default`` (a path) or required when None."""
    if default is None:
        p.add_argument("--out", type=arg.writable_dir, required=True, help=help)
    else:
        p.add_argument("--out", type=arg.writable_dir, default=Path(default), help=help)


def _add_report_only(p) -> None:
    p.add_argument("--report-only", action="store_true", help="write the report of the finished cells only")


def _print_report(out: Path) -> None:
    print((out / "REPORT.md").read_text())


def _add_table2(jobs) -> None:
    p = jobs.add_parser("table2", help="Tables II and III and Fig. 6: visibility, lap time and smoothness against "
                                       "nominal MPPI over the t_f x c_pixel grid, at the paper's 14 m/s label and its "
                                       "pace, with the best preset beside them (REPORT.md, summary.json, figures)")
    _add_out(p, "experiments/results/table2", "output directory")
    p.add_argument("--laps", type=arg.positive_int, default=10, help="laps per cell (default 10)")
    p.add_argument("--seed", type=arg.seed, default=SEED,
                   help=f"seed of the first lap, in [0, {SEED_MAX}] (default {SEED}, the reproduction's)")
    p.add_argument("--pixel-model", choices=("dof", "projection"), default="dof",
                   help="the grid's pixel model: dof (the paper's) or projection (PAMPC-style; default dof)")
    p.add_argument("--quick", action="store_true", help="nominal MPPI and the presets at the pace only")
    p.add_argument("--main", action="store_true",
                   help="the paper's main cell only (t_f 1 s, c_pixel 9e6: the paper preset) beside nominal MPPI and "
                        "the best preset, at both operating points, instead of the whole t_f x c_pixel grid")
    p.add_argument("--frontier-speeds", type=arg.target_speeds, nargs="*", default=(), metavar="M_S|LO:HI:STEP",
                   help="also fly nominal MPPI at these target speeds (each a speed or a range, as the frontier's "
                        "--speeds) into the same folder, same laps and seeds, and report each PixelMPC cell's "
                        "frontier gain against them (default: none, no gains)")
    p.set_defaults(func=_cmd_table2)


def _cmd_table2(args) -> int:
    from pixelmpc_jax.apps.experiments.paper import visibility_experiment

    visibility_experiment(args.out, laps=args.laps, pixel_model=args.pixel_model, quick=args.quick, seed=args.seed,
                          main=args.main, frontier_speeds=tuple(sorted({v for vs in args.frontier_speeds for v in vs})),
                          **_executor(args))
    _print_report(args.out)
    return 0


def _add_table4(jobs) -> None:
    from pixelmpc_jax.apps.experiments.estimation import ESTIMATORS, LOOPS, RACE_LABELS, WHO

    p = jobs.add_parser("table4", help="Table IV, the straight lane, Fig. 6 and Fig. 9: nominal MPPI against PixelMPC "
                                       "on a filter's estimate (REPORT.md, summary.json, figures)")
    _add_out(p, "experiments/results/table4", "output directory")
    p.add_argument("--laps", type=arg.positive_int, default=25, help="laps per cell (default 25)")
    p.add_argument("--seed", type=arg.seed, default=SEED,
                   help=f"seed of the first lap, in [0, {SEED_MAX}] (default {SEED}, the reproduction's)")
    p.add_argument("--quick", action="store_true", help="the 16 m/s pace only (and the straight lane's)")
    p.add_argument("--no-straight", action="store_true", help="skip the straight-lane test")
    p.add_argument("--paces-only", action="store_true",
                   help="Table IV at the labels' paces only (8.5 and 9.1 m/s), not at the labels' own targets")
    p.add_argument("--labels", nargs="+", type=float, choices=RACE_LABELS, default=RACE_LABELS, metavar="LABEL",
                   help="the paper's labels Table IV flies, at their paces and targets: 14 and 16 (m/s; default "
                        "both). A run split over processes by label joins with --reuse")
    p.add_argument("--estimators", nargs="+", choices=LOOPS, default=ESTIMATORS,
                   help="Table IV's loops: pf, the paper's particle filter, and eskf, the error-state Kalman filter, "
                        "each with the detector's report clipped at the image border (default: both); onboard, the "
                        "onboard loop (the image detector, the ESKF, the gate switch from the estimate, the "
                        "surveyed map). The straight lane flies the particle filter")
    p.add_argument("--controllers", nargs="+", choices=WHO, default=WHO,
                   help="fly and report only these: mppi (nominal MPPI), paper and best (the presets; default: all "
                        "three)")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="*", default=(), metavar="DIR",
                   help="grid folders (another Table IV run's) whose finished cells with the same race, laps and seed "
                        "are copied, not flown again: a run split over processes (by filter or by controller) joins "
                        "here")
    p.set_defaults(func=_cmd_table4)


def _cmd_table4(args) -> int:
    from pixelmpc_jax.apps.experiments.estimation import estimation_experiment

    estimation_experiment(args.out, laps=args.laps, quick=args.quick, straight=not args.no_straight, seed=args.seed,
                          estimators=tuple(args.estimators), reuse=tuple(args.reuse), who=tuple(args.controllers),
                          at_labels=not args.paces_only, labels=tuple(sorted(set(args.labels))),
                          **_executor(args))
    _print_report(args.out)
    return 0


def _add_robustness(jobs) -> None:
    from pixelmpc_jax.apps.experiments.robustness import CONTROLLERS, ESTIMATORS, FAULTS, LEVER_SETS
    from pixelmpc_jax.sim.faults import LEVELS

    p = jobs.add_parser("robustness", help="the faults of a real flight: nominal MPPI and the best preset at the "
                                           "paper's pace under each fault (REPORT.md, robustness.json, "
                                           "robustness.png)")
    _add_out(p, "experiments/results/robustness", "output directory")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run: 2 laps per cell, the moderate level (on the particle filter only unless "
                        "--estimators names others)")
    p.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=None,
                   help="fly and report only the loops on these estimators (default: all; pf only with --quick)")
    p.add_argument("--faults", nargs="+", choices=FAULTS, default=None,
                   help="fly and report only these faults (default: all, with none and combined)")
    p.add_argument("--levels", nargs="+", choices=LEVELS, default=None,
                   help="fly and report only these fault levels (default: both; the fault-free race is in each)")
    p.add_argument("--controllers", nargs="+", choices=CONTROLLERS, default=None,
                   help="fly and report only these controllers (default: both)")
    p.add_argument("--levers", nargs="*", choices=tuple(LEVER_SETS), default=None,
                   help="also fly the moderate cells with each set of levers on, apart: model (the disturbance "
                        "observer, the latency in the model; on every loop, both controllers), filter (the particle "
                        "filter's guards), gate and bias (the guards' two halves alone), robust (model and gate at "
                        "once); the guards on the particle filter and PixelMPC only; exact (the Kalman filter taking "
                        "the map as exact, its default before a surveyed map's accuracy), align (the Kalman filter "
                        "aligned on its IMU at rest before the lap), adapt (the Kalman filter's corner noise "
                        "following its innovations; also at the severe level) and model-adapt (model and adapt at "
                        "once) on the Kalman filter; no name: all")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="*", default=(), metavar="DIR",
                   help="other grids' output folders whose finished cells of the same race (the fault-free "
                        "ones, and any other flown the same) are copied, not flown")
    _add_report_only(p)
    p.set_defaults(func=_cmd_robustness)


def _cmd_robustness(args) -> int:
    from pixelmpc_jax.apps.experiments.robustness import LEVER_SETS, robustness_experiment

    levers = () if args.levers is None else tuple(args.levers or LEVER_SETS)
    robustness_experiment(args.out, quick=args.quick, levers=levers, reuse=args.reuse, run=not args.report_only,
                          estimators=tuple(args.estimators) if args.estimators else None,
                          faults=tuple(args.faults) if args.faults else None,
                          levels=tuple(args.levels) if args.levels else None,
                          controllers=tuple(args.controllers) if args.controllers else None, **_executor(args))
    _print_report(args.out)
    return 0


def _add_fault_curves(jobs) -> None:
    from pixelmpc_jax.apps.experiments.fault_curves import CURVES, DELAY_TICKS, ESTIMATORS, LAPS, WIND_M_S
    from pixelmpc_jax.apps.experiments.robustness import CONTROLLER_LEVERS

    p = jobs.add_parser("fault-curves", help="success against steady wind and detection delay: both controllers on "
                                             "the particle filter and the Kalman filter (REPORT.md, curves.json, "
                                             "fault_curves.png)")
    _add_out(p, "experiments/results/fault_curves", "output directory (resumable)")
    p.add_argument("--quick", action="store_true",
                   help=f"a smoke run: 2 laps per point, the middle and the end of each curve (default: {LAPS} laps "
                        f"at wind {', '.join(f'{w:g}' for w in WIND_M_S)} m/s and delay "
                        f"{', '.join(str(d) for d in DELAY_TICKS)} ticks)")
    p.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=ESTIMATORS,
                   help="the filters flown (default: both)")
    p.add_argument("--levers", nargs="*", choices=CONTROLLER_LEVERS, default=(),
                   help="also fly both controllers at every point with these levers on (model: the disturbance "
                        "observer)")
    p.add_argument("--curves", nargs="+", choices=tuple(CURVES), default=tuple(CURVES),
                   help="fly and report only these curves (default: both; the fault-free point is on each)")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="*", default=(), metavar="DIR",
                   help="grid folders (the robustness grid's) whose finished cells of the same race are copied")
    _add_report_only(p)
    p.set_defaults(func=_cmd_fault_curves)


def _cmd_fault_curves(args) -> int:
    from pixelmpc_jax.apps.experiments.fault_curves import fault_curves_experiment

    fault_curves_experiment(args.out, quick=args.quick, estimators=tuple(args.estimators),
                            levers=tuple(args.levers or ()), reuse=args.reuse, run=not args.report_only,
                            curves=tuple(args.curves), **_executor(args))
    _print_report(args.out)
    return 0


def _add_frontier(jobs) -> None:
    from pixelmpc_jax.world.course import COURSES

    p = jobs.add_parser("frontier", help="the speed frontier: PixelMPC's avoidable low-visibility time against "
                                         "nominal MPPI flown slower (frontier.json, REPORT.md, frontier.png)")
    _add_out(p, None, "output folder (resumable)")
    p.add_argument("--laps", type=arg.positive_int, default=None, help="laps per point (default 10; 4 with --quick)")
    p.add_argument("--seed", type=arg.seed, default=0,
                   help=f"first seed, in [0, {SEED_MAX}]; lap i uses seed + i (default 0)")
    p.add_argument("--quick", action="store_true", help="4 nominal speeds and the 2 border-cost cells, 4 laps")
    p.add_argument("--cells", choices=FRONTIER_CELLS, default="all",
                   help="PixelMPC cells: all (the paper's L1 and the border cost, both pixel models; default), "
                        "border (the border cost alone, at each model's weight of the 4-lap sweep), preset (the "
                        "best preset at the paper's pace and the exact projection flying its settings, the ceiling "
                        "of knowing where the gate is), partial (the best preset at the paper's pace and the same "
                        "race with its target's pixel from the detector while it reports the gate cut by the image "
                        "border, where the preset takes the map's); none flies nominal MPPI's points alone, to split "
                        "a frontier over processes (a last run with the cells and --reuse of each folder joins them)")
    p.add_argument("--speeds", type=arg.target_speeds, nargs="+", default=None, metavar="M_S|LO:HI:STEP",
                   help=f"nominal target speeds in m/s, in (0, {arg.TARGET_SPEED_MAX:g}], each a speed or a range "
                        "(6:9:0.25 flies 6, 6.25, ..., 9: a frontier without gaps for the paired gain; nominal "
                        "points already flown in --out are kept). At least 2; default 6 7 8 8.5 9.1 10 12 14, quick "
                        "6 8 8.5 10")
    p.add_argument("--course", type=arg.course, default=None, metavar="|".join(COURSES) + "|FILE",
                   help="the course every cell flies: a name or a course file (`pixelmpc course`; default "
                        "alphapilot)")
    p.add_argument("--camera-tilt", type=arg.float_range(CAMERA_TILT_RANGE), default=None,
                   metavar="DEG",
                   help=f"the camera tilted up on its mount by DEG degrees, in {CAMERA_TILT_RANGE.interval}, for every "
                        "cell, nominal MPPI's too (default: the cells' own, the paper's 0); the packaged learned pixel "
                        "models are trained for 0, so with a tilt only nominal MPPI's points (--cells none) fly as "
                        "they should")
    p.add_argument("--loop", choices=tuple(LOOPS), default=None,
                   help="the loop every cell flies, nominal MPPI's too: onboard, only what the drone has (the image "
                        "detector, the ESKF, the gate switch from the estimate, the surveyed map); truth, the "
                        "controller on the true state (default: the cells' own, the true state)")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="*", default=(), metavar="DIR",
                   help="grid folders (another frontier's, a tune validation's) whose finished cells with the same "
                        "race, laps and seed are copied, not flown again")
    p.set_defaults(func=_cmd_frontier, validate=_two_speeds, precheck=_check_course)


def _nominal_speeds(args) -> tuple[float, ...] | None:
    """The speeds of ``--speeds`` (each a speed or a range), sorted, each once; None when not given."""
    return None if args.speeds is None else tuple(sorted({v for speeds in args.speeds for v in speeds}))


def _two_speeds(args) -> str | None:
    if args.speeds is not None and len(_nominal_speeds(args)) < 2:
        return "argument --speeds: needs at least 2 different speeds to draw a frontier"
    return None


def _check_course(args) -> None:
    """A course file's bad field, named before anything runs."""
    if args.course is not None:
        from pixelmpc_jax.world.course import make_course

        make_course(args.course)


def _cmd_frontier(args) -> int:
    from pixelmpc_jax.apps.experiments import frontier

    spec = frontier.quick_spec() if args.quick else frontier.default_spec()
    changes = {}
    if args.cells == "border":
        changes["cells"] = frontier.border_cells()
    elif args.cells == "preset":
        from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEED

        changes["cells"] = frontier.ceiling_cells(PAPER_PACE_SPEED)
    elif args.cells == "partial":
        from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEED

        changes["cells"] = frontier.partial_target_cells(PAPER_PACE_SPEED)
    elif args.cells == "none":
        changes["cells"] = ()
    if args.speeds:
        changes["nominal_speeds"] = _nominal_speeds(args)
    if args.laps is not None:
        changes["laps"] = args.laps
    spec = dataclasses.replace(spec, **changes)
    frontier.run_frontier(spec.nominal_speeds, spec.cells, args.out, laps=spec.laps, seed=args.seed,
                          course=args.course, camera_tilt_deg=args.camera_tilt, reuse=tuple(args.reuse), loop=args.loop,
                          **_executor(args))
    _print_report(args.out)
    return 0


def _add_margin_probe(jobs) -> None:
    p = jobs.add_parser("margin-probe", help="the best preset's clearance to the gate frames against the vehicle's "
                                             "own, on the true state (the frontier) and on the filter (Table IV)")
    _add_out(p, None, "output folder (resumable)")
    p.add_argument("--frontier", type=arg.grid_dir, nargs="*", default=(), metavar="DIR",
                   help="grid folders (a frontier run's) whose nominal cells are copied, not flown again")
    p.add_argument("--seed", type=arg.seed, default=SEED,
                   help=f"the first lap's seed, in [0, {SEED_MAX}] (default {SEED}, the reproduction's)")
    p.set_defaults(func=_cmd_margin_probe)


def _cmd_margin_probe(args) -> int:
    from pixelmpc_jax.apps.experiments.margin_probe import margin_probe

    margin_probe(args.out, args.frontier, args.seed, **_executor(args))
    _print_report(args.out / "truth")
    _print_report(args.out / "pf")
    return 0


def _add_speed_probe(jobs) -> None:
    p = jobs.add_parser("speed-probe", help="what PixelMPC's visibility costs in lap time over pixel-cost weights at "
                                            "one target speed (REPORT.md, tradeoff.png)")
    p.add_argument("--speed", type=arg.target_speed, default=8.0,
                   help=f"target speed, m/s, in (0, {arg.TARGET_SPEED_MAX:g}] (default 8)")
    p.add_argument("--laps", type=arg.positive_int, default=4, help="laps per cell (default 4)")
    p.add_argument("--models", nargs="+", default=["projection", "dof"], choices=["projection", "dof"],
                   help="the pixel models of the PixelMPC cells (default projection dof)")
    p.add_argument("--c-pixel", type=arg.float_range(C_PIXEL_RANGE._replace(lo_open=True)), nargs="+", default=[9e6],
                   help=f"pixel cost weights, in {C_PIXEL_RANGE._replace(lo_open=True).interval} (default 9e6)")
    p.add_argument("--t-f", type=arg.float_range(T_F_RANGE._replace(lo_open=True)), default=1.0,
                   help=f"seconds of the horizon with the pixel cost, in {T_F_RANGE._replace(lo_open=True).interval} "
                        "(default 1)")
    p.add_argument("--dof-weights", type=arg.weights_file, default=None,
                   help="DOF weights file for the dof cells (default: the shipped weights)")
    _add_out(p, "runs/visibility_probe", "output directory")
    p.set_defaults(func=_cmd_speed_probe)


def _cmd_speed_probe(args) -> int:
    from pixelmpc_jax.apps.experiments.speed_probe import speed_probe

    speed_probe(args.out, speed=args.speed, laps=args.laps, models=tuple(args.models), c_pixels=tuple(args.c_pixel),
                t_f=args.t_f, dof_weights=args.dof_weights, **_executor(args))
    _print_report(args.out)
    return 0


def _add_lap_picture(jobs) -> None:
    p = jobs.add_parser("lap-picture", help="every lap of result folders (a frontier's or any grid's, a `pixelmpc race "
                                            "--out` comparison's): lap time against avoidable low-visibility time, "
                                            "one dot per lap, both controllers, every pace, beside the share of time "
                                            "in view (flies nothing)")
    p.add_argument("folders", type=arg.result_dir, nargs="+", metavar="DIR",
                   help="result folders: results.json (a grid's) or metrics.json (a race's)")
    p.add_argument("--out", type=arg.output_file, default=None, help="the PNG to write (default DIR/laps.png of the "
                                                                      "first folder)")
    p.set_defaults(func=_cmd_lap_picture)


def _cmd_lap_picture(args) -> int:
    from pixelmpc_jax.apps.experiments.lap_picture import write_lap_picture

    print(write_lap_picture(args.folders, args.out))
    return 0


def _add_detector_agreement(jobs) -> None:
    p = jobs.add_parser("detector-agreement", help="the geometric detector against the image detector on every frame "
                                                   "of flown laps (per-tick records, ticks_*.npz): found or not, and "
                                                   "the centres' distance, the gates partly out of view apart "
                                                   "(agreement.json, REPORT.md, agreement.png; flies nothing)")
    p.add_argument("ticks", type=arg.ticks_file, nargs="+", metavar="TICKS",
                   help="per-tick records of AlphaPilot races (ticks_*.npz, as a race or a grid writes them)")
    p.add_argument("--laps", type=arg.positive_int, default=1, help="laps of each record, from its first (default 1)")
    _add_out(p, None, "output folder")
    p.set_defaults(func=_cmd_detector_agreement)


def _cmd_detector_agreement(args) -> int:
    from pixelmpc_jax.apps.experiments import detector_agreement

    detector_agreement.run(args.ticks, args.laps, args.out)
    _print_report(args.out)
    return 0


def _add_run(jobs) -> None:
    p = jobs.add_parser("run", help="an experiment from a grid file (experiments/grids/*.toml: a named experiment "
                                    "and its options, or explicit cells), checked whole before anything flies; its "
                                    "cells fly on an executor, by default a pool of pinned processes, one per core")
    p.add_argument("grid", type=arg.grid_file, metavar="GRID", help="the grid file (TOML)")
    _add_executor_flags(p, default="local")
    p.add_argument("--out", type=arg.writable_dir, default=None,
                   help="output folder (resumable; default: the file's out, else the experiment's own default)")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="+", default=(), metavar="DIR",
                   help="grid folders whose finished cells of the same race, laps and seed are copied, not flown "
                        "(added to the file's own, where the experiment takes reuse)")
    p.set_defaults(func=_cmd_run, precheck=functools.partial(_check_grid_file, jobs=jobs))


def _check_grid_file(args, jobs) -> None:
    """Read the grid file and check all of it: a ValueError names the file and the first problem. A named
    experiment's options are parsed by that experiment's own parser into ``args.grid_args``."""
    from pixelmpc_jax.apps.racing.grid_file import CELLS, read_grid_file

    grid = read_grid_file(args.grid)
    args.grid_file, args.grid_args = grid, None
    if grid.experiment == CELLS:
        if (args.out or grid.out) is None:
            raise ValueError(f"grid file {grid.path}: it names no output folder: add out = \"...\" or give --out")
        return
    parser = jobs.choices[grid.experiment]
    try:
        args.grid_args = _parse_options(parser, grid, args)
    except ValueError as err:
        raise ValueError(f"grid file {grid.path}: {err}") from None
    args.grid_outputs = [getattr(args.grid_args, action.dest) for action in parser._actions
                         if action.type is arg.writable_dir and getattr(args.grid_args, action.dest, None) is not None]
    problem = args.grid_args.validate(args.grid_args) if getattr(args.grid_args, "validate", None) else None
    if problem:
        raise ValueError(f"grid file {grid.path}: {_option_names(problem)}")
    if getattr(args.grid_args, "precheck", None) is not None:
        args.grid_args.precheck(args.grid_args)


def _parse_options(parser: argparse.ArgumentParser, grid, args) -> argparse.Namespace:
    """A named experiment's options (the file's, with the command line's ``--out`` and ``--reuse``) parsed as its
    command's flags: ``laps = 4`` as ``--laps 4``, a list as several values, ``true`` as a switch."""
    flags = {action.dest: action for action in parser._actions if action.option_strings and action.dest != "help"}
    options = {key.replace("-", "_"): value for key, value in grid.options.items()}
    if args.out is not None:
        options["out"] = str(args.out)
    if args.reuse:
        if "reuse" not in flags:
            raise ValueError(f"--reuse: {grid.experiment} takes no reuse folders")
        reuse = options.get("reuse", [])
        options["reuse"] = [*(reuse if isinstance(reuse, list) else [reuse]), *map(str, args.reuse)]
    argv = []
    for key, value in options.items():
        if key in GRID_FILE_REFUSED:
            raise ValueError(f"{key} is where the cells fly: give --{key} on the command line, not in the file")
        action = flags.get(key)
        if action is None:
            raise ValueError(f"unknown key {key!r} for experiment {grid.experiment}; it takes "
                             f"{', '.join(sorted(set(flags) - set(GRID_FILE_REFUSED)))}")
        argv += _option_argv(key, action, value)

    def refuse(message):
        raise ValueError(_option_names(message))

    parser.error = refuse  # one line naming the file's key, not an exit
    try:
        return parser.parse_args(argv)
    finally:
        del parser.error


def _option_argv(key: str, action: argparse.Action, value) -> list[str]:
    """One option of a grid file as the flags of its command."""
    flag = action.option_strings[-1]
    if action.nargs == 0:  # a switch
        if not isinstance(value, bool):
            raise ValueError(f"{key} is a switch: write {key} = true or false, got {value!r}")
        return [flag] if value else []
    values = value if isinstance(value, list) else [value]
    if action.nargs is None and len(values) != 1:
        raise ValueError(f"{key} takes one value, got {value!r}")
    if any(isinstance(v, (bool, dict, list)) for v in values):
        raise ValueError(f"{key} takes numbers or strings, got {value!r}")
    return [flag, *(str(v) for v in values)]


def _option_names(message: str) -> str:
    """An argparse message with its flags named as a grid file's keys (``argument --frontier-speeds`` ->
    ``frontier_speeds``)."""
    return re.sub(r"(?:argument )?--([a-z][a-z0-9-]*)", lambda m: m.group(1).replace("-", "_"), message)


def _cmd_run(args) -> int:
    from pixelmpc_jax.apps.racing.grid_file import CELLS

    grid = args.grid_file
    if grid.experiment != CELLS:
        job = args.grid_args
        job.executor, job.workers = args.executor, args.workers
        for out in args.grid_outputs:
            arg.make_output_dir(out)
        return job.func(job)
    from pixelmpc_jax.apps.experiments import skeleton
    from pixelmpc_jax.apps.racing.executor import make_executor

    out = args.out or grid.out
    arg.make_output_dir(out)
    skeleton.run(skeleton.cells_experiment(grid.cells), out, grid.laps, grid.seed, reuse=tuple(args.reuse),
                 executor=make_executor(args.executor, args.workers))
    _print_report(out)
    return 0
