"""The closed loop's tick: PixelMPC (packaged DOF) and nominal MPPI flying a lap as ``pixelmpc race`` does,
the compiled episode's wall time per tick flown.

    python benchmarks/closed_loop.py [--mode full|quick|smoke] [--repeats 3]

A thin script: the same as ``pixelmpc bench closed-loop`` (its ``--help`` lists every option); the code lives in the
package (``pixelmpc_jax/apps/bench/closed_loop.py``).
"""

import sys

from pixelmpc_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "closed-loop", *sys.argv[1:]]))
