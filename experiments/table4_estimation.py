"""Table IV, the straight-lane test, Fig. 6 and Fig. 9 of the paper: nominal MPPI against PixelMPC flying on the
particle filter's estimate: success rate and lap time over 25 laps at the paper's 14 and 16 m/s labels (nominal MPPI
and the ``paper`` preset) and at their paces (8.5 and 9.1 m/s, with the ``best`` preset too), and the maximum
position covariance over 25 runs of a straight lane at 20 m/s and at its pace.

    python experiments/table4_estimation.py --out experiments/results/table4 [--laps 25] [--seed 200] [--quick]

Writes REPORT.md (ours beside the paper's), results.json, summary.json, fig6_pf.png and fig9_<cell>.png.
Interrupted runs resume: finished cells are kept.

A thin script: the same as ``pixelmpc experiment table4`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/experiments/estimation.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "table4", *sys.argv[1:]]))
