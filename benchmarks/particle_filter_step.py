"""Median time of one particle-filter tick at the paper's 6,400 particles.

    python benchmarks/particle_filter_step.py [--particles 6400] [--repeats 50]

A thin script: the same as ``pixelmpc bench pf-step`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/bench/particle_filter_step.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "pf-step", *sys.argv[1:]]))
