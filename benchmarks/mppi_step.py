"""Median step time of the quadrotor MPPI at the paper's sizes (N=512, T=80, K=1).

    python benchmarks/mppi_step.py [--samples 512] [--horizon 80] [--repeats 50] [--cost racing|waypoint]

A thin script: the same as ``pixelmpc bench mppi-step`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/bench/mppi_step.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "mppi-step", *sys.argv[1:]]))
