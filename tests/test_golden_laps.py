"""The same laps, bit for bit: the first 2 s of a lap of each controller at a fixed seed on one device, against
states recorded before the race's settings moved into one configuration (``tests/data/golden_laps.npz``).

A lap is chaotic in its float rounding, so any change to what a step computes (the order of a sum, a fused
kernel) shows here. XLA's CPU kernels differ between processors, so the states are compared bit for bit on the
processor and JAX version that recorded them, and within 1e-4 elsewhere."""

from pathlib import Path

import numpy as np
import pytest

from pixelmpc_jax.apps import race
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import PixelMPCConfig
from pixelmpc_jax.platform_info import device_description

GOLDEN = np.load(Path(__file__).resolve().parent / "data" / "golden_laps.npz")
RACES = {  # the recorded laps: target speed, seed, controller configuration
    "mppi": RaceSpec("mppi", speed=14.0, seed=0),
    "pixelmpc_l1": RaceSpec("pixelmpc", speed=14.0, seed=0),
    "pixelmpc_border": RaceSpec("pixelmpc", PixelMPCConfig(c_pixel=3e7, pixel_cost="border"), speed=8.5, seed=3),
}


def _recorded_here() -> bool:
    import jax

    return str(GOLDEN["cpu_model"]) == device_description()["cpu_model"] and str(GOLDEN["jax"]) == jax.__version__


@pytest.mark.parametrize("name", ["mppi", "pixelmpc_border",
                                  pytest.param("pixelmpc_l1", marks=pytest.mark.slow)])  # same step, another cost
def test_a_lap_flies_the_recorded_states(name):
    """Recorded on one device, as the test process runs (a lap's rounding depends on the device split)."""
    recorded = GOLDEN[name]
    spec = RACES[name].replace(max_time_s=(len(recorded) - 1) / 40.0)
    flown = race.run_laps(spec, batch_size=1, progress=False)["trajectories"][0]
    assert flown.shape == recorded.shape
    if _recorded_here():
        np.testing.assert_array_equal(flown, recorded)
    else:
        np.testing.assert_allclose(flown, recorded, atol=1e-4)
