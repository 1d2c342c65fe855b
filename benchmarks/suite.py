"""The runtime harness: bench.json, bench.md and scaling.png.

    python benchmarks/suite.py --out DIR [--quick | --smoke]

A thin script: the same as ``pixelmpc bench suite`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/bench/suite.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "suite", *sys.argv[1:]]))
