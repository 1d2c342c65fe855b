"""The speed frontier (issue 15): PixelMPC's avoidable low-visibility time against nominal MPPI flown slower.

Flies nominal MPPI at several target speeds (default 6, 7, 8, 8.5, 9.1, 10, 12, 14 m/s) and the PixelMPC cells (the
paper's L1 cost and the border cost, projection and DOF pixel models, 8 m/s, t_f 1 s), then writes DIR/frontier.json,
DIR/REPORT.md and DIR/frontier.png. ``--quick``: nominal 6, 8, 8.5, 10 m/s and the border-cost cells only, 4 laps
each; ``--cells border``: the border-cost cells alone. Resumable per cell: an interrupted run (Ctrl-C) keeps its
finished cells and exits with status 130; run it again to go on.

    python experiments/visibility_frontier.py --quick --out runs/frontier_quick
    python experiments/visibility_frontier.py --out runs/frontier --laps 10

A thin script: the same as ``pixelmpc experiment frontier`` (its ``--help`` lists every option); the code lives in
the package (``pixelmpc_jax/apps/experiments/frontier.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "frontier", *sys.argv[1:]]))
