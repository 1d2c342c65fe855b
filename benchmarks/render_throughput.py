"""Render throughput: frames per second of the ray-caster at 204 x 153, batched.

    python benchmarks/render_throughput.py [--batch 8 32] [--repeats 10] [--supersample 3]

A thin script: the code lives in the package (``pixelmpc_jax/apps/bench/render_throughput.py``), which runs it from
an installed copy, away from this checkout, as ``python -m pixelmpc_jax.apps.bench.render_throughput``.
"""

from pixelmpc_jax.apps.bench.render_throughput import main

if __name__ == "__main__":
    main()
