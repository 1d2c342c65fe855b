"""The closed loop's tick: PixelMPC (packaged DOF) and nominal MPPI flying a lap as ``pixelmpc race`` does,
the compiled episode's wall time per tick flown.

    python benchmarks/closed_loop.py [--mode full|quick|smoke] [--repeats 3]

A thin script: the code lives in the package (``pixelmpc_jax/apps/bench/closed_loop.py``), which runs it from
an installed copy, away from this checkout, as ``python -m pixelmpc_jax.apps.bench.closed_loop``.
"""

from pixelmpc_jax.apps.bench.closed_loop import main

if __name__ == "__main__":
    main()
