"""The same laps, bit for bit: the first 2 s of a lap of each controller at a fixed seed on one device, on the
true state and on the particle filter, against recorded states.

``tests/data/golden_laps.npz`` was recorded before the house moved (AMD EPYC family 25 model 1, AVX2);
``tests/data/golden_laps_*.npz`` hold the same laps recorded later on other processors, which pin every later change
there. ``python tests/test_golden_laps.py`` records this processor's laps into a file named for it (with
``XLA_FLAGS`` set to tests/conftest.py's ``FAST_COMPILE_XLA_FLAGS``, the test run's compilation's).

A lap is chaotic in its float rounding, so any change to what a step computes (the order of a sum, a fused
kernel) shows here. XLA's CPU kernels differ between processors, so the states are compared bit for bit against a
recording of this processor (its family, model and vector extensions) and JAX version. Without one they are
compared with the first recording: the true-state laps within 1e-3 over the 2 s (an EPYC of another family flew
the border lap 1.2e-4 m apart), the particle filter's over their first 0.2 s only, the states within 1e-3 and the
estimates within 2e-2. The filter's resampling picks other particles once rounding moves a weight, so its laps
part quickly: on an AVX-512 EPYC (family 25 model 17) the states stayed within 4e-4 and the estimates within
6.3e-3 over the first 8 ticks, and parted by 0.08 m and 0.24 m/s after 2 s.

The laps were recorded on the loop as it was: the ideal projection as the detector (corners and centre reported in
the image or not) and, on the filter, the world's gate switch. Their races name both (``detector="ideal"``,
``gate_switch="truth"``), so the defaults that came later (the detector's report cut at the image border, the switch
from the estimate) leave them as recorded.

A recording names the compilation it was flown under too: XLA's default flags (a user's run, and the test run with
``--runslow`` or ``--optimized-xla``), or the test run's cheapest (tests/conftest.py), whose kernels round otherwise.
The laps are compared bit for bit with this processor's recording at the compilation the test process runs; the
first recording was made under XLA's default flags. At the cheapest, XLA's kernels split a product over the cores the
process may use and round as they split it, so that recording holds for its number of cores too."""

import os
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import FAST_COMPILE_XLA_FLAGS

from pixelmpc_jax.apps.racing import race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.platform_info import cpu_signature

DATA = Path(__file__).resolve().parent / "data"
FIRST_RECORDING = DATA / "golden_laps.npz"
BORDER = ControllerConfig(c_pixel=3e7, pixel_cost="border")
RECORDED_LOOP = {"detector": "ideal", "gate_switch": "truth"}  # the loop the laps were recorded on
RACES = {  # the recorded laps: target speed, seed, controller configuration, estimator
    "mppi": RaceSpec("mppi", speed=14.0, seed=0, **RECORDED_LOOP),
    "pixelmpc_l1": RaceSpec("pixelmpc", speed=14.0, seed=0, **RECORDED_LOOP),
    "pixelmpc_border": RaceSpec("pixelmpc", BORDER, speed=8.5, seed=3, **RECORDED_LOOP),
    "mppi_pf": RaceSpec("mppi", speed=14.0, seed=1, estimator="pf", **RECORDED_LOOP),
    "pixelmpc_border_pf": RaceSpec("pixelmpc", BORDER, speed=8.5, seed=4, estimator="pf", **RECORDED_LOOP),
}
SECONDS = 2.0
FOREIGN_FILTER_TICKS = 8  # the particle filter's ticks compared with another processor's recording


def _recording(path: Path) -> dict:
    with np.load(path) as npz:
        return dict(npz)


def compilation() -> str:
    """How this process compiles: "cheapest" (the test run's XLA flags, tests/conftest.py) or "default"."""
    return "cheapest" if FAST_COMPILE_XLA_FLAGS in os.environ.get("XLA_FLAGS", "") else "default"


def _compilation_of(recording: dict) -> str:
    return str(recording["compilation"]) if "compilation" in recording else "default"  # the first ones name none


def _cores() -> int:
    return len(os.sched_getaffinity(0))


