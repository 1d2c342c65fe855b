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
import os
import sys
import threading
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import MAX_TIME_S, SEED_MAX
from pixelmpc_jax.commands import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from pixelmpc_jax.commands.bench import add_bench
from pixelmpc_jax.commands.experiment import add_experiment
from pixelmpc_jax.commands.race import add_race
from pixelmpc_jax.commands.tune import add_tune

# the commands that split the CPU into devices by default
SPLIT_CPU_COMMANDS = ("race", "bench", "reproduce", "tune", "experiment")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose error is one line on stderr (no usage block), exit code 2."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


# --------------------------------------------------------------------------------------------------
# Commands.
# --------------------------------------------------------------------------------------------------


def _cmd_version(args) -> int:
    import jax

    from pixelmpc_jax import __version__

    print(f"pixelmpc-jax {__version__} (jax {jax.__version__}, devices: {jax.devices()})")
    return 0


def _cmd_demo(args) -> int:
    from pixelmpc_jax.apps.racing.waypoint import run_demo

    summary = run_demo(args.distance, args.seconds, args.samples, args.seed, args.out)
    return 0 if summary["final_error_m"] < 0.5 else EXIT_FAILED


def _cmd_course(args) -> int:
    from pixelmpc_jax.world import course

    data = course.generate_course(args.seed, num_gates=args.gates)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    course.write_course(data, args.out)
    track = course.load_course(args.out)
    print(f"wrote {args.out}: {track.num_gates} gates, {float(track.path_s[-1]):.0f} m of path (seed {args.seed})")
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


def _train_settings(args, model: str) -> dict:
    """The model config's fields the train flags set: those of every model (dest ``model:`` + field) and those of
    ``model`` alone (dest ``dof:`` or ``vdof:`` + field), as given (a flag left out keeps the config's default)."""
    prefixes = ("model:", f"{model}:")
    return {dest.partition(":")[2]: value for dest, value in vars(args).items()
            if dest.startswith(prefixes) and value is not None}


def _cmd_train(args) -> int:
    from pixelmpc_jax.learn.dof_spec import DOFConfig
    from pixelmpc_jax.learn.train import TrainConfig, run_train
    from pixelmpc_jax.learn.vdof_spec import VDOFConfig

    model = {"dof": DOFConfig, "vdof": VDOFConfig}[args.model](**_train_settings(args, args.model))
    config = TrainConfig(model=model, seed=args.seed, progress=not args.no_progress)
    out = args.out if args.out is not None else Path(f"runs/{args.model}_train")
    record = run_train(args.data, out_dir=out, config=config, resume=args.resume, ship=args.ship)
    return EXIT_INTERRUPTED if record.get("interrupted") else 0


def _check_weights(args) -> None:
    """Read the weights file before anything is written (a ValueError names what is wrong with it)."""
    if args.weights is not None:
        from pixelmpc_jax.learn.evaluate import read_weights

        read_weights(args.weights)


def _cmd_evaluate(args) -> int:
    from pixelmpc_jax.learn.evaluate import run_evaluate

    run_evaluate(weights=args.weights, data_dir=args.data, out_dir=args.out, horizon=args.horizon)
    return 0


def _cmd_reproduce(args) -> int:
    from pixelmpc_jax.apps.experiments.reproduce import reproduce

    reproduce([args.parts] if isinstance(args.parts, str) else args.parts, args.out, quick=args.quick)
    print(f"report: {args.out / 'REPORT.md'}")
    return 0


