"""``pixelmpc course``: a seeded race course file (:func:`~pixelmpc_jax.world.course.generate_course`), for
``pixelmpc race --course`` and the frontier."""

from __future__ import annotations

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX


def add_course(sub) -> None:
    """``pixelmpc course``: a seeded course file."""
    p = sub.add_parser("course", help="generate a seeded race course (a file for `race --course` and the frontier)")
    p.add_argument("--seed", type=arg.seed, default=0, help=f"the course's seed, in [0, {SEED_MAX}] (default 0)")
    p.add_argument("--gates", type=arg.int_in(2, 30), default=8, help="number of gates, in [2, 30] (default 8)")
    p.add_argument("--out", type=arg.output_file, required=True, help="the course file to write (JSON)")
    p.set_defaults(func=_cmd_course)


def _cmd_course(args) -> int:
    from pixelmpc_jax.world import course

    data = course.generate_course(args.seed, num_gates=args.gates)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    course.write_course(data, args.out)
    track = course.load_course(args.out)
    print(f"wrote {args.out}: {track.num_gates} gates, {float(track.path_s[-1]):.0f} m of path (seed {args.seed})")
    return 0
