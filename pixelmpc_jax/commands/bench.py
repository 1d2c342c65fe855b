"""``pixelmpc bench JOB``: the runtime harness (``suite``: Table I, the controller step and its scaling, the closed
loop, the peers, the matmul limit), the device suite (``device``: what a GPU is asked to show, in one run) and the
harness's single measurements on their own. The ``benchmarks/`` scripts call these jobs."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg


def add_bench(sub) -> None:
    """``pixelmpc bench``: its jobs as sub-commands."""
    p = sub.add_parser("bench", help="runtime harness: suite (Table I, controller scaling, peers, matmul roofline), "
                                     "device (the GPU suite), mppi-step, closed-loop, pf-step, eskf-step, render")
    jobs = p.add_subparsers(dest="bench", metavar="JOB", required=True)
    for add in (_add_suite, _add_device, _add_mppi_step, _add_closed_loop, _add_pf_step, _add_eskf_step, _add_render):
        add(jobs)


def _add_suite(jobs) -> None:
    p = jobs.add_parser("suite", help="the harness: Table I, the controller step and its scaling, the closed loop's "
                                      "tick, peers, the matmul limit (bench.json, bench.md, scaling.png)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/bench"), help="output directory")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true",
                      help="paper-size controller rows and the pytorch-mppi peer only (< 5 min on 2 cores)")
    size.add_argument("--smoke", action="store_true", help="tiny sizes, 3 repeats (a schema check)")
    p.set_defaults(func=_cmd_suite)


def _cmd_suite(args) -> int:
    from pixelmpc_jax.apps.bench.suite import run_bench

    run_bench(args.out, quick=args.quick, smoke=args.smoke)
    return 0


def _add_device(jobs) -> None:
    from pixelmpc_jax.apps.bench.device import LAP_SECONDS_LIMIT, DeviceSuiteConfig
    from pixelmpc_jax.timing import CONTROL_DT

    default = DeviceSuiteConfig()
    p = jobs.add_parser("device", help="the device suite, under 8 min on one GPU: the DOF, vdof and nominal MPPI "
                                       "steps at 512 x 80, the DOF step from 512 to 16,384 samples, a batch of 64 "
                                       "laps of the best race (device.json, device_scaling.png)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/bench_device"), help="output directory")
    p.add_argument("--max-samples", type=arg.positive_int, default=default.max_samples,
                   help=f"the scaling's largest N, 512 times a power of two (default {default.max_samples})")
    p.add_argument("--repeats", type=arg.positive_int, default=default.repeats,
                   help=f"timed calls of each step (default {default.repeats})")
    p.add_argument("--laps", type=arg.positive_int, default=default.laps,
                   help=f"laps of the race, flown in one batch (default {default.laps})")
    p.add_argument("--lap-seconds", type=arg.float_in(CONTROL_DT, LAP_SECONDS_LIMIT, unit="s"),
                   default=default.lap_seconds, help=f"each lap's time limit, s (default {default.lap_seconds:g})")
    p.set_defaults(func=_cmd_device, validate=_check_device)


def _device_config(args):
    from pixelmpc_jax.apps.bench.device import DeviceSuiteConfig

    return DeviceSuiteConfig(max_samples=args.max_samples, repeats=args.repeats, laps=args.laps,
                             lap_seconds=args.lap_seconds)


def _check_device(args) -> str | None:
    try:
        _device_config(args)
    except ValueError as err:
        return str(err)
    return None


def _cmd_device(args) -> int:
    from pixelmpc_jax.apps.bench.device import run_device_suite

    run_device_suite(args.out, _device_config(args))
    return 0


def _add_mppi_step(jobs) -> None:
    from pixelmpc_jax.apps.bench.mppi_step import COSTS
    from pixelmpc_jax.control.mppi_checks import NUM_SAMPLES_RANGE

    p = jobs.add_parser("mppi-step", help="median step time of the quadrotor MPPI (the paper's N=512, T=80, K=1)")
    p.add_argument("--samples", type=arg.int_range(NUM_SAMPLES_RANGE), default=512,
                   help=f"samples N, in {NUM_SAMPLES_RANGE.interval} (default 512)")
    p.add_argument("--horizon", type=arg.int_in(1, 10_000), default=80, help="horizon T, in [1, 10000] (default 80)")
    p.add_argument("--repeats", type=arg.positive_int, default=50, help="timed steps (default 50)")
    p.add_argument("--cost", choices=COSTS, default=COSTS[0],
                   help="racing: Eq. (19) on the AlphaPilot course (default); waypoint: the demo's cost")
    p.set_defaults(func=_cmd_mppi_step)


def _cmd_mppi_step(args) -> int:
    from pixelmpc_jax.apps.bench.mppi_step import run_mppi_step

    run_mppi_step(args.samples, args.horizon, args.repeats, args.cost)
    return 0


def _add_closed_loop(jobs) -> None:
    from pixelmpc_jax.apps.bench.closed_loop import MODES

    p = jobs.add_parser("closed-loop", help="the closed loop's tick: PixelMPC and nominal MPPI flying a lap as "
                                            "`pixelmpc race` does, wall time per tick flown")
    p.add_argument("--mode", choices=MODES, default="quick",
                   help="full: one AlphaPilot lap per controller; quick: 2.5 s of it (default); smoke: tiny")
    p.add_argument("--repeats", type=arg.positive_int, default=None, help="timed laps per row (default 3; smoke 2)")
    p.set_defaults(func=_cmd_closed_loop)


def _cmd_closed_loop(args) -> int:
    from pixelmpc_jax.apps.bench.closed_loop import run_closed_loop

    run_closed_loop(args.mode, args.repeats)
    return 0


def _add_pf_step(jobs) -> None:
    p = jobs.add_parser("pf-step", help="median time of one particle-filter tick (the paper's 6,400 particles)")
    p.add_argument("--particles", type=arg.int_in(1, 2**22), default=6400,
                   help="particles, in [1, 2^22] (default 6400)")
    p.add_argument("--repeats", type=arg.positive_int, default=50, help="timed ticks (default 50)")
    p.set_defaults(func=_cmd_pf_step)


def _cmd_pf_step(args) -> int:
    from pixelmpc_jax.apps.bench.particle_filter_step import run_pf_step

    run_pf_step(args.particles, args.repeats)
    return 0


def _add_eskf_step(jobs) -> None:
    p = jobs.add_parser("eskf-step", help="median time of one error-state Kalman filter tick (its bar: 1 ms)")
    p.add_argument("--repeats", type=arg.positive_int, default=200, help="timed ticks (default 200)")
    p.set_defaults(func=_cmd_eskf_step)


def _cmd_eskf_step(args) -> int:
    from pixelmpc_jax.apps.bench.eskf_step import run_eskf_step

    run_eskf_step(args.repeats)
    return 0


def _add_render(jobs) -> None:
    p = jobs.add_parser("render", help="render throughput: frames per second of the ray-caster at 204 x 153, batched")
    p.add_argument("--batch", type=arg.positive_int, nargs="+", default=[8, 32], metavar="B",
                   help="frames per batched call (default 8 32)")
    p.add_argument("--repeats", type=arg.positive_int, default=10, help="timed calls (default 10)")
    p.add_argument("--supersample", type=arg.int_in(1, 9, odd=True), default=3,
                   help="render supersampling, odd, in [1, 9] (default 3)")
    p.set_defaults(func=_cmd_render)


def _cmd_render(args) -> int:
    from pixelmpc_jax.apps.bench.render_throughput import run_render_throughput

    run_render_throughput(tuple(args.batch), args.repeats, args.supersample)
    return 0
