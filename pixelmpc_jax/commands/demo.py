"""``pixelmpc demo``: MPPI flies the quadrotor model from hover to a waypoint and holds it
(:func:`~pixelmpc_jax.apps.racing.waypoint.run_demo`)."""

from __future__ import annotations

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX
from pixelmpc_jax.commands import EXIT_FAILED
from pixelmpc_jax.control.mppi_checks import NUM_SAMPLES_RANGE


def add_demo(sub) -> None:
    """``pixelmpc demo``: MPPI flying the model to a waypoint."""
    p = sub.add_parser("demo", help="MPPI flies the quadrotor model from hover to a waypoint and holds it")
    p.add_argument("--distance", type=arg.float_in(-50.0, 50.0, unit="m"), default=5.0,
                   help="waypoint distance ahead, m, in [-50, 50] (default 5)")
    p.add_argument("--seconds", type=arg.float_in(0.025, 600.0, unit="s"), default=4.0,
                   help="flight time, s, in [0.025, 600] (default 4)")
    p.add_argument("--samples", type=arg.int_range(NUM_SAMPLES_RANGE), default=512,
                   help=f"MPPI samples, in {NUM_SAMPLES_RANGE.interval} (default 512)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--out", type=arg.writable_dir, default=None, help="write demo.json and demo.png here")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    from pixelmpc_jax.apps.racing.waypoint import run_demo

    summary = run_demo(args.distance, args.seconds, args.samples, args.seed, args.out)
    return 0 if summary["final_error_m"] < 0.5 else EXIT_FAILED
