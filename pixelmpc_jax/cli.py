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
import dataclasses
import json
import os
import sys
import threading
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX
from pixelmpc_jax.commands.bench import add_bench
from pixelmpc_jax.commands.experiment import add_experiment
from pixelmpc_jax.commands.tune import add_tune
from pixelmpc_jax.timing import LAP_TIME_LIMIT_S

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
MAX_TIME_S = 600.0  # per lap (a lap of the course takes 20-35 s)
# the commands that split the CPU into devices by default
SPLIT_CPU_COMMANDS = ("race", "bench", "reproduce", "tune", "experiment")
SETTING = "setting:"  # the dest of a race flag that sets a controller setting: SETTING + its field (see _setting)


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


def _setting(p: argparse.ArgumentParser, flag: str, field: str, help: str, **kwargs) -> None:
    """A race flag that sets one controller setting: ``field`` names it in the
    :class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig` the race flies ("t_f"; "mppi.temperature" for its
    MPPIConfig; "racing.heading_weight" for its RacingCostConfig). Left out, the setting keeps its default."""
    shown = {name: _preset_setting(name, field) for name in ("best", "paper")}
    shown = ", ".join(f"{name} {value:g}" if isinstance(value, float) else f"{name} {value}"
                      for name, value in shown.items())
    if "choices" not in kwargs:
        kwargs["metavar"] = flag.lstrip("-").upper().replace("-", "_")
    p.add_argument(flag, dest=SETTING + field, default=None, help=f"{help} (default: the preset's; {shown})",
                   **kwargs)


def _preset_setting(preset: str, field: str):
    """A controller setting of a preset (building a preset creates no JAX array: no backend starts)."""
    from pixelmpc_jax.apps.racing.presets import preset as preset_spec

    value = preset_spec(preset).config
    for name in field.split("."):
        value = getattr(value, name)
    return value


def _with_setting(config, path: list[str], value):
    """``config`` (a frozen dataclass) with the field at ``path`` (nested names) set to ``value``."""
    if len(path) == 1:
        return dataclasses.replace(config, **{path[0]: value})
    return dataclasses.replace(config, **{path[0]: _with_setting(getattr(config, path[0]), path[1:], value)})


def _controller_config(args, config):
    """The controller configuration the race flags ask for: ``config`` (the preset's), with each setting flag
    given."""
    for dest, value in sorted(vars(args).items()):
        if dest.startswith(SETTING) and value is not None:
            config = _with_setting(config, dest[len(SETTING):].split("."), value)
    return config


def _race_spec(args):
    """The race the arguments ask for: the preset, each flag given overriding one field (a ValueError names a
    setting the library refuses), and the DOF weights of a weights file (None for packaged weights, which the
    spec names), which enter the spec as their fingerprint."""
    from pixelmpc_jax.apps.racing.presets import preset
    from pixelmpc_jax.apps.racing.spec import RaceSpec
    from pixelmpc_jax.dynamics.dof import PACKAGED_VARIANTS
    from pixelmpc_jax.dynamics.network_weights import dof_weights_hash

    base = RaceSpec.from_record(json.loads(args.config.read_text())) if args.config else preset(args.preset)
    fields = {"speed": args.speed, "laps": args.laps, "seed": args.seed, "perturb": args.perturb,
              "course": args.course, "detector": args.detector, "estimator": args.estimator,
              "max_time_s": args.max_time, "dof_weights": args.dof_weights, "camera_tilt_deg": args.camera_tilt}
    spec = base.replace(config=_controller_config(args, base.config),
                        **{name: value for name, value in fields.items() if value is not None})
    spec = arg.with_faults(args, spec)
    if args.dof_weights == "vdof":  # the packaged vdof weights: the vdof model's default
        if spec.config.pixel_model != "vdof":
            raise ValueError("--dof-weights vdof names the vdof model's weights: fly it with --pixel-model vdof")
        spec = spec.replace(dof_weights=None)
    dof_params = None
    if spec.dof_weights is not None and spec.dof_weights not in PACKAGED_VARIANTS:
        dof_params = _race_dof(spec.dof_weights, spec.config.pixel_model)
        spec = spec.replace(dof_weights=dof_weights_hash(dof_params))
    return spec, dof_params