def _check_train(args) -> str | None:
    """A flag of another model than ``--model`` names is refused (its dest is that model's, ``dof:`` or ``vdof:``
    + the config field, the flag's name); turned rows need the flown input."""
    for dest, value in vars(args).items():
        model, _, field = dest.partition(":")
        if model in ("dof", "vdof") and model != args.model and value is not None:
            return f"argument --{field.replace('_', '-')}: applies to --model {model} only"
    if (getattr(args, "dof:rotation_augment") or 0.0) > 0 and getattr(args, "dof:input") != "flown":
        return "argument --rotation-augment: needs --input flown (it turns the rate flown over the frame)"
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="pixelmpc",
        description="PixelMPC in JAX: perception-aware MPPI with Deep Optical Flow dynamics.",
        epilog="Exit codes: 0 done; 1 the run completed but failed (no lap succeeded, the demo missed its "
               "waypoint); 2 bad input (one line names it); 130 interrupted (what finished is saved).",
    )
    _add_process_flags(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    p = sub.add_parser("version", help="print the package, JAX version and devices")
    p.set_defaults(func=_cmd_version)
    for add in (_add_demo, _add_render, _add_collect, _add_train, _add_evaluate, add_bench, _add_reproduce,
                add_race, _add_course, add_tune, add_experiment):
        add(sub)
    return parser


def _add_process_flags(parser: argparse.ArgumentParser) -> None:
    """The flags that set up the process before any command: hosts, devices, memory, tracebacks."""
    parser.add_argument("--distributed", action="store_true",
                        help="join a multi-host run (jax.distributed.initialize: the cluster is detected under "
                             "SLURM, Open MPI or on TPU; elsewhere set JAX_COORDINATOR_ADDRESS, "
                             "JAX_NUM_PROCESSES, JAX_PROCESS_ID); run the same command on every host")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error instead of one line")
    from pixelmpc_jax.host import HOST_CPU_DEVICES_MAX  # imports JAX, starts no backend

    parser.add_argument("--cpu-devices", type=arg.int_in(1, 1024), default=None, metavar="N",
                        help="split the CPU into N JAX devices (default for race, bench, reproduce, tune and "
                             f"experiment: one per core, at most {HOST_CPU_DEVICES_MAX}; else 1). A lap's controller "
                             "splits its samples over them and batches of laps spread over them: XLA runs one "
                             "device's program on one core")
    parser.add_argument("--release-memory", action="store_true", help="leave glibc's defaults (the commands that "
                        "split the CPU otherwise keep freed memory for the next step: no page faults at large N)")


def _add_demo(sub) -> None:
    """``pixelmpc demo``: MPPI flying the model to a waypoint."""
    p = sub.add_parser("demo", help="MPPI flies the quadrotor model from hover to a waypoint and holds it")
    p.add_argument("--distance", type=arg.float_in(-50.0, 50.0, unit="m"), default=5.0,
                   help="waypoint distance ahead, m, in [-50, 50] (default 5)")
    p.add_argument("--seconds", type=arg.float_in(0.025, 600.0, unit="s"), default=4.0,
                   help="flight time, s, in [0.025, 600] (default 4)")
    p.add_argument("--samples", type=arg.int_in(1, 2**20), default=512, help="MPPI samples, in [1, 2^20] (default 512)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--out", type=arg.writable_dir, default=None, help="write demo.json and demo.png here")
    p.set_defaults(func=_cmd_demo)


def _add_render(sub) -> None:
    """``pixelmpc render``: rendered frames and their flow."""
    p = sub.add_parser("render", help="render course frames with their exact and Farneback optical flow")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/render"), help="output directory")
    p.set_defaults(func=_cmd_render)


def _add_collect(sub) -> None:
    """``pixelmpc collect``: the DOF dataset."""
    p = sub.add_parser("collect", help="fly nominal MPPI laps and store frames' Farneback flow (DOF data)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/dof_data"), help="dataset directory")
    p.add_argument("--laps", type=arg.positive_int, default=4, help="laps, speeds spread over 6-14 m/s (default 4)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"seed of lap 0, in [0, {SEED_MAX}]; lap i uses seed + i")
    p.add_argument("--max-lap-time", type=arg.float_in(0.0, MAX_TIME_S, lo_open=True, unit="s"), default=10.0,
                   help=f"seconds flown per lap, in (0, {MAX_TIME_S:g}] (default 10)")
    p.add_argument("--supersample", type=arg.int_in(1, 9, odd=True), default=1,
                   help="render supersampling, odd, in [1, 9] (default 1)")
    p.add_argument("--paper", action="store_true", help="the paper's size: 10 laps of up to 30 s")
    p.add_argument("--excitation", action="store_true",
                   help="train laps add held body-rate pulses and dither to the nominal MPPI's command")
    p.add_argument("--excitation-pulse", type=arg.float_in(0.0, 6.0, lo_open=True, unit="rad/s"), default=1.5,
                   help="pulse amplitude, uniform in +- this per axis, rad/s, in (0, 6], the rate limit (default 1.5)")
    p.add_argument("--excitation-dither", type=arg.float_in(0.0, 6.0, lo_open=True, unit="rad/s"), default=0.3,
                   help="std of the per-tick rate dither, rad/s, in (0, 6] (default 0.3)")
    p.set_defaults(func=_cmd_collect, validate=arg.seed_range)


def _model_flag(p, model: str, field: str, help: str, **kwargs) -> None:
    """A train flag named after a field of the model config it sets (``--box-cue`` sets ``box_cue``): ``model``
    "model" for a field every model has, else "dof" or "vdof" (the other model refuses it). Left out, the field
    keeps the config's default."""
    if "choices" not in kwargs:
        kwargs.setdefault("metavar", field.upper())
    p.add_argument(f"--{field.replace('_', '-')}", dest=f"{model}:{field}", default=None, help=help, **kwargs)


def _add_train(sub) -> None:
    """``pixelmpc train``: a pixel model's training, the DOF's or vdof's, through the one pipeline."""
    from pixelmpc_jax.dynamics.dof import PACKAGED_VARIANTS
    from pixelmpc_jax.learn.dataset import INPUTS
    from pixelmpc_jax.learn.dof_spec import LOSSES, DOFConfig
    from pixelmpc_jax.learn.vdof_spec import BOX_CUES, BOX_LOSSES, VDOFConfig

    dof, vdof = DOFConfig(), VDOFConfig()
    p = sub.add_parser("train", help="train a pixel model (the DOF or vdof) on a collected dataset (resumable)")
    p.add_argument("--model", choices=("dof", "vdof"), default="dof",
                   help="dof: the paper's DOF on every pixel's Farneback flow (default); vdof: the velocity-and-depth "
                        "pixel model on the gate detector's frame-to-frame motion (the best preset's)")
    p.add_argument("--data", type=arg.dataset_dir, required=True, help="dataset directory from `pixelmpc collect`")
    p.add_argument("--out", type=arg.writable_dir, default=None, help="output directory (default runs/MODEL_train)")
    _model_flag(p, "model", "steps", type=arg.positive_int,
                help=f"Adam steps (vdof: of its one-step stage; default: dof {dof.steps}, vdof {vdof.steps})")
    _model_flag(p, "model", "batch_size", type=arg.positive_int,
                help=f"rows per step (dof: pixels, vdof: detections; default: dof {dof.batch_size}, vdof "
                     f"{vdof.batch_size})")
    _model_flag(p, "model", "learning_rate", type=arg.float_in(0.0, 1.0, lo_open=True),
                help=f"Adam's peak learning rate, in (0, 1] (default: dof {dof.learning_rate:g}, vdof "
                     f"{vdof.learning_rate:g})")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    p.add_argument("--ship", action="store_true", help="also copy the weights into the installed package")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    g = p.add_argument_group("--model dof only")
    _model_flag(g, "dof", "loss", choices=LOSSES,
                help="polar: the paper's MSE on (l, theta) (default); endpoint: squared flow-vector error")
    _model_flag(g, "dof", "input", choices=INPUTS,
                help="the network's control input: command, the paper's (the rates commanded at the frame's "
                     "tick, default), or flown (the rates flown over the frame: what the MPC's model means)")
    _model_flag(g, "dof", "rotation_augment", type=arg.float_in(0.0, 6.0, unit="rad/s"), metavar="SIGMA",
                help="turn training rows by an extra body rate of std SIGMA rad/s, label and rate changed "
                     "exactly (needs --input flown; default 0: off, the paper's)")
    _model_flag(g, "dof", "rotation_augment_fraction", type=arg.float_in(0.0, 1.0), metavar="P",
                help="share of the rows turned, in [0, 1] (default 1)")
    g = p.add_argument_group("--model vdof only")
    _model_flag(g, "vdof", "hidden_sizes", type=arg.widths, metavar="W,W",
                help=f"hidden widths of g(uv), comma-separated (default {','.join(map(str, vdof.hidden_sizes))})")
    _model_flag(g, "vdof", "box_loss", choices=BOX_LOSSES,
                help=f"the box size's rate scored absolute or relative (s_dot / s) (default {vdof.box_loss})")
    _model_flag(g, "vdof", "box_cue", choices=BOX_CUES,
                help=f"s: the detected box's apparent size, or that per the gate's size (default {vdof.box_cue})")
    _model_flag(g, "vdof", "rollout_steps", type=arg.int_in(0, 1000), metavar="K",
                help=f"K of the rollout fine-tuning stage, 0: none (default {vdof.rollout_steps})")
    _model_flag(g, "vdof", "rollout_train_steps", type=arg.int_in(0, 10_000_000),
                help=f"Adam steps of the rollout stage, 0: none (default {vdof.rollout_train_steps})")
    _model_flag(g, "vdof", "rollout_learning_rate", type=arg.float_in(0.0, 1.0, lo_open=True),
                help=f"the rollout stage's peak learning rate (default {vdof.rollout_learning_rate:g})")
    _model_flag(g, "vdof", "rollout_batch_size", type=arg.positive_int,
                help=f"windows per step of the rollout stage (default {vdof.rollout_batch_size})")
    _model_flag(g, "vdof", "comparison_dof", choices=sorted(PACKAGED_VARIANTS),
                help=f"the packaged DOF the held-out figures are reported beside (default {vdof.comparison_dof})")
    p.set_defaults(func=_cmd_train, validate=_check_train)


def _add_evaluate(sub) -> None:
    """``pixelmpc evaluate``: the DOF's accuracy."""
    p = sub.add_parser("evaluate", help="DOF accuracy: AEE, baselines, multi-step error, figures")
    p.add_argument("--weights", type=arg.weights_file, default=None,
                   help="weights file (default: the shipped weights)")
    p.add_argument("--data", type=arg.dataset_dir, default=None,
                   help="dataset directory (default: collect a small seeded held-out set)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/dof_eval"))
    p.add_argument("--horizon", type=arg.positive_int, default=80, help="multi-step horizon (default 80)")
    p.set_defaults(func=_cmd_evaluate, precheck=_check_weights)


