"""Table IV, the straight-lane test and Fig. 9 of the paper: nominal MPPI against PixelMPC (t_f = 1 s,
c_pixel = 9e6) flying on the particle filter's estimate: success rate and lap time over 25 laps at 14 and
16 m/s, and the maximum position covariance over 25 runs of a straight lane at 20 m/s.

    python experiments/table4_estimation.py --out experiments/results/table4 [--laps 25] [--quick]

Writes REPORT.md (ours beside the paper's), results.json, summary.json and fig9_<cell>.png.
Interrupted runs resume: finished cells are kept.
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.estimation import estimation_experiment


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/table4"))
    parser.add_argument("--laps", type=int, default=25)
    parser.add_argument("--quick", action="store_true", help="16 m/s only (and the straight lane)")
    parser.add_argument("--no-straight", action="store_true", help="skip the straight-lane test")
    args = parser.parse_args(argv)
    if args.laps <= 0:
        parser.error("--laps must be positive")
    result = estimation_experiment(args.out, laps=args.laps, quick=args.quick, straight=not args.no_straight)
    print((args.out / "REPORT.md").read_text())
    return result


if __name__ == "__main__":
    main()
