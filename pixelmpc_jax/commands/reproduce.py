"""``pixelmpc reproduce``: the paper's experiments and the benchmark into one report, resumable
(:func:`~pixelmpc_jax.apps.experiments.reproduce.reproduce`)."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg


def add_reproduce(sub) -> None:
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


def _cmd_reproduce(args) -> int:
    from pixelmpc_jax.apps.experiments.reproduce import reproduce

    reproduce([args.parts] if isinstance(args.parts, str) else args.parts, args.out, quick=args.quick)
    print(f"report: {args.out / 'REPORT.md'}")
    return 0
