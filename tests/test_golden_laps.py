"""The same laps, bit for bit: the first 2 s of a lap of each controller at a fixed seed on one device, on the
true state and on the particle filter, against states recorded before the house moved (``tests/data/golden_laps.npz``;
``python tests/test_golden_laps.py`` records them again).

A lap is chaotic in its float rounding, so any change to what a step computes (the order of a sum, a fused
kernel) shows here. XLA's CPU kernels differ between processors (a lap recorded on one AMD EPYC and flown on an
EPYC of another family differed by 1.2e-4 m after 2 s), so the states are compared bit for bit on the processor
(its family, model and vector extensions) and JAX version that recorded them, and within 1e-3 elsewhere."""

from pathlib import Path

import numpy as np
import pytest

from pixelmpc_jax.apps.racing import race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.platform_info import cpu_signature

GOLDEN_PATH = Path(__file__).resolve().parent / "data" / "golden_laps.npz"
GOLDEN = np.load(GOLDEN_PATH)
BORDER = ControllerConfig(c_pixel=3e7, pixel_cost="border")
RACES = {  # the recorded laps: target speed, seed, controller configuration, estimator
    "mppi": RaceSpec("mppi", speed=14.0, seed=0),
    "pixelmpc_l1": RaceSpec("pixelmpc", speed=14.0, seed=0),
    "pixelmpc_border": RaceSpec("pixelmpc", BORDER, speed=8.5, seed=3),
    "mppi_pf": RaceSpec("mppi", speed=14.0, seed=1, estimator="pf"),
    "pixelmpc_border_pf": RaceSpec("pixelmpc", BORDER, speed=8.5, seed=4, estimator="pf"),
}
SECONDS = 2.0


def _fly(name: str, ticks: int) -> tuple[np.ndarray, np.ndarray]:
    """The true states and the estimates the controller saw, ticks 0..``ticks``."""
    spec = RACES[name].replace(max_time_s=ticks / 40.0)
    results = race.run_laps(spec, batch_size=1, progress=False)
    return results["trajectories"][0], results["estimates"][0]


def _recorded_here() -> bool:
    import jax

    return str(GOLDEN["cpu"]) == cpu_signature() and str(GOLDEN["jax"]) == jax.__version__


@pytest.mark.parametrize("name", ["mppi", "pixelmpc_border", "mppi_pf", "pixelmpc_border_pf",
                                  pytest.param("pixelmpc_l1", marks=pytest.mark.slow)])  # same step, another cost
def test_a_lap_flies_the_recorded_states(name):
    """Recorded on one device, as the test process runs (a lap's rounding depends on the device split)."""
    recorded_states, recorded_estimates = GOLDEN[f"{name}/states"], GOLDEN[f"{name}/estimates"]
    states, estimates = _fly(name, len(recorded_states) - 1)
    assert states.shape == recorded_states.shape and estimates.shape == recorded_estimates.shape
    if _recorded_here():
        np.testing.assert_array_equal(states, recorded_states)
        np.testing.assert_array_equal(estimates, recorded_estimates)
    else:
        np.testing.assert_allclose(states, recorded_states, atol=1e-3)
        np.testing.assert_allclose(estimates, recorded_estimates, atol=1e-3)


def record() -> None:
    """Fly every race of :data:`RACES` for :data:`SECONDS` and write them, with this processor's signature."""
    import jax

    arrays = {"cpu": np.asarray(cpu_signature()), "jax": np.asarray(jax.__version__)}
    for name in RACES:
        arrays[f"{name}/states"], arrays[f"{name}/estimates"] = _fly(name, round(SECONDS * 40))
    np.savez(GOLDEN_PATH, **arrays)


if __name__ == "__main__":
    record()
