"""Probe: what does PixelMPC's visibility cost in lap time, over pixel-cost weights at one target speed?

    python experiments/visibility_speed_probe.py --speed 8 --laps 4 --out DIR
    python experiments/visibility_speed_probe.py --speed 14 --c-pixel 9e6 3e7 1e8 3e8 --out DIR

Writes ``results.json`` (resumable per cell), ``REPORT.md`` and ``tradeoff.png`` in DIR.

A thin script: the same as ``pixelmpc experiment speed-probe`` (its ``--help`` lists every option); the code lives
in the package (``pixelmpc_jax/apps/experiments/speed_probe.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "speed-probe", *sys.argv[1:]]))
