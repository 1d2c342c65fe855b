"""Median step time of the quadrotor MPPI at the paper's sizes (N=512, T=80, K=1).

    python benchmarks/mppi_step.py [--samples 512] [--horizon 80] [--repeats 50] [--cost racing|waypoint]

A thin script: the code lives in the package (``pixelmpc_jax/apps/bench/mppi_step.py``), which runs it from
an installed copy, away from this checkout, as ``python -m pixelmpc_jax.apps.bench.mppi_step``.
"""

from pixelmpc_jax.apps.bench.mppi_step import main

if __name__ == "__main__":
    main()
