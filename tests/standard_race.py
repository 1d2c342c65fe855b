"""The one small race the tests that fly laps share, so that the suite compiles a handful of closed-loop programs.

A closed-loop program is the episode compiled for one controller configuration, one episode configuration (its time
limit sizes the per-tick log), one course's shape and one batch shape; each costs seconds to compile, and a test
that changes any of them compiles another. The tests that fly laps to check what a lap gives (the command, the
Python race, the comparison, the frontier, the batching, the data collection) fly these, on the AlphaPilot course:

- :data:`NOMINAL`: nominal MPPI at the paper's settings with 64 samples, laps of at most :data:`MAX_TIME_S`;
- :data:`PIXELMPC`: PixelMPC on the same sampler with the projection pixel model (no weights to load);

each in batches of :data:`BATCH` laps (``run_laps``, ``race``, ``fly``; a shorter run is padded to it), and nominal
MPPI also as one episode (``Runner.single``, the data collection's runner: ``tests/test_collect.py`` collects with
64 samples and :data:`MAX_TIME_S`). The golden laps (``tests/test_golden_laps.py``) fly the paper's own sizes.
"""

from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config

SAMPLES = 64
MAX_TIME_S = 1.0  # 40 ticks: no lap reaches the first gate at 10 m/s
BATCH = 2
MPPI = paper_mppi_config(num_samples=SAMPLES)
NOMINAL = RaceSpec("mppi", ControllerConfig(mppi=MPPI), speed=10.0, max_time_s=MAX_TIME_S)
PIXELMPC = RaceSpec("pixelmpc", ControllerConfig(mppi=MPPI, pixel_model="projection"), speed=10.0,
                    max_time_s=MAX_TIME_S)
TICKS = round(MAX_TIME_S * 40)  # a lap's ticks when it times out
