"""The ``pixelmpc`` command: parses arguments and calls library functions (no logic of its own)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _writable_dir(path: str) -> Path:
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise argparse.ArgumentTypeError(f"output directory {path!r} cannot be written: {err}") from err
    return out


def _cmd_version(args) -> int:
    import jax

    from pixelmpc_jax import __version__

    print(f"pixelmpc-jax {__version__} (jax {jax.__version__}, devices: {jax.devices()})")
    return 0


def _cmd_demo(args) -> int:
    import jax.numpy as jnp
    import numpy as np

    from pixelmpc_jax.dynamics import quadrotor
    from pixelmpc_jax.sim.waypoint import fly_to_waypoint, waypoint_config

    start = quadrotor.hover_state((0.0, 0.0, 2.0))
    waypoint = jnp.asarray([args.distance, 0.0, 2.0, 0.0])
    config = waypoint_config(num_samples=args.samples)
    print(f"MPPI hover-to-waypoint: {args.distance:.1f} m, N={config.num_samples}, T={config.horizon}, "
          f"{args.seconds:.1f} s at {1 / config.dt:.0f} Hz ...")
    flight = fly_to_waypoint(start, waypoint, num_ticks=int(round(args.seconds / config.dt)), seed=args.seed,
                             config=config)
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
        (out / "demo.json").write_text(json.dumps(summary, indent=2))
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
    return 0 if error[-1] < 0.5 else 1


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from err
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from err
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _cmd_race(args) -> int:
    from pixelmpc_jax.sim import metrics, race

    course = "the AlphaPilot course" if args.course == "alphapilot" else "the straight lane"
    print(f"{args.controller} racing {course} at {args.speed:g} m/s: {args.laps} lap(s), "
          f"seeds {args.seed}..{args.seed + args.laps - 1}, output {args.out}")
    results = race.run_laps(controller=args.controller, speed=args.speed, laps=args.laps, seed=args.seed,
                            out=args.out, batch_size=args.batch, perturb=args.perturb,
                            max_time_s=args.max_time, temperature=args.temperature,
                            pixel_model=args.pixel_model, detector=args.detector, t_f=args.t_f,
                            c_pixel=args.c_pixel, estimator=args.estimator, video=args.video,
                            course=args.course)
    if not results["laps"]:
        print("no lap finished")
        return 1
    print(metrics.format_table(results["laps"], results["aggregate"]))
    print(f"wrote {args.out / 'metrics.json'} and {args.out / 'trajectories.png'}")
    return 0


def _cmd_render(args) -> int:
    from pixelmpc_jax.perception.figures import write_render_figures

    print(f"rendering the AlphaPilot course: frames, exact and Farneback flow -> {args.out}")
    results = write_render_figures(args.out)
    for name, entry in results.items():
        print(f"  {name}: Farneback vs exact AEE {entry['aee_px']:.2f} px, written to {entry['path']}")
    return 0


def _cmd_collect(args) -> int:
    from pixelmpc_jax.learn.dataset import run_collect

    run_collect(args.out, laps=args.laps, seed=args.seed, max_lap_time_s=args.max_lap_time,
                supersample=args.supersample, paper=args.paper, excitation=args.excitation,
                excitation_pulse_rad_s=args.excitation_pulse, excitation_dither_rad_s=args.excitation_dither)
    return 0


def _cmd_train(args) -> int:
    from pixelmpc_jax.learn.evaluate import run_train

    run_train(args.data, out_dir=args.out, steps=args.steps, batch_size=args.batch_size,
              learning_rate=args.learning_rate, seed=args.seed, resume=args.resume, ship=args.ship,
              loss=args.loss, input=args.input)
    return 0


def _cmd_evaluate(args) -> int:
    from pixelmpc_jax.learn.evaluate import run_evaluate

    run_evaluate(weights=args.weights, data_dir=args.data, out_dir=args.out, horizon=args.horizon)
    return 0


def _cmd_bench(args) -> int:
    from pixelmpc_jax.bench import run_bench

    run_bench(args.out, quick=args.quick)
    return 0


def _cmd_reproduce(args) -> int:
    from pixelmpc_jax.reproduce import reproduce

    reproduce(args.parts, args.out, quick=args.quick)
    print(f"report: {args.out / 'REPORT.md'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pixelmpc",
        description="PixelMPC in JAX: perception-aware MPPI with Deep Optical Flow dynamics.",
    )
    parser.add_argument("--distributed", action="store_true",
                        help="join a multi-host run (jax.distributed.initialize: the cluster is detected under "
                             "SLURM, Open MPI or on TPU; elsewhere set JAX_COORDINATOR_ADDRESS, "
                             "JAX_NUM_PROCESSES, JAX_PROCESS_ID); run the same command on every host")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("version", help="print the package, JAX version and devices")
    p.set_defaults(func=_cmd_version)

    p = sub.add_parser("demo", help="MPPI flies the quadrotor model from hover to a waypoint and holds it")
    p.add_argument("--distance", type=float, default=5.0, help="waypoint distance ahead, m (default 5)")
    p.add_argument("--seconds", type=float, default=4.0, help="flight time, s (default 4)")
    p.add_argument("--samples", type=int, default=512, help="MPPI samples (default 512)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=_writable_dir, default=None, help="write demo.json and demo.png here")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("render", help="render course frames with their exact and Farneback optical flow")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/render"), help="output directory")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("collect", help="fly nominal MPPI laps and store frames' Farneback flow (DOF data)")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_data"), help="dataset directory")
    p.add_argument("--laps", type=_positive_int, default=4, help="laps, speeds spread over 6-14 m/s (default 4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-lap-time", type=_positive_float, default=10.0, help="seconds flown per lap (default 10)")
    p.add_argument("--supersample", type=_positive_int, default=1, help="render supersampling (default 1)")
    p.add_argument("--paper", action="store_true", help="the paper's size: 10 laps of up to 30 s")
    p.add_argument("--excitation", action="store_true",
                   help="train laps add held body-rate pulses and dither to the nominal MPPI's command")
    p.add_argument("--excitation-pulse", type=_positive_float, default=1.5,
                   help="pulse amplitude, uniform in +- this per axis, rad/s (default 1.5)")
    p.add_argument("--excitation-dither", type=_positive_float, default=0.3,
                   help="std of the per-tick rate dither, rad/s (default 0.3)")
    p.set_defaults(func=_cmd_collect)

    p = sub.add_parser("train", help="train the DOF network on a collected dataset (resumable)")
    p.add_argument("--data", type=Path, required=True, help="dataset directory from `pixelmpc collect`")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_train"))
    p.add_argument("--steps", type=_positive_int, default=20000)
    p.add_argument("--batch-size", type=_positive_int, default=4096, help="pixels per step (default 4096)")
    p.add_argument("--learning-rate", type=_positive_float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    p.add_argument("--loss", choices=["polar", "endpoint"], default="polar",
                   help="polar: the paper's MSE on (l, theta) (default); endpoint: squared flow-vector error")
    p.add_argument("--input", choices=["command", "flown"], default="command",
                   help="the network's control input: command, the paper's (the rates commanded at the frame's "
                        "tick, default), or flown (the rates flown over the frame: what the MPC's model means)")
    p.add_argument("--ship", action="store_true", help="also copy the weights into the installed package")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("evaluate", help="DOF accuracy: AEE, baselines, multi-step error, figures")
    p.add_argument("--weights", type=Path, default=None, help="weights file (default: the shipped weights)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset directory (default: collect a small seeded held-out set)")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/dof_eval"))
    p.add_argument("--horizon", type=_positive_int, default=80, help="multi-step horizon (default 80)")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("bench", help="runtime harness: Table I, controller scaling, peers, matmul roofline")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/bench"))
    p.add_argument("--quick", action="store_true", help="paper-size controller rows and the pytorch-mppi peer only")
    p.set_defaults(func=_cmd_bench)

    from pixelmpc_jax.reproduce import CHOICES

    p = sub.add_parser("reproduce", help="run the paper's experiments and benchmark into one report (resumable)")
    p.add_argument("parts", nargs="*", default=["all"], choices=CHOICES, metavar="PART",
                   help=f"what to reproduce (default all): {', '.join(CHOICES)}")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/reproduce"), help="output directory")
    p.add_argument("--quick", action="store_true",
                   help="a small version in minutes (2 laps per cell, the bench's quick rows, the tables only)")
    p.set_defaults(func=_cmd_reproduce)

    from pixelmpc_jax.sim.race import CONTROLLERS, COURSES

    p = sub.add_parser("race", help="fly laps of the AlphaPilot course in the closed loop")
    p.add_argument("--controller", choices=CONTROLLERS, default="pixelmpc",
                   help="pixelmpc (default) or mppi, the paper's nominal baseline")
    p.add_argument("--pixel-model", choices=("dof", "projection"), default="dof",
                   help="PixelMPC's pixel model: the shipped DOF network (default) or PAMPC-style projection")
    p.add_argument("--detector", choices=("geometry", "image"), default="geometry",
                   help="target detection: projection of the true gate (default) or OpenCV on rendered frames")
    p.add_argument("--course", choices=COURSES, default="alphapilot",
                   help="alphapilot (default) or straight (five gates 20 m apart, the paper's straight lane)")
    p.add_argument("--estimator", choices=("truth", "pf"), default="truth",
                   help="state the controller acts on: ground truth (default) or the particle filter")
    p.add_argument("--video", action="store_true",
                   help="write OUT/onboard.mp4 of the first lap: predicted (green) and actual (red) target pixel")
    p.add_argument("--t-f", type=float, default=1.0, help="PixelMPC pixel-cost horizon t_f, s (default 1)")
    p.add_argument("--c-pixel", type=float, default=9e6, help="PixelMPC pixel-cost weight (default 9e6)")
    p.add_argument("--speed", type=_positive_float, default=14.0, help="target speed, m/s (default 14)")
    p.add_argument("--laps", type=_positive_int, default=1, help="number of laps (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first lap; lap i uses seed + i")
    p.add_argument("--out", type=_writable_dir, default=Path("runs/race"), help="output directory")
    p.add_argument("--batch", type=_positive_int, default=1,
                   help="laps per batched (vmapped) call; raise it on a GPU (default 1)")
    p.add_argument("--perturb", action="store_true", help="perturb the gates per lap within the AlphaPilot bounds")
    p.add_argument("--max-time", type=_positive_float, default=60.0, help="timeout per lap, s (default 60)")
    p.add_argument("--temperature", type=_positive_float, default=None, help="MPPI lambda (default: tuned)")
    p.set_defaults(func=_cmd_race)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    if args.distributed:
        _initialize_distributed()
    return int(args.func(args) or 0)


def _initialize_distributed() -> None:
    """``jax.distributed.initialize`` from the cluster's environment, or from the JAX_* variables."""
    import os

    import jax

    kwargs = {}
    if os.environ.get("JAX_COORDINATOR_ADDRESS"):
        missing = [name for name in ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID") if name not in os.environ]
        if missing:
            raise SystemExit(f"--distributed with JAX_COORDINATOR_ADDRESS also needs {' and '.join(missing)}")
        kwargs = {"coordinator_address": os.environ["JAX_COORDINATOR_ADDRESS"],
                  "num_processes": int(os.environ["JAX_NUM_PROCESSES"]),
                  "process_id": int(os.environ["JAX_PROCESS_ID"])}
    jax.distributed.initialize(**kwargs)
    print(f"process {jax.process_index()} of {jax.process_count()}: {jax.local_device_count()} local and "
          f"{jax.device_count()} global device(s)", flush=True)


if __name__ == "__main__":
    sys.exit(main())
