"""``pixelmpc collect``: the DOF dataset, nominal MPPI laps with their frames' Farneback flow
(:func:`~pixelmpc_jax.learn.collect.run_collect`). The speeds' and the camera tilt's flags are made from
:class:`~pixelmpc_jax.learn.collect.CollectConfig`'s fields (their ranges, their help), so the flag and the
configuration refuse the same values."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX
from pixelmpc_jax.commands import EXIT_INTERRUPTED
from pixelmpc_jax.learn.collect import CollectConfig
from pixelmpc_jax.settings import MAX_TIME_RANGE

_DEFAULT = CollectConfig()
COLLECT_FLAGS = (
    arg.setting_flag("--speed-min", _DEFAULT, "speed_min", metavar="M_S"),
    arg.setting_flag("--speed-max", _DEFAULT, "speed_max", metavar="M_S"),
    arg.setting_flag("--camera-tilt", _DEFAULT, "camera_tilt_deg", metavar="DEG"),
)


def add_collect(sub) -> None:
    """``pixelmpc collect``: the DOF dataset."""
    p = sub.add_parser("collect", help="fly nominal MPPI laps and store frames' Farneback flow (DOF data)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/dof_data"), help="dataset directory")
    p.add_argument("--laps", type=arg.positive_int, default=4,
                   help="laps, speeds spread over --speed-min to --speed-max (default 4)")
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
    for flag in COLLECT_FLAGS:
        flag.add_to(p, help=f"{flag.help} (default {getattr(_DEFAULT, flag.field):g})")
    p.set_defaults(func=_cmd_collect, validate=_check_collect)


def _check_collect(args) -> str | None:
    """The seeds of the laps, and the speeds in order (a command's ``validate``: the problem, or None)."""
    speeds = {field: getattr(_DEFAULT, field) for field in ("speed_min", "speed_max")}
    speeds.update(arg.fields_given(args, COLLECT_FLAGS[:2]))
    if speeds["speed_min"] > speeds["speed_max"]:
        return (f"argument --speed-min: must be at most --speed-max, got {speeds['speed_min']:g} > "
                f"{speeds['speed_max']:g} m/s")
    return arg.seed_range(args)


def _cmd_collect(args) -> int:
    from pixelmpc_jax.learn.collect import run_collect

    manifest = run_collect(args.out, laps=args.laps, seed=args.seed, max_lap_time_s=args.max_lap_time,
                           supersample=args.supersample, paper=args.paper, excitation=args.excitation,
                           excitation_pulse_rad_s=args.excitation_pulse,
                           excitation_dither_rad_s=args.excitation_dither, **arg.fields_given(args, COLLECT_FLAGS))
    return EXIT_INTERRUPTED if manifest.get("interrupted") else 0
