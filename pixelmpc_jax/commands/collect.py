"""``pixelmpc collect``: the DOF dataset, nominal MPPI laps with their frames' Farneback flow
(:func:`~pixelmpc_jax.learn.collect.run_collect`)."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX
from pixelmpc_jax.commands import EXIT_INTERRUPTED
from pixelmpc_jax.settings import MAX_TIME_RANGE


def add_collect(sub) -> None:
    """``pixelmpc collect``: the DOF dataset."""
    p = sub.add_parser("collect", help="fly nominal MPPI laps and store frames' Farneback flow (DOF data)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/dof_data"), help="dataset directory")
    p.add_argument("--laps", type=arg.positive_int, default=4, help="laps, speeds spread over 6-14 m/s (default 4)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"seed of lap 0, in [0, {SEED_MAX}]; lap i uses seed + i")
    p.add_argument("--max-lap-time", type=arg.float_range(MAX_TIME_RANGE), default=10.0,
                   help=f"seconds flown per lap, in {MAX_TIME_RANGE.interval} (default 10)")
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


def _cmd_collect(args) -> int:
    from pixelmpc_jax.learn.collect import run_collect

    manifest = run_collect(args.out, laps=args.laps, seed=args.seed, max_lap_time_s=args.max_lap_time,
                           supersample=args.supersample, paper=args.paper, excitation=args.excitation,
                           excitation_pulse_rad_s=args.excitation_pulse,
                           excitation_dither_rad_s=args.excitation_dither)
    return EXIT_INTERRUPTED if manifest.get("interrupted") else 0
