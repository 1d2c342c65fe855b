"""Median time of one particle-filter tick at the paper's 6,400 particles.

    python benchmarks/particle_filter_step.py [--particles 6400] [--repeats 50]

A thin script: the code lives in the package (``pixelmpc_jax/apps/bench/particle_filter_step.py``), which runs it from
an installed copy, away from this checkout, as ``python -m pixelmpc_jax.apps.bench.particle_filter_step``.
"""

from pixelmpc_jax.apps.bench.particle_filter_step import main

if __name__ == "__main__":
    main()
