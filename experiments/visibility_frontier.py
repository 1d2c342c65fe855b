"""The speed frontier (issue 15): PixelMPC's avoidable low-visibility time against nominal MPPI flown slower.

Flies nominal MPPI at several target speeds (default 5, 6, 7, 8, 10, 14 m/s) and the PixelMPC cells (the
paper's L1 cost and the border cost, c_pixel 9e6, projection and DOF pixel models, 8 m/s, t_f 1 s), then
writes DIR/frontier.json, DIR/REPORT.md and DIR/frontier.png (see pixelmpc_jax/apps/frontier.py).
``--quick``: nominal 6, 8, 10 m/s and the border-cost cells only, 4 laps each. Resumable per cell: an
interrupted run (Ctrl-C) keeps its finished cells and exits with status 130; run it again to go on.

    python experiments/visibility_frontier.py --quick --out runs/frontier_quick
    python experiments/visibility_frontier.py --out runs/frontier --laps 10
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

from pixelmpc_jax.apps import frontier as frontier_lib


def spec_from_args(args) -> frontier_lib.FrontierSpec:
    spec = frontier_lib.quick_spec() if args.quick else frontier_lib.default_spec()
    changes = {}
    if args.cells == "best":
        changes["cells"] = frontier_lib.best_cells()
    if args.speeds:
        changes["nominal_speeds"] = tuple(sorted(set(args.speeds)))
    if args.laps is not None:
        changes["laps"] = args.laps
    return dataclasses.replace(spec, **changes)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="output folder (resumable)")
    parser.add_argument("--laps", type=int, default=None, help="laps per point (default 10; 4 with --quick)")
    parser.add_argument("--seed", type=int, default=0, help="first seed; lap i uses seed + i (default 0)")
    parser.add_argument("--quick", action="store_true", help="3 nominal speeds and the 2 border-cost cells, 4 laps")
    parser.add_argument("--cells", choices=("all", "best"), default="all",
                        help="PixelMPC cells: all (the paper's L1 and the border cost, both pixel models; default) or "
                             "best (the border cost at each model's best weight)")
    parser.add_argument("--speeds", type=float, nargs="+", default=None, metavar="M_S",
                        help="nominal target speeds in m/s (at least 2; default 5 6 7 8 10 14, quick 6 8 10)")
    parser.add_argument("--course", default=None, metavar="alphapilot|straight|FILE",
                        help="the course every cell flies: a name or a course file (`pixelmpc course`; default "
                             "alphapilot)")
    args = parser.parse_args(argv)
    if args.course is not None and args.course not in ("alphapilot", "straight") and not Path(args.course).is_file():
        parser.error(f"--course: no course {args.course!r}: choose alphapilot or straight, or give a course file")
    if args.laps is not None and args.laps <= 0:
        parser.error(f"--laps must be a positive integer, got {args.laps}")
    if args.seed < 0:
        parser.error(f"--seed must be a non-negative integer, got {args.seed}")
    if args.speeds is not None:
        bad = [s for s in args.speeds if not (math.isfinite(s) and s > 0)]
        if bad:
            parser.error(f"--speeds must be positive finite numbers of m/s, got {' '.join(map(str, bad))}")
        if len(set(args.speeds)) < 2:
            parser.error("--speeds needs at least 2 different speeds to draw a frontier")
    if args.course is not None:
        from pixelmpc_jax.apps.race import make_course

        try:
            make_course(args.course)
        except ValueError as err:
            parser.error(f"--course: {err}")
    spec = spec_from_args(args)
    try:
        frontier = frontier_lib.run_frontier(spec.nominal_speeds, spec.cells, args.out, laps=spec.laps,
                                             seed=args.seed, course=args.course)
    except KeyboardInterrupt:
        print(f"\ninterrupted: the finished cells are kept in {args.out}; run the same command again to resume",
              file=sys.stderr)
        return 130
    print(frontier_lib.report(frontier))
    return 0


if __name__ == "__main__":
    sys.exit(main())
