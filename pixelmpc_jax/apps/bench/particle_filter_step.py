"""Median time of one particle-filter tick (predict + update + estimate + resample) at the paper's 6,400 particles.

    pixelmpc bench pf-step [--particles 6400] [--repeats 50]

The timed call is the filter's compiled step (``devices.compile_estimator(make_particle_filter(...))``: inputs
checked, one compiled call) on the AlphaPilot course, 6 m
before gate 3 with the gate in view, a hover tick of preintegrated IMU samples (what the closed loop feeds
it) and a noisy geometric detection; the filter state changes every call as in the loop. ``pf_rows`` gives
the same measurement as rows of the harness (``pixelmpc bench``). Compilation happens before the timed
region; every call is blocked on.
The paper runs its filter on a GPU and reports no time for it; the baseline measured in the same run is the
motion update alone (``particle_filter.predict``, compiled), to show what the sensor update, estimate and
resampling add.
"""

from __future__ import annotations

import json

import jax

from pixelmpc_jax import devices, timing
from pixelmpc_jax.apps.bench.measure import make_row, measure, spread
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import particle_filter as pf
from pixelmpc_jax.perception.estimator import EstimatorParams
from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.sim.plant import hover_tick_imu
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render as render_lib


def estimator_scene():
    """What an estimator's bench tick is fed: (track, camera, the true pose 6 m before gate 3, a noisy geometric
    detection of that gate, a hover tick of preintegrated IMU samples)."""
    track = course_lib.load_course()
    camera = camera_lib.default_camera()
    gate_index = 2
    x_true = render_lib.pose_before_gate(track.gate(gate_index), 6.0, 0.3, 0.2)
    detection = detector_lib.detect_from_geometry(
        track.gate(gate_index), x_true, camera, jax.random.PRNGKey(1), 0.5, 0.0, gate_index)
    return track, camera, x_true, detection, hover_tick_imu(timing.CONTROL_DT)


def _problem(particles: int):
    config = pf.PFConfig(num_particles=particles)
    track, camera, x_true, detection, imu = estimator_scene()
    est = devices.compile_estimator(pf.make_particle_filter(config, spread=(0.5, 0.03, 0.2)))
    predict_jit, _ = devices.counted_jit(lambda state, imu: pf.predict(state, imu, config))
    params = EstimatorParams(gates=track.gates, camera=camera)
    holder = {"state": est.init(jax.random.PRNGKey(0), x_true)}

    def step():
        estimate, holder["state"], info = est.step(holder["state"], imu, detection, params)
        return holder["state"].particles, estimate.mean, info.ess

    def predict():
        holder["state"] = predict_jit(holder["state"], imu)
        return holder["state"].particles

    return step, predict


def measure_pf(particles: int = 6400, repeats: int = 30) -> tuple[dict, dict]:
    """(full step, motion update alone) timings; compilation outside the timed region."""
    step, predict = _problem(particles)
    jax.block_until_ready(step())
    jax.block_until_ready(predict())
    return measure(step, repeats=repeats), measure(predict, repeats=repeats)


def pf_rows(particles: int = 6400, repeats: int = 30) -> list[dict]:
    """Harness rows (group "estimator"): the filter tick and its motion update alone."""
    full, predict = measure_pf(particles, repeats)
    return [make_row("estimator", "particle filter tick (predict + update + estimate + resample)", particles, None,
                     full),
            make_row("estimator", "particle filter motion update alone", particles, None, predict)]


def run_pf_step(particles: int = 6400, repeats: int = 50) -> dict:
    """Time the filter tick and its motion update alone (:func:`measure_pf`); prints the device, the figures and a
    JSON line, and returns them."""
    result, baseline = measure_pf(particles, repeats)
    device = device_line()
    result.update(num_particles=particles, device=device, predict_only=baseline)
    print(f"device: {device}")
    print(f"particle filter step, P={particles}: {spread(result, 3, repeats)}; "
          f"{particles / (result['median_ms'] / 1e3) / 1e6:.2f} M particle-updates/s")
    print(f"baseline predict only: {spread(baseline, 3)}")
    print(json.dumps({k: v for k, v in result.items() if k not in ("device", "predict_only")}))
    return result