def _check_race(args) -> None:
    """Build the race and its controllers before anything runs: a ValueError names a setting the library refuses,
    and a missing or damaged weights file is refused."""
    from pixelmpc_jax.world.course import make_course

    spec = _race_spec(args)[0]
    make_course(spec.course)  # a course file's bad field is named here
    for controller in (args.controller,) if args.controller else ("pixelmpc", "mppi"):
        spec.replace(controller=controller).policy()


def _race_dof(weights: str, pixel_model: str):
    """The pixel model's weights in the weights file ``--dof-weights`` names (a DOF or, for "vdof", a vdof
    checkpoint)."""
    if pixel_model == "vdof":
        from pixelmpc_jax.dynamics import vdof

        return vdof.load_vdof(Path(weights))[0]
    from pixelmpc_jax.dynamics import dof

    return dof.load_checkpoint(Path(weights))[0]


def _cmd_race(args) -> int:
    from pixelmpc_jax import host
    from pixelmpc_jax.apps.racing import compare
    from pixelmpc_jax.world.course import course_title

    if not args.no_compile_cache:
        host.use_compilation_cache()
    spec, dof_params = _race_spec(args)
    controllers = (args.controller,) if args.controller else ("pixelmpc", "mppi")
    source = f"config {args.config}" if args.config else f"preset {args.preset}"
    print(f"{source}: {' and '.join(compare.LABELS[c] for c in controllers)} racing {course_title(spec.course)} at "
          f"{spec.speed:g} m/s, {spec.laps} lap(s) each, seeds {spec.seed}..{spec.seed + spec.laps - 1}, "
          f"output {args.out}")
    record = compare.run_compare(spec, controllers, out=args.out, preset=str(args.config or args.preset),
                                 batch_size=args.batch, video=args.video, dof_params=dof_params)
    if any(results["laps"] for results in record["controllers"].values()):
        print(compare.side_by_side(record))
        written = [p for p in ("metrics.json", *(f"ticks_{c}.npz" for c in controllers), "trajectories.png",
                               "visibility.png") if (args.out / p).exists()]
        print(f"wrote {', '.join(str(args.out / p) for p in written)}")
    if record["interrupted"]:
        print(f"interrupted; the finished laps are in {args.out / 'metrics.json'} and its ticks_*.npz",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    laps = [lap for results in record["controllers"].values() for lap in results["laps"]]
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


def _seed_range(args) -> str | None:
    """Lap i flies seed + i: the last seed must still be a seed."""
    laps = 10 if getattr(args, "paper", False) else args.laps or 1  # collect --paper flies the paper's 10 laps
    last = (args.seed or 0) + laps - 1
    if last > SEED_MAX:
        return (f"argument --seed: --seed + --laps - 1 must be at most {SEED_MAX} (lap i uses seed + i), "
                f"got {last}")
    return None


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
                _add_race, _add_course, add_tune, add_experiment):
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
    p.set_defaults(func=_cmd_collect, validate=_seed_range)


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