def _this_processors_recording() -> dict | None:
    import jax

    for path in sorted(DATA.glob("golden_laps*.npz")):
        recording = _recording(path)
        if (str(recording["cpu"]) == cpu_signature() and str(recording["jax"]) == jax.__version__
                and _compilation_of(recording) == compilation()
                and ("cores" not in recording or int(recording["cores"]) == _cores())):
            return recording
    return None


def _fly(name: str, ticks: int) -> tuple[np.ndarray, np.ndarray]:
    """The true states and the estimates the controller saw, ticks 0..``ticks``."""
    spec = RACES[name].replace(max_time_s=ticks / 40.0)
    results = race.run_laps(spec, batch_size=1, progress=False)
    return results["trajectories"][0], results["estimates"][0]


# The default run pins each controller's step and each loop, in two programs: nominal MPPI on the truth, PixelMPC
# on the particle filter. The slow run (--runslow, in CI) flies the other recorded laps too, each a program of its
# own: nominal MPPI on the filter, PixelMPC on the truth, and PixelMPC's step with the other pixel cost.
@pytest.mark.parametrize("name", ["mppi", "pixelmpc_border_pf",
                                  pytest.param("mppi_pf", marks=pytest.mark.slow),
                                  pytest.param("pixelmpc_border", marks=pytest.mark.slow),
                                  pytest.param("pixelmpc_l1", marks=pytest.mark.slow)])
def test_a_lap_flies_the_recorded_states(name):
    """Recorded on one device, as the test process runs (a lap's rounding depends on the device split). On the
    particle filter the controller acts on the filter's estimate, not the truth, and the filter tracks the truth."""
    here = _this_processors_recording()
    golden = here if here is not None else _recording(FIRST_RECORDING)
    recorded_states, recorded_estimates = golden[f"{name}/states"], golden[f"{name}/estimates"]
    states, estimates = _fly(name, len(recorded_states) - 1)
    assert states.shape == recorded_states.shape and estimates.shape == recorded_estimates.shape
    if RACES[name].estimator == "pf":
        error = np.linalg.norm(estimates[:, :3] - states[:-1, :3], axis=1)
        assert np.all(np.isfinite(error)) and error.mean() < 0.5, error
        assert not np.allclose(estimates, states[:-1])
    if here is not None:
        np.testing.assert_array_equal(states, recorded_states)
        np.testing.assert_array_equal(estimates, recorded_estimates)
    else:
        on_filter = RACES[name].estimator == "pf"
        ticks = FOREIGN_FILTER_TICKS + 1 if on_filter else len(recorded_states)
        np.testing.assert_allclose(states[:ticks], recorded_states[:ticks], atol=1e-3)
        np.testing.assert_allclose(estimates[:ticks], recorded_estimates[:ticks], atol=2e-2 if on_filter else 1e-3)


def recording_path(signature: str, compiled: str = "default") -> Path:
    """Where this processor's laps are recorded: ``golden_laps_<signature>.npz``, ``..._cheapest_<n>_cores.npz`` for
    the test run's compilation on n cores."""
    name = re.sub(r"[^a-z0-9]+", "_", signature.lower()).strip("_")
    return DATA / f"golden_laps_{name}{'' if compiled == 'default' else f'_{compiled}_{_cores()}_cores'}.npz"


def record() -> Path:
    """Fly every race of :data:`RACES` for :data:`SECONDS` and write them, with this processor's signature, into
    :func:`recording_path` (the first recording is never overwritten)."""
    import jax

    arrays = {"cpu": np.asarray(cpu_signature()), "jax": np.asarray(jax.__version__),
              "compilation": np.asarray(compilation())}
    if compilation() == "cheapest":
        arrays["cores"] = np.asarray(_cores())
    for name in RACES:
        arrays[f"{name}/states"], arrays[f"{name}/estimates"] = _fly(name, round(SECONDS * 40))
    path = recording_path(cpu_signature(), compilation())
    np.savez(path, **arrays)
    return path


if __name__ == "__main__":
    print(record())