def _add_reproduce(sub) -> None:
    """``pixelmpc reproduce``: the paper's experiments."""
    from pixelmpc_jax.apps.experiments.reproduce import CHOICES

    p = sub.add_parser("reproduce", help="run the paper's experiments and benchmark into one report (resumable)")
    # default "all", not ["all"]: argparse checks a list default against the choices as one value, and fails
    p.add_argument("parts", nargs="*", default="all", choices=CHOICES, metavar="PART",
                   help=f"what to reproduce (default all): {', '.join(CHOICES)}")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/reproduce"), help="output directory")
    p.add_argument("--quick", action="store_true",
                   help="a small version in minutes (2 laps per cell, the bench's quick rows, the tables only)")
    p.set_defaults(func=_cmd_reproduce)


def _add_course(sub) -> None:
    """``pixelmpc course``: a seeded course file."""
    p = sub.add_parser("course", help="generate a seeded race course (a file for `race --course` and the frontier)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"the course's seed, in [0, {SEED_MAX}] (default 0)")
    p.add_argument("--gates", type=arg.int_in(2, 30), default=8, help="number of gates, in [2, 30] (default 8)")
    p.add_argument("--out", type=arg.output_file, required=True, help="the course file to write (JSON)")
    p.set_defaults(func=_cmd_course)


def _command_parser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The parser of the (sub-)command ``args`` ran: ``pixelmpc race``'s, ``pixelmpc experiment table2``'s."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return _command_parser(action.choices[getattr(args, action.dest)], args)
    return parser


def _make_output_dirs(args, command_parser: argparse.ArgumentParser) -> None:
    """Create every output folder the command was given (or defaults to), now that all else is checked."""
    for action in command_parser._actions:
        if action.type is not arg.writable_dir or getattr(args, action.dest, None) is None:
            continue
        out = Path(getattr(args, action.dest))
        try:
            arg.make_output_dir(out)
        except OSError as err:
            command_parser.error(f"argument {'/'.join(action.option_strings)}: output directory {str(out)!r} "
                                 f"cannot be written: {err}")


def _one_line(err: BaseException, limit: int = 600) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    text = " ".join(lines) or type(err).__name__
    return text if len(text) <= limit else text[:limit] + " ... (--debug shows all of it)"


def main(argv: list[str] | None = None, split_cpu: bool = False) -> int:
    """Run the command ``argv`` (default: the process's arguments). With ``split_cpu`` (the ``pixelmpc``
    command), race, bench, reproduce, tune and experiment split the CPU into one device per core unless
    ``--cpu-devices`` says otherwise, and keep freed memory (``host.keep_host_memory``) unless
    ``--release-memory``; called from Python, only ``--cpu-devices`` splits (and only before JAX has started)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    if args.cpu_devices is not None or (split_cpu and args.command in SPLIT_CPU_COMMANDS):
        from pixelmpc_jax import host

        host.split_host_cpu(args.cpu_devices)
        if split_cpu and args.command in SPLIT_CPU_COMMANDS and not args.release_memory:
            host.keep_host_memory()
    command_parser = _command_parser(parser, args)
    if threading.current_thread() is threading.main_thread():
        from pixelmpc_jax import host

        host.stop_on_sigterm()
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
