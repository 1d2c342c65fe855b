"""Table IV, the straight-lane test, Fig. 6 and Fig. 9 of the paper: nominal MPPI against PixelMPC flying on the
particle filter's estimate: success rate and lap time over 25 laps at the paper's 14 and 16 m/s labels (nominal MPPI
and the ``paper`` preset) and at their paces (8.5 and 9.1 m/s, with the ``best`` preset too), and the maximum
position covariance over 25 runs of a straight lane at 20 m/s and at its pace.

    python experiments/table4_estimation.py --out experiments/results/table4 [--laps 25] [--seed 200] [--quick]

Writes REPORT.md (ours beside the paper's), results.json, summary.json, fig6_pf.png and fig9_<cell>.png.
Interrupted runs resume: finished cells are kept.
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.estimation import estimation_experiment


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/table4"))
    parser.add_argument("--laps", type=int, default=25)
    parser.add_argument("--seed", type=int, default=200, help="seed of the first lap (default 200)")
    parser.add_argument("--quick", action="store_true", help="the 16 m/s pace only (and the straight lane's)")
    parser.add_argument("--no-straight", action="store_true", help="skip the straight-lane test")
    args = parser.parse_args(argv)
    if args.laps <= 0 or args.seed < 0:
        parser.error("--laps must be positive and --seed non-negative")
    result = estimation_experiment(args.out, laps=args.laps, quick=args.quick, straight=not args.no_straight,
                                   seed=args.seed)
    print((args.out / "REPORT.md").read_text())
    return result


if __name__ == "__main__":
    main()
