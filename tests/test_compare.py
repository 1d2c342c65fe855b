"""The main job: PixelMPC beside nominal MPPI (apps/compare.py), the presets, and the two visibility families of
the lap metrics (the share of time with the target in view, the angle to it)."""

import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.apps import compare, presets, race
from pixelmpc_jax.apps.spec import RaceSpec
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.sim import metrics
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib


def _fake_results(spec, lap_time: float, below_50: float) -> dict:
    states = np.zeros((5, 10), np.float32)
    states[:, 0] = np.arange(5)
    lap = {"success": True, "seed": spec.seed, "time_vis_below_50_s": below_50}
    aggregate = {"lap_time_s": {"mean": lap_time, "two_sigma": 0.0},
                 "time_vis_below_50_s": {"mean": below_50, "two_sigma": 0.0},
                 "time_vis_below_50_unavoidable_s": {"mean": 1.0, "two_sigma": 0.0}}
    return {"race": spec.record(), "laps": [lap], "aggregate": aggregate, "interrupted": False,
            "trajectories": [states], "visibility": [np.linspace(0.0, 1.0, 5)], "covariances": []}


def test_both_controllers_fly_the_same_race_and_one_file_names_the_preset(monkeypatch, tmp_path):
    flown = []

    def run_laps(spec, **kwargs):
        flown.append(spec)
        return _fake_results(spec, 30.0 if spec.controller == "mppi" else 33.0,
                             9.0 if spec.controller == "mppi" else 4.0)

    monkeypatch.setattr(race, "run_laps", run_laps)
    spec = presets.preset("best").replace(laps=1, seed=7)
    record = compare.run_compare(spec, out=tmp_path, preset="best", progress=False)
    assert [s.controller for s in flown] == ["pixelmpc", "mppi"]
    # the same race otherwise, nominal MPPI with the paper's sampling (the frontier's), not the tuned lambda
    assert flown[1] == presets.nominal_of(flown[0]) and flown[1].seed == 7 and flown[1].speed == flown[0].speed
    assert flown[1].config.mppi.temperature == 200.0 and flown[1].config.mppi.noise_exponent == 0.0
    assert flown[0].config.mppi.temperature != 200.0 and flown[1].config.mppi.num_samples == 512
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["preset"] == "best" and saved["race"] == json.loads(json.dumps(spec.record()))
    assert saved["race"]["config"]["pixel_cost"] == "border" and set(saved["controllers"]) == {"pixelmpc", "mppi"}
    assert saved["controllers"]["mppi"]["race"]["controller"] == "mppi"
    assert saved["controllers"]["mppi"]["race"]["config"]["mppi"]["temperature"] == 200.0
    assert (tmp_path / "trajectories.png").stat().st_size > 0 and (tmp_path / "visibility.png").stat().st_size > 0
    table = compare.side_by_side(record).splitlines()
    assert "PixelMPC" in table[0] and "nominal MPPI" in table[0]
    avoidable = next(line for line in table if "avoidable" in line).split()
    assert avoidable[-2:] == ["3.00", "8.00"]  # below 50 % less the unavoidable part, per controller


def test_an_interrupted_controller_ends_the_comparison_and_keeps_its_laps(monkeypatch, tmp_path):
    def run_laps(spec, **kwargs):
        return {**_fake_results(spec, 30.0, 5.0), "interrupted": True}

    monkeypatch.setattr(race, "run_laps", run_laps)
    record = compare.run_compare(presets.preset("paper"), out=tmp_path, preset="paper", progress=False)
    assert record["interrupted"] and list(record["controllers"]) == ["pixelmpc"]
    assert json.loads((tmp_path / "metrics.json").read_text())["interrupted"] is True


def test_the_presets():
    paper, best = presets.preset("paper"), presets.preset("best")
    assert paper.speed == 14.0 and paper.config.pixel_cost == "l1" and paper.config.c_pixel == 9e6
    assert paper.dof_weights is None  # the paper's own DOF weights
    assert best.speed == presets.PAPER_PACE_SPEED and best.config.pixel_cost == "border"
    assert best.config.pixel_model == "vdof" and best.key() != paper.key()
    # best flies the tuned trial it names (the best within +5 %), exactly as the search recorded it
    tuned = json.loads((Path(presets.__file__).parents[2] / "experiments/results/tune/best_bound5.json").read_text())
    trial = RaceSpec.from_record(tuned).replace(laps=1, seed=0)
    assert trial.key() != best.key()  # with the clearance to the frames, which the search did not set
    racing = dataclasses.replace(trial.config.racing, vehicle_radius=presets.BEST_VEHICLE_RADIUS_M)
    assert trial.replace(config=dataclasses.replace(trial.config, racing=racing)).key() == best.key()
    assert best.config.racing.vehicle_radius == 0.3 > trial.config.racing.vehicle_radius
    assert best.config != presets.HAND_TUNED_BEST and presets.HAND_TUNED_BEST.box_size_limit == 0.5
    with pytest.raises(ValueError, match="unknown preset 'fast'"):
        presets.preset("fast")


@pytest.mark.parametrize("yaw, angle", [(0.0, 0.0), (np.pi / 2, 90.0), (np.pi / 4, 45.0)])
def test_the_angle_to_the_target_is_the_optical_axis_against_the_ray_to_its_centre(yaw, angle):
    track = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=20.0)
    x = quadrotor.hover_state((0.0, 0.0, 3.0), yaw=yaw)
    states = np.stack([np.asarray(x)] * 3)
    visibility = np.asarray([1.0, 0.0, 1.0])
    view = metrics.view_metrics(states, visibility, np.zeros(3, np.int32), 2, track, camera_lib.default_camera())
    assert view["mean_target_angle_deg"] == pytest.approx(angle, abs=1e-3)
    assert view["share_target_in_view"] == pytest.approx(0.5)  # ticks 1 and 2: hidden, then in view


def test_a_lap_reports_both_view_figures():
    assert {"share_target_in_view", "mean_target_angle_deg"} <= set(metrics.LAP_KEYS)
    assert metrics.view_metrics(jnp.zeros((1, 10)), np.ones(1), np.zeros(1, np.int32), 0, None, None) == {
        "share_target_in_view": None, "mean_target_angle_deg": None}
