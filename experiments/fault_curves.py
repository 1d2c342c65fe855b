"""Success against the size of two faults (issue 39): steady wind 0-6 m/s and detection delay 0-3 ticks, for nominal
MPPI and PixelMPC (the ``best`` preset) at the paper's pace on the particle filter and the error-state Kalman filter.

    python experiments/fault_curves.py --out DIR [--quick] [--estimators pf eskf] [--levers model]
        [--curves wind detection_delay] [--reuse DIR ...] [--report-only]

Writes REPORT.md, curves.json, fault_curves.png (one figure, both curves) and results.json. Interrupted runs
resume: finished cells are kept.

A thin script: the same as ``pixelmpc experiment fault-curves`` (its ``--help`` lists every option); the code lives
in the package (``pixelmpc_jax/apps/experiments/fault_curves.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fault-curves", *sys.argv[1:]]))