def _add_race(sub) -> None:
    """``pixelmpc race``: laps in the closed loop. The race's own flags set a RaceSpec field; each controller
    flag sets one controller setting (:func:`_setting`)."""
    from pixelmpc_jax.apps.racing.presets import DEFAULT_PRESET, PRESETS
    from pixelmpc_jax.apps.racing.spec import CAMERA_TILT_MAX_DEG
    from pixelmpc_jax.control.mppi_checks import FLOAT32_MAX, TEMPERATURE_MIN
    from pixelmpc_jax.control.pixelmpc import LOOK_AHEAD_MODELS, PIXEL_COSTS, PIXEL_MODELS, TARGET_PRIORS
    from pixelmpc_jax.dynamics.dof import PACKAGED_VARIANTS
    from pixelmpc_jax.sim.controllers import CONTROLLERS
    from pixelmpc_jax.sim.env import DETECTORS, ESTIMATORS
    from pixelmpc_jax.world.course import COURSES

    p = sub.add_parser("race", help="PixelMPC beside nominal MPPI on the AlphaPilot course, in the closed loop")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--preset", choices=PRESETS, default=DEFAULT_PRESET,
                       help="the race to start from: best (default), the best configuration measured on the speed "
                            "frontier at the paper's pace; paper, the paper's formulation at its 14 m/s target. Every "
                            "other flag overrides one field of it")
    start.add_argument("--config", type=Path, default=None, metavar="FILE",
                       help="start from a saved race instead of a preset: a RaceSpec record in JSON, as `pixelmpc "
                            "tune` writes its best.json; every other flag overrides one field of it")
    p.add_argument("--controller", choices=CONTROLLERS, default=None,
                   help="fly one controller alone: pixelmpc or mppi, the paper's nominal baseline (default: both, "
                        "at the same target and seeds)")
    p.add_argument("--dof-weights", default=None, metavar="|".join(PACKAGED_VARIANTS) + "|vdof|FILE",
                   help="the learned pixel model's weights: a packaged DOF variant (paper: command input; flown: "
                        "the flown-rate weights; turned: trained with turned rows) or a weights file from `pixelmpc "
                        "train`; with --pixel-model vdof: vdof, the packaged vdof weights (its default), or a file) "
                        "(default: the preset's)")
    p.add_argument("--detector", choices=DETECTORS, default=None,
                   help="target detection: geometry, the projection of the true gate, or image, OpenCV on "
                        "rendered frames (default: the preset's, geometry)")
    p.add_argument("--course", type=arg.course, default=None, metavar="|".join(COURSES) + "|FILE",
                   help="alphapilot, straight (five gates 20 m apart, the paper's straight lane) or a course file "
                        "in the format of pixelmpc_jax/data/alphapilot_course.json (`pixelmpc course` makes one) "
                        "(default: the preset's, alphapilot)")
    p.add_argument("--estimator", choices=ESTIMATORS, default=None,
                   help="state the controller acts on: truth, pf (the paper's particle filter) or eskf (an "
                        "error-state Kalman filter with IMU bias states) (default: the preset's, truth)")
    p.add_argument("--video", action="store_true",
                   help="write OUT/onboard.mp4 of PixelMPC's first lap: predicted (green) and actual (red) pixel")
    p.add_argument("--no-compile-cache", action="store_true",
                   help="compile afresh (by default compiled steps are kept in the user's cache folder, "
                        "~/.cache/pixelmpc-jax, so a second run starts faster)")
    _setting(p, "--pixel-model", "pixel_model", "PixelMPC's pixel model: dof, the paper's DOF network; vdof, "
             "the learned model with velocity and the gate's size; or projection, the PAMPC-style projection of the "
             "known gate", choices=PIXEL_MODELS)
    _setting(p, "--t-f", "t_f", f"PixelMPC pixel-cost horizon t_f, s, in [0, {arg.T_F_MAX_S:g}] (the MPC horizon)",
             type=arg.float_in(0.0, arg.T_F_MAX_S, unit="s"))
    _setting(p, "--c-pixel", "c_pixel", "PixelMPC pixel-cost weight, in [0, 1e30]", type=arg.float_in(0.0, 1e30))
    _setting(p, "--pixel-cost", "pixel_cost", "PixelMPC pixel cost: l1, the paper's distance from the image centre, "
             "or border, a barrier on the image border that charges only a gate leaving the view", choices=PIXEL_COSTS)
    _setting(p, "--target-prior", "target_prior", "what PixelMPC's pixel cost charges while the target is not "
             "detected: none, the paper's (no pixel cost); map, its pixel projected from the map and the estimate; "
             "kept, its last pixel moved on by the pixel model since it was last seen; or seeded, kept once seen "
             "and from the map before",
             choices=TARGET_PRIORS)
    _setting(p, "--look-ahead", "look_ahead", "PixelMPC's weight, relative to the target's, of the next gate's pixel "
             "cost on the predicted states past the target (its pixel from the map and the estimate); 0: none, the "
             "paper's", type=arg.float_in(0.0, 1e3))
    _setting(p, "--look-ahead-model", "look_ahead_model", "what predicts the next gate's pixel along the horizon with "
             "the look-ahead: own, PixelMPC's pixel model; projection, the gate's centre from the map projected "
             "through each predicted pose (map-aided)", choices=LOOK_AHEAD_MODELS)
    _setting(p, "--border-margin", "border_margin", "where the border cost starts, as a fraction of the image inside "
             "the border, in (0, 0.5]", type=arg.float_in(0.0, 0.5, lo_open=True))
    _setting(p, "--noise-exponent", "mppi.noise_exponent", "MPPI sampling noise coloured as 1/f^beta along the "
             "horizon, beta in [0, 4] (0: white, the paper's)", type=arg.float_in(0.0, 4.0))
    _setting(p, "--heading-weight", "racing.heading_weight", "share of the racing cost's attitude term that pins "
             "the heading to the path, in [0, 1] (1: the paper's)", type=arg.float_in(0.0, 1.0))
    _setting(p, "--clearance", "racing.vehicle_radius", "m: the racing cost's clearance to gate frames, floor and "
             "walls (the world keeps the vehicle's 0.1 m), in [0.05, 1]", type=arg.float_in(0.05, 1.0, unit="m"))
    _setting(p, "--temperature", "mppi.temperature", f"MPPI lambda, in [{TEMPERATURE_MIN:g}, {FLOAT32_MAX:.4g}]",
             type=arg.float_in(TEMPERATURE_MIN, FLOAT32_MAX))
    _setting(p, "--samples", "mppi.num_samples", "MPPI samples per step, in [1, 2^20]", type=arg.int_in(1, 2**20))
    p.add_argument("--speed", type=arg.target_speed, default=None,
                   help=f"target speed, m/s, in (0, {arg.TARGET_SPEED_MAX:g}] (default: the preset's; best 8.5, the "
                        "paper's pace; paper 14, the paper's label)")
    p.add_argument("--laps", type=arg.positive_int, default=None, help="laps per controller (default 1)")
    p.add_argument("--seed", type=arg.seed, default=None, help=f"seed of the first lap, in [0, {SEED_MAX}]; lap i "
                                                            "uses seed + i (default 0)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/race"), help="output directory")
    p.add_argument("--batch", type=arg.positive_int, default=1,
                   help="laps per batched (vmapped) call; raise it on a GPU (default 1)")
    p.add_argument("--perturb", action="store_true", default=None,
                   help="perturb the gates per lap within the AlphaPilot bounds")
    p.add_argument("--camera-tilt", type=arg.float_in(0.0, CAMERA_TILT_MAX_DEG, unit="deg"), default=None,
                   metavar="DEG", help="the onboard camera tilted up on its mount by DEG degrees, in "
                   f"[0, {CAMERA_TILT_MAX_DEG:g}], for both controllers, the detector and the measure (default 0, the "
                   "paper's); the packaged learned pixel models are trained for 0, so fly --pixel-model projection")
    p.add_argument("--max-time", type=arg.float_in(0.0, MAX_TIME_S, lo_open=True, unit="s"), default=None,
                   help=f"timeout per lap, s, in (0, {MAX_TIME_S:g}] (default {LAP_TIME_LIMIT_S:g})")
    _setting(p, "--model-latency", "model_latency_ticks", "ticks of actuation latency the controller's model "
             "predicts across, in [0, 3] (0: none)", type=arg.int_in(0, 3))
    _setting(p, "--disturbance-observer", "disturbance_time_constant_s", "s: the controller's model learns an "
             "external push (wind, model error) with this time constant, in [0.025, 60]", type=arg.float_in(0.025, 60))
    arg.add_fault_flags(p)
    p.set_defaults(func=_cmd_race, validate=_seed_range, precheck=_check_race)


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
