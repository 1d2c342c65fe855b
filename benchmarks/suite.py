"""The runtime harness (the same as ``pixelmpc bench``): bench.json, bench.md and scaling.png.

    python benchmarks/suite.py --out DIR [--quick | --smoke]

A thin script: the code lives in the package (``pixelmpc_jax/apps/bench/suite.py``), which runs it from
an installed copy, away from this checkout, as ``python -m pixelmpc_jax.apps.bench.suite``.
"""

from pixelmpc_jax.apps.bench.suite import main

if __name__ == "__main__":
    main()
