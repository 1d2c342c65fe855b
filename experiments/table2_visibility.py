"""Tables II and III and Fig. 8 of the paper: target visibility, lap time and smoothness of PixelMPC
against nominal MPPI at 14 m/s, over t_f in {1, 2} s x c_pixel in {3e6, 6e6, 9e6}, 10 races per cell.

    python experiments/table2_visibility.py --out experiments/results/table2 [--laps 10] [--quick]
    python experiments/table2_visibility.py --pixel-model projection --out experiments/results/table2_projection

Writes REPORT.md (ours beside the paper's), results.json, summary.json, visibility.png, smoothness.png.
Interrupted runs resume: finished cells are kept.
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.paper import visibility_experiment


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/table2"))
    parser.add_argument("--laps", type=int, default=10)
    parser.add_argument("--pixel-model", choices=("dof", "projection"), default="dof")
    parser.add_argument("--quick", action="store_true", help="nominal MPPI and the best PixelMPC cell only")
    args = parser.parse_args(argv)
    rows = visibility_experiment(args.out, laps=args.laps, pixel_model=args.pixel_model, quick=args.quick)
    print((args.out / "REPORT.md").read_text())
    return rows


if __name__ == "__main__":
    main()
