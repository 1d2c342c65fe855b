"""Robustness to the faults a real flight brings (issue 28): nominal MPPI and PixelMPC (the ``best`` preset) at the
paper's pace under wind, model error, latency, IMU and detector faults and map errors, each alone at a moderate and
a severe level and all moderate ones at once, on the particle filter and the error-state Kalman filter (and at the
moderate level on the true state).

    python experiments/robustness.py --out DIR [--quick] [--estimators pf eskf truth] [--faults NAME ...]
        [--levels moderate severe] [--controllers mppi pixelmpc] [--levers [NAME ...]] [--reuse FOLDER ...]
        [--report-only]

--levers: model, filter, gate, bias, robust, exact, align, adapt, model-adapt (no name: all).

Writes REPORT.md (success at a glance, every cell, the fault levels and their reasons), robustness.json,
robustness.png and results.json. Interrupted runs resume: finished cells are kept.

A thin script: the same as ``pixelmpc experiment robustness`` (its ``--help`` lists every option); the code lives in
the package (``pixelmpc_jax/apps/experiments/robustness.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "robustness", *sys.argv[1:]]))
