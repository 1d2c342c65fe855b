"""Render throughput: frames per second of the ray-caster at 204 x 153, batched.

    python benchmarks/render_throughput.py [--batch 8 32] [--repeats 10] [--supersample 3]

A thin script: the same as ``pixelmpc bench render`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/bench/render_throughput.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "render", *sys.argv[1:]]))
