"""Tables II and III and Fig. 6 of the paper: target visibility, lap time and smoothness of PixelMPC against
nominal MPPI over t_f in {1, 2} s x c_pixel in {3e6, 6e6, 9e6}, 10 races per cell, at the paper's 14 m/s label and
at its pace (8.5 m/s, where our nominal lap matches the paper's), with the ``best`` preset beside the grid.

    python experiments/table2_visibility.py --out experiments/results/table2 [--laps 10] [--seed 200] [--quick]
    python experiments/table2_visibility.py --pixel-model projection --out experiments/results/table2_projection

Writes REPORT.md (ours beside the paper's), results.json, summary.json, visibility.png, smoothness.png.
Interrupted runs resume: finished cells are kept. The frontier gains need a frontier run (``pixelmpc reproduce``
reads them off its ``frontier`` part).

A thin script: the same as ``pixelmpc experiment table2`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/experiments/paper.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "table2", *sys.argv[1:]]))
