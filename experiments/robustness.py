"""Robustness to the faults a real flight brings (issue 28): nominal MPPI and PixelMPC (the ``best`` preset) at the
paper's pace under wind, model error, latency, IMU and detector faults and map errors, each alone at a moderate and
a severe level and all moderate ones at once, on the particle filter (and at the moderate level on the true state).

    python experiments/robustness.py --out DIR [--quick] [--levers [NAME ...]] [--reuse FOLDER ...]

--levers: model, filter, gate, bias, robust (no name: all).

Writes REPORT.md (success at a glance, every cell, the fault levels and their reasons), robustness.json,
robustness.png and results.json. Interrupted runs resume: finished cells are kept.
"""

import argparse
from pathlib import Path

from pixelmpc_jax.apps.robustness import LEVER_SETS, robustness_experiment


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/robustness"))
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: 2 laps per cell, the moderate level on the particle filter only")
    parser.add_argument("--levers", nargs="*", choices=tuple(LEVER_SETS), default=None,
                        help="also fly PixelMPC's moderate filter cells with each set of levers on, apart: model "
                             "(the disturbance observer, the latency in the model), filter (the filter's guards), "
                             "gate and bias (the guards' two halves alone), robust (model and gate at once); no name: "
                             "all five")
    parser.add_argument("--reuse", type=Path, nargs="*", default=(),
                        help="other grids' output folders whose finished fault-free cells are copied, not flown")
    parser.add_argument("--report-only", action="store_true", help="write the report of the finished cells only")
    args = parser.parse_args(argv)
    levers = () if args.levers is None else tuple(args.levers or LEVER_SETS)
    rows = robustness_experiment(args.out, quick=args.quick, levers=levers, reuse=args.reuse,
                                 run=not args.report_only)
    print((args.out / "REPORT.md").read_text())
    return rows


if __name__ == "__main__":
    main()
