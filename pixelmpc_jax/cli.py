"""The ``pixelmpc`` command: parses arguments and calls library functions (no logic of its own).

Bad input gets one line on stderr and exit code 2, never a traceback and never a run: every argument is
checked as it is parsed (finite, in range, an existing dataset or weights file), the controller settings
are built before anything runs, and output folders are made only after all of that passed. A library
error reaching the command (ValueError, OSError) prints ``pixelmpc: error: ...``; ``--debug`` shows the
traceback instead. Exit codes: 0 done; 1 the run completed but failed (no lap succeeded, the demo missed
its waypoint, a runtime error); 2 bad input; 130 interrupted (what had finished is saved).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
SEED_MAX = 2**31 - 1  # a PRNG seed is a non-negative int32 (a larger one would wrap onto another seed)
FLOAT32_MAX = 3.4028234663852886e38
RACE_T_F_MAX_S = 2.0  # the race controller's horizon: 80 steps of 0.025 s (a longer t_f acts as 2 s)
RACE_SPEED_MAX = 50.0  # m/s; the vehicle's top speed is about 19 m/s (thrust 36.98 N against drag 0.1 |v| v)
MAX_TIME_S = 600.0  # per lap (a lap of the course takes 20-35 s)
SPLIT_CPU_COMMANDS = ("race", "bench", "reproduce")  # the commands that split the CPU into devices by default


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose error is one line on stderr (no usage block), exit code 2."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


# --------------------------------------------------------------------------------------------------
# Argument types: each returns the value or raises ArgumentTypeError with the accepted range.
# --------------------------------------------------------------------------------------------------


def _float_in(lo: float, hi: float, *, lo_open: bool = False, unit: str = ""):
    """An argparse type: a finite number in [lo, hi] ((lo, hi] with ``lo_open``)."""
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {interval}, got {text!r}") from None
        if not (math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi):
            raise argparse.ArgumentTypeError(f"must be a finite number in {interval}, got {text}")
        return value

    return parse


def _int_in(lo: int, hi: int, *, odd: bool = False):
    """An argparse type: an integer in [lo, hi] (odd with ``odd``)."""
    what = f"{'an odd integer' if odd else 'an integer'} in [{lo}, {hi}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not lo <= value <= hi or (odd and value % 2 == 0):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text}")
        return value

    return parse


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from err
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


_seed = _int_in(0, SEED_MAX)


def _unwritable_reason(out: Path) -> str | None:
    """Why ``out`` could not be used as an output folder, or None; looks only (creates nothing)."""
    probe = out
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        return f"{probe} is not a directory"
    if not os.access(probe, os.W_OK | os.X_OK):
        return f"{probe} is not writable"
    return None


def _writable_dir(path: str) -> Path:
    """An argparse type: an output folder that exists and is writable or could be created there. It is
    made (by :func:`main`) only after every argument has been checked."""
    out = Path(path)
    reason = _unwritable_reason(out)
    if reason is not None:
        raise argparse.ArgumentTypeError(f"output directory {path!r} cannot be written: {reason}")
    return out


def _make_output_dir(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    probe = out / ".write_test"
    probe.write_text("")
    probe.unlink()


def _dataset_dir(path: str) -> Path:
    """An argparse type: a DOF dataset folder (one holding the manifest ``collect`` writes)."""
    root = Path(path)
    hint = f"collect one with `pixelmpc collect --out {path}`"
    if not root.is_dir():
        raise argparse.ArgumentTypeError(f"no DOF dataset at {path!r}: the directory does not exist ({hint})")
    if not (root / "manifest.json").is_file():
        raise argparse.ArgumentTypeError(f"no DOF dataset at {path!r}: manifest.json is missing ({hint})")
    return root


def _weights_file(path: str) -> Path:
    """An argparse type: an existing file (its contents are checked before anything runs)."""
    file = Path(path)
    if not file.is_file():
        reason = "it is a directory" if file.is_dir() else "no such file"
        raise argparse.ArgumentTypeError(f"no DOF weights file at {path!r}: {reason}")
    return file


# --------------------------------------------------------------------------------------------------
# Commands.
# --------------------------------------------------------------------------------------------------


def _cmd_version(args) -> int:
    import jax

    from pixelmpc_jax import __version__

    print(f"pixelmpc-jax {__version__} (jax {jax.__version__}, devices: {jax.devices()})")
    return 0


def _cmd_demo(args) -> int:
    import jax.numpy as jnp
    import numpy as np

    from pixelmpc_jax.apps.waypoint import fly_to_waypoint, waypoint_config
    from pixelmpc_jax.dynamics import quadrotor
    from pixelmpc_jax.strict_json import write_json_atomic

    start = quadrotor.hover_state((0.0, 0.0, 2.0))
    waypoint = jnp.asarray([args.distance, 0.0, 2.0, 0.0])
    config = waypoint_config(num_samples=args.samples)
    print(f"MPPI hover-to-waypoint: {args.distance:.1f} m, N={config.num_samples}, T={config.horizon}, "
          f"{args.seconds:.1f} s at {1 / config.dt:.0f} Hz ...")
    flight = fly_to_waypoint(start, waypoint, num_ticks=max(1, int(round(args.seconds / config.dt))),
                             seed=args.seed, config=config)
    states = np.asarray(flight.states)
    error = np.linalg.norm(states[:, :3] - np.asarray(waypoint[:3]), axis=1)
    times = np.arange(len(states)) * config.dt
    reached = np.nonzero(error < 0.2)[0]
    summary = {
        "final_position": states[-1, :3].round(3).tolist(),
        "final_error_m": float(error[-1]),
        "time_to_within_0.2m_s": float(times[reached[0]]) if reached.size else None,
        "max_error_last_second_m": float(error[times >= times[-1] - 1.0].max()),
    }
    for key, value in summary.items():
        print(f"  {key}: {value}")
    if args.out:
        out = args.out
        write_json_atomic(out / "demo.json", summary)
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
        for i, name in enumerate("xyz"):
            ax[0].plot(times, states[:, i], label=name)
        ax[0].set(xlabel="time [s]", ylabel="position [m]", title="position")
        ax[0].legend()
        ax[1].plot(times, error)
        ax[1].set(xlabel="time [s]", ylabel="distance to waypoint [m]", yscale="log", title="error")
        fig.tight_layout()
        fig.savefig(out / "demo.png", dpi=120)
        print(f"  wrote {out / 'demo.json'} and {out / 'demo.png'}")
    return 0 if error[-1] < 0.5 else EXIT_FAILED


def _race_spec(args, dof_params=None):
    """The race the arguments ask for (a ValueError names a setting the library refuses); ``dof_params``, the
    weights :func:`_race_dof` loads, enter it as their fingerprint."""
    from pixelmpc_jax.apps.spec import RaceSpec, dof_weights_hash

    return RaceSpec(controller=args.controller, speed=args.speed, laps=args.laps, seed=args.seed,
                    perturb=args.perturb, course=args.course, detector=args.detector, estimator=args.estimator,
                    pixel_model=args.pixel_model, t_f=args.t_f, c_pixel=args.c_pixel, temperature=args.temperature,
                    max_time_s=args.max_time, options=_race_options(args),
                    dof_weights=None if dof_params is None else dof_weights_hash(dof_params))


def _check_race(args) -> None:
    """Build the race and its controller before anything runs: a ValueError names a setting the library refuses,
    and a missing or damaged weights file is refused."""
    _race_spec(args, _race_dof(args)).policy()


def _race_options(args) -> dict:
    """The controller options the race flags set away from their defaults (see RaceSpec.options)."""
    options = {}
    if args.controller == "pixelmpc":
        if args.pixel_cost != "l1":
            options["pixel_cost"] = args.pixel_cost
        if args.border_margin is not None:
            options["border_margin"] = args.border_margin
    if args.noise_exponent:
        options["mppi.noise_exponent"] = args.noise_exponent
    if args.heading_weight is not None:
        options["racing.heading_weight"] = args.heading_weight
    return options


def _race_dof(args):
    """The DOF weights the race's PixelMPC uses: a packaged variant by name, or a weights file; None for the
    default (the packaged paper weights, loaded by the race itself) or a race without the DOF."""
    if args.controller != "pixelmpc" or args.pixel_model != "dof" or args.dof_weights == "paper":
        return None
    from pixelmpc_jax.dynamics import dof

    if args.dof_weights in dof.PACKAGED_VARIANTS:
        return dof.load_packaged_dof(args.dof_weights)
    return dof.load_checkpoint(Path(args.dof_weights))[0]


def _cmd_race(args) -> int:
    from pixelmpc_jax.apps import race
    from pixelmpc_jax.sim import metrics

    course = "the AlphaPilot course" if args.course == "alphapilot" else "the straight lane"
    print(f"{args.controller} racing {course} at {args.speed:g} m/s: {args.laps} lap(s), "
          f"seeds {args.seed}..{args.seed + args.laps - 1}, output {args.out}")
    dof_params = _race_dof(args)
    results = race.run_laps(_race_spec(args, dof_params), out=args.out, batch_size=args.batch, video=args.video,
                            dof_params=dof_params)
    laps = results["laps"]
    if laps:
        print(metrics.format_table(laps, results["aggregate"]))
        written = [p for p in (args.out / "metrics.json", args.out / "trajectories.png") if p.exists()]
        print(f"wrote {' and '.join(str(p) for p in written)}")
    if results.get("interrupted"):
        print(f"interrupted after {len(laps)} of {args.laps} lap(s)", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not any(lap.get("success") for lap in laps):
        print(f"no lap succeeded ({len(laps)} flown)", file=sys.stderr)
        return EXIT_FAILED
    return 0


def _cmd_render(args) -> int:
    from pixelmpc_jax.perception.figures import write_render_figures

    print(f"rendering the AlphaPilot course: frames, exact and Farneback flow -> {args.out}")
    results = write_render_figures(args.out)
    for name, entry in results.items():
        print(f"  {name}: Farneback vs exact AEE {entry['aee_px']:.2f} px, written to {entry['path']}")
    return 0


def _cmd_collect(args) -> int:
    from pixelmpc_jax.learn.collect import run_collect

    manifest = run_collect(args.out, laps=args.laps, seed=args.seed, max_lap_time_s=args.max_lap_time,
                           supersample=args.supersample, paper=args.paper, excitation=args.excitation,
                           excitation_pulse_rad_s=args.excitation_pulse,
                           excitation_dither_rad_s=args.excitation_dither)
    return EXIT_INTERRUPTED if manifest.get("interrupted") else 0


def _cmd_train(args) -> int:
    from pixelmpc_jax.learn.train import run_train

    record = run_train(args.data, out_dir=args.out, steps=args.steps, batch_size=args.batch_size,
                       learning_rate=args.learning_rate, seed=args.seed, resume=args.resume, ship=args.ship,
                       loss=args.loss, input=args.input, rotation_augment=args.rotation_augment,
                       rotation_augment_fraction=args.rotation_augment_fraction)
    return EXIT_INTERRUPTED if record.get("interrupted") else 0


def _check_weights(args) -> None:
    """Read the weights file before anything is written (a ValueError names what is wrong with it)."""
    if args.weights is not None:
        from pixelmpc_jax.dynamics import dof

        dof.read_checkpoint(args.weights)


def _cmd_evaluate(args) -> int:
    from pixelmpc_jax.learn.evaluate import run_evaluate

    run_evaluate(weights=args.weights, data_dir=args.data, out_dir=args.out, horizon=args.horizon)
    return 0


def _cmd_bench(args) -> int:
    from pixelmpc_jax.apps.bench.suite import run_bench

    run_bench(args.out, quick=args.quick)
    return 0


def _cmd_reproduce(args) -> int:
    from pixelmpc_jax.apps.reproduce import reproduce

    reproduce([args.parts] if isinstance(args.parts, str) else args.parts, args.out, quick=args.quick)
    print(f"report: {args.out / 'REPORT.md'}")
    return 0


def _seed_range(args) -> str | None:
    """Lap i flies seed + i: the last seed must still be a seed."""
    laps = 10 if getattr(args, "paper", False) else args.laps  # collect --paper flies the paper's 10 laps
    last = args.seed + laps - 1
    if last > SEED_MAX:
        return (f"argument --seed: --seed + --laps - 1 must be at most {SEED_MAX} (lap i uses seed + i), "
                f"got {last}")
    return None


def _turned_rows_need_flown_input(args) -> str | None:
    if args.rotation_augment > 0 and args.input != "flown":
        return "argument --rotation-augment: needs --input flown (it turns the rate flown over the frame)"
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="pixelmpc",
        description="PixelMPC in JAX: perception-aware MPPI with Deep Optical Flow dynamics.",
        epilog="Exit codes: 0 done; 1 the run completed but failed (no lap succeeded, the demo missed its "
               "waypoint); 2 bad input (one line names it); 130 interrupted (what finished is saved).",
    )
    parser.add_argument("--distributed", action="store_true",
                        help="join a multi-host run (jax.distributed.initialize: the cluster is detected under "
                             "SLURM, Open MPI or on TPU; elsewhere set JAX_COORDINATOR_ADDRESS, "
                             "JAX_NUM_PROCESSES, JAX_PROCESS_ID); run the same command on every host")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error instead of one line")
    from pixelmpc_jax.control.sampling import HOST_CPU_DEVICES_MAX  # imports JAX, starts no backend

    parser.add_argument("--cpu-devices", type=_int_in(1, 1024), default=None, metavar="N",
                        help="split the CPU into N JAX devices (default for race, bench and reproduce: one per "
                             f"core, at most {HOST_CPU_DEVICES_MAX}; else 1). A lap's controller splits its "
                             "samples over them and batches of laps spread over them: XLA runs one device's "
                             "program on one core")
    parser.add_argument("--release-memory", action="store_true", help="leave glibc's defaults (race, bench and "
                        "reproduce otherwise keep freed memory for the next step: no page faults at large N)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("version", help="print the package, JAX version and devices")
    p.set_defaults(func=_cmd_version)

    p = sub.add_parser("demo", help="MPPI flies the quadrotor model from hover to a waypoint and holds it")
    p.add_argument("--distance", type=_float_in(-50.0, 50.0, unit="m"), default=5.0,
                   help="waypoint distance ahead, m, in [-50, 50] (default 5)")
    p.add_argument("--seconds", type=_float_in(0.025, 600.0, unit="s"), default=4.0,
                   help="flight time, s, in [0.025, 600] (default 4)")
    p.add_argument("--samples", type=_int_in(1, 2**20), default=512, help="MPPI samples, in [1, 2^20] (default 512)")
    p.add_argument("--seed", type=_seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--out", type=_writable_dir, default=None, help="write demo.json and demo.png here")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("render", help="render course frames with their exact and Farneback optical flow")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/render"), help="output directory")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("collect", help="fly nominal MPPI laps and store frames' Farneback flow (DOF data)")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_data"), help="dataset directory")
    p.add_argument("--laps", type=_positive_int, default=4, help="laps, speeds spread over 6-14 m/s (default 4)")
    p.add_argument("--seed", type=_seed, default=0, help=f"seed of lap 0, in [0, {SEED_MAX}]; lap i uses seed + i")
    p.add_argument("--max-lap-time", type=_float_in(0.0, MAX_TIME_S, lo_open=True, unit="s"), default=10.0,
                   help=f"seconds flown per lap, in (0, {MAX_TIME_S:g}] (default 10)")
    p.add_argument("--supersample", type=_int_in(1, 9, odd=True), default=1,
                   help="render supersampling, odd, in [1, 9] (default 1)")
    p.add_argument("--paper", action="store_true", help="the paper's size: 10 laps of up to 30 s")
    p.add_argument("--excitation", action="store_true",
                   help="train laps add held body-rate pulses and dither to the nominal MPPI's command")
    p.add_argument("--excitation-pulse", type=_float_in(0.0, 6.0, lo_open=True, unit="rad/s"), default=1.5,
                   help="pulse amplitude, uniform in +- this per axis, rad/s, in (0, 6], the rate limit (default 1.5)")
    p.add_argument("--excitation-dither", type=_float_in(0.0, 6.0, lo_open=True, unit="rad/s"), default=0.3,
                   help="std of the per-tick rate dither, rad/s, in (0, 6] (default 0.3)")
    p.set_defaults(func=_cmd_collect, validate=_seed_range)

    p = sub.add_parser("train", help="train the DOF network on a collected dataset (resumable)")
    p.add_argument("--data", type=_dataset_dir, required=True, help="dataset directory from `pixelmpc collect`")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_train"))
    p.add_argument("--steps", type=_positive_int, default=20000)
    p.add_argument("--batch-size", type=_positive_int, default=4096, help="pixels per step (default 4096)")
    p.add_argument("--learning-rate", type=_float_in(0.0, 1.0, lo_open=True), default=1e-3,
                   help="Adam's learning rate, in (0, 1] (default 1e-3)")
    p.add_argument("--seed", type=_seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    p.add_argument("--loss", choices=["polar", "endpoint"], default="polar",
                   help="polar: the paper's MSE on (l, theta) (default); endpoint: squared flow-vector error")
    p.add_argument("--input", choices=["command", "flown"], default="command",
                   help="the network's control input: command, the paper's (the rates commanded at the frame's "
                        "tick, default), or flown (the rates flown over the frame: what the MPC's model means)")
    p.add_argument("--rotation-augment", type=_float_in(0.0, 6.0, unit="rad/s"), default=0.0, metavar="SIGMA",
                   help="turn training rows by an extra body rate of std SIGMA rad/s, label and rate changed "
                        "exactly (needs --input flown; default 0: off, the paper's)")
    p.add_argument("--rotation-augment-fraction", type=_float_in(0.0, 1.0), default=1.0, metavar="P",
                   help="share of the rows turned, in [0, 1] (default 1)")
    p.add_argument("--ship", action="store_true", help="also copy the weights into the installed package")
    p.set_defaults(func=_cmd_train, validate=_turned_rows_need_flown_input)

    p = sub.add_parser("evaluate", help="DOF accuracy: AEE, baselines, multi-step error, figures")
    p.add_argument("--weights", type=_weights_file, default=None,
                   help="weights file (default: the shipped weights)")
    p.add_argument("--data", type=_dataset_dir, default=None,
                   help="dataset directory (default: collect a small seeded held-out set)")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_eval"))
    p.add_argument("--horizon", type=_positive_int, default=80, help="multi-step horizon (default 80)")
    p.set_defaults(func=_cmd_evaluate, precheck=_check_weights)

    p = sub.add_parser("bench", help="runtime harness: Table I, controller scaling, peers, matmul roofline")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/bench"))
    p.add_argument("--quick", action="store_true", help="paper-size controller rows and the pytorch-mppi peer only")
    p.set_defaults(func=_cmd_bench)

    from pixelmpc_jax.apps.reproduce import CHOICES

    p = sub.add_parser("reproduce", help="run the paper's experiments and benchmark into one report (resumable)")
    # default "all", not ["all"]: argparse checks a list default against the choices as one value, and fails
    p.add_argument("parts", nargs="*", default="all", choices=CHOICES, metavar="PART",
                   help=f"what to reproduce (default all): {', '.join(CHOICES)}")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/reproduce"), help="output directory")
    p.add_argument("--quick", action="store_true",
                   help="a small version in minutes (2 laps per cell, the bench's quick rows, the tables only)")
    p.set_defaults(func=_cmd_reproduce)

    from pixelmpc_jax.apps.race import COURSES
    from pixelmpc_jax.control.mppi import TEMPERATURE_MIN
    from pixelmpc_jax.sim.controllers import CONTROLLERS

    p = sub.add_parser("race", help="fly laps of the AlphaPilot course in the closed loop")
    p.add_argument("--controller", choices=CONTROLLERS, default="pixelmpc",
                   help="pixelmpc (default) or mppi, the paper's nominal baseline")
    p.add_argument("--pixel-model", choices=("dof", "projection"), default="dof",
                   help="PixelMPC's pixel model: the shipped DOF network (default) or PAMPC-style projection")
    p.add_argument("--dof-weights", default="paper", metavar="paper|flown|turned|FILE",
                   help="the DOF's weights: the packaged paper weights (command input; default), the packaged "
                        "flown-rate weights, those trained with turned rows, or a weights file from `pixelmpc train`")
    p.add_argument("--detector", choices=("geometry", "image"), default="geometry",
                   help="target detection: projection of the true gate (default) or OpenCV on rendered frames")
    p.add_argument("--course", choices=COURSES, default="alphapilot",
                   help="alphapilot (default) or straight (five gates 20 m apart, the paper's straight lane)")
    p.add_argument("--estimator", choices=("truth", "pf"), default="truth",
                   help="state the controller acts on: ground truth (default) or the particle filter")
    p.add_argument("--video", action="store_true",
                   help="write OUT/onboard.mp4 of the first lap: predicted (green) and actual (red) target pixel")
    p.add_argument("--t-f", type=_float_in(0.0, RACE_T_F_MAX_S, unit="s"), default=1.0,
                   help=f"PixelMPC pixel-cost horizon t_f, s, in [0, {RACE_T_F_MAX_S:g}] (the MPC horizon; default 1)")
    p.add_argument("--c-pixel", type=_float_in(0.0, 1e30), default=9e6,
                   help="PixelMPC pixel-cost weight, in [0, 1e30] (default 9e6)")
    p.add_argument("--pixel-cost", choices=("l1", "border"), default="l1",
                   help="PixelMPC pixel cost: l1, the paper's distance from the image centre (default), or border, "
                        "a barrier on the image border that charges only a gate leaving the view")
    p.add_argument("--border-margin", type=_float_in(0.0, 0.5, lo_open=True), default=None,
                   help="where the border cost starts, as a fraction of the image inside the border, in (0, 0.5] "
                        "(default 0.15)")
    p.add_argument("--noise-exponent", type=_float_in(0.0, 4.0), default=0.0,
                   help="MPPI sampling noise coloured as 1/f^beta along the horizon, beta in [0, 4] (default 0, "
                        "white, the paper's)")
    p.add_argument("--heading-weight", type=_float_in(0.0, 1.0), default=None,
                   help="share of the racing cost's attitude term that pins the heading to the path, in [0, 1] "
                        "(default 1, the paper's)")
    p.add_argument("--speed", type=_float_in(0.0, RACE_SPEED_MAX, lo_open=True, unit="m/s"), default=14.0,
                   help=f"target speed, m/s, in (0, {RACE_SPEED_MAX:g}] (default 14)")
    p.add_argument("--laps", type=_positive_int, default=1, help="number of laps (default 1)")
    p.add_argument("--seed", type=_seed, default=0, help=f"seed of the first lap, in [0, {SEED_MAX}]; lap i uses "
                                                         "seed + i")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/race"), help="output directory")
    p.add_argument("--batch", type=_positive_int, default=1,
                   help="laps per batched (vmapped) call; raise it on a GPU (default 1)")
    p.add_argument("--perturb", action="store_true", help="perturb the gates per lap within the AlphaPilot bounds")
    p.add_argument("--max-time", type=_float_in(0.0, MAX_TIME_S, lo_open=True, unit="s"), default=60.0,
                   help=f"timeout per lap, s, in (0, {MAX_TIME_S:g}] (default 60)")
    p.add_argument("--temperature", type=_float_in(TEMPERATURE_MIN, FLOAT32_MAX), default=None,
                   help=f"MPPI lambda, in [{TEMPERATURE_MIN:g}, {FLOAT32_MAX:.4g}] (default: tuned)")
    p.set_defaults(func=_cmd_race, validate=_seed_range, precheck=_check_race)
    return parser


def _command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[command]
    raise LookupError(command)


def _make_output_dirs(args, command_parser: argparse.ArgumentParser) -> None:
    """Create every output folder the command was given (or defaults to), now that all else is checked."""
    for action in command_parser._actions:
        if action.type is not _writable_dir or getattr(args, action.dest, None) is None:
            continue
        out = Path(getattr(args, action.dest))
        try:
            _make_output_dir(out)
        except OSError as err:
            command_parser.error(f"argument {'/'.join(action.option_strings)}: output directory {str(out)!r} "
                                 f"cannot be written: {err}")


def _one_line(err: BaseException, limit: int = 600) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    text = " ".join(lines) or type(err).__name__
    return text if len(text) <= limit else text[:limit] + " ... (--debug shows all of it)"


def main(argv: list[str] | None = None, split_cpu: bool = False) -> int:
    """Run the command ``argv`` (default: the process's arguments). With ``split_cpu`` (the ``pixelmpc``
    command), race, bench and reproduce split the CPU into one device per core unless ``--cpu-devices`` says
    otherwise, and keep freed memory (``sampling.keep_host_memory``) unless ``--release-memory``; called from
    Python, only ``--cpu-devices`` splits (and only before JAX has started)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    if args.cpu_devices is not None or (split_cpu and args.command in SPLIT_CPU_COMMANDS):
        from pixelmpc_jax.control import sampling

        sampling.split_host_cpu(args.cpu_devices)
        if split_cpu and args.command in SPLIT_CPU_COMMANDS and not args.release_memory:
            sampling.keep_host_memory()
    command_parser = _command_parser(parser, args.command)
    validate = getattr(args, "validate", None)
    problem = validate(args) if validate is not None else None
    if problem:
        command_parser.error(problem)
    try:
        if args.distributed:
            _initialize_distributed()
        precheck = getattr(args, "precheck", None)
        if precheck is not None:
            precheck(args)
        _make_output_dirs(args, command_parser)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print("pixelmpc: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as err:  # bad input found by the library: a file, a setting
        if args.debug:
            raise
        print(f"pixelmpc: error: {_one_line(err)}", file=sys.stderr)
        return EXIT_USAGE
    except RuntimeError as err:  # the run itself failed (a lap too short to store, out of memory)
        if args.debug:
            raise
        print(f"pixelmpc: error: {_one_line(err)}", file=sys.stderr)
        return EXIT_FAILED


def _initialize_distributed() -> None:
    """``jax.distributed.initialize`` from the cluster's environment, or from the JAX_* variables."""
    import jax

    kwargs = {}
    if os.environ.get("JAX_COORDINATOR_ADDRESS"):
        missing = [name for name in ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID") if name not in os.environ]
        if missing:
            raise ValueError(f"--distributed with JAX_COORDINATOR_ADDRESS also needs {' and '.join(missing)}")
        try:
            kwargs = {"coordinator_address": os.environ["JAX_COORDINATOR_ADDRESS"],
                      "num_processes": int(os.environ["JAX_NUM_PROCESSES"]),
                      "process_id": int(os.environ["JAX_PROCESS_ID"])}
        except ValueError as err:
            raise ValueError(f"--distributed: JAX_NUM_PROCESSES and JAX_PROCESS_ID must be integers ({err})") from None
    jax.distributed.initialize(**kwargs)
    print(f"process {jax.process_index()} of {jax.process_count()}: {jax.local_device_count()} local and "
          f"{jax.device_count()} global device(s)", flush=True)


def console_main() -> int:
    """The ``pixelmpc`` command."""
    return main(split_cpu=True)


if __name__ == "__main__":
    sys.exit(console_main())
