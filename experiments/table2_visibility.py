"""Tables II and III and Fig. 6 of the paper: target visibility, lap time and smoothness of PixelMPC against
nominal MPPI over t_f in {1, 2} s x c_pixel in {3e6, 6e6, 9e6}, 10 races per cell, at the paper's 14 m/s label and
at its pace (8.5 m/s, where our nominal lap matches the paper's), with the ``best`` preset beside the grid.

    python experiments/table2_visibility.py --out experiments/results/table2 [--laps 10] [--seed 200] [--quick]
    python experiments/table2_visibility.py --pixel-model projection --out experiments/results/table2_projection

Writes REPORT.md (ours beside the paper's), results.json, summary.json, visibility.png, smoothness.png.
Interrupted runs resume: finished cells are kept. The frontier gains need a frontier run (``pixelmpc reproduce``
reads them off its ``frontier`` part).
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.paper import visibility_experiment


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/table2"))
    parser.add_argument("--laps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=200, help="seed of the first lap (default 200)")
    parser.add_argument("--pixel-model", choices=("dof", "projection"), default="dof")
    parser.add_argument("--quick", action="store_true", help="nominal MPPI and the presets at the pace only")
    args = parser.parse_args(argv)
    if args.laps <= 0 or args.seed < 0:
        parser.error("--laps must be positive and --seed non-negative")
    rows = visibility_experiment(args.out, laps=args.laps, pixel_model=args.pixel_model, quick=args.quick,
                                 seed=args.seed)
    print((args.out / "REPORT.md").read_text())
    return rows


if __name__ == "__main__":
    main()
