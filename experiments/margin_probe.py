"""The ``best`` preset's clearance to the gate frames (0.3 m) against the vehicle's own 0.1 m, where the reproduction
reports it: the true-state frontier cell at the preset's pace (10 laps) and Table IV's filter cells at both paces
(25 laps).

    pixelmpc reproduce frontier --out runs/reproduce
    python experiments/margin_probe.py --out runs/margin --frontier runs/reproduce/frontier [--seed 200]

Writes ``truth/`` (the frontier with both clearances) and ``pf/`` (the filter cells), each resumable per cell.

A thin script: the same as ``pixelmpc experiment margin-probe`` (its ``--help`` lists every option); the code lives
in the package (``pixelmpc_jax/apps/experiments/margin_probe.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "margin-probe", *sys.argv[1:]]))
