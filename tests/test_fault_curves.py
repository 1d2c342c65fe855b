"""The fault curves of issue 39: their points (wind 0-6 m/s, delay 0-3 ticks, the fault-free point shared), both
controllers on both filters, and a run from stub laps that writes the table, the record and the figure and resumes."""

import json

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import fault_curves as C
from pixelmpc_jax.apps.experiments import robustness as R
from pixelmpc_jax.apps.racing import race
from pixelmpc_jax.sim.faults import Faults


def test_every_point_of_both_curves_for_both_controllers_on_both_filters():
    points = C.curve_cells()
    per_loop = len(C.WIND_M_S) + len(C.DELAY_TICKS) - 1  # the fault-free point once
    assert len(points) == per_loop * len(R.CONTROLLERS) * len(C.ESTIMATORS)
    by_name = {p.cell.name: p for p in points}
    assert len(by_name) == len(points) and len({p.cell.spec.key() for p in points}) == len(points)
    wind = by_name["pixelmpc_eskf_wind_4"].cell.spec
    assert wind.faults == Faults(wind=(4.0, 0.0, 0.0)) and wind.estimator == "eskf"
    assert wind == R.race("pixelmpc", "eskf", Faults(wind=(4.0, 0.0, 0.0)))  # the robustness grid's race
    assert by_name["mppi_pf_detection_delay_3"].cell.spec.faults == Faults(detection_delay_ticks=3)
    # the fault-free point and the moderate sizes are the robustness grid's cells: its folder can be reused
    grid = {rc.cell.name: rc.cell.spec for rc in R.robustness_cells(estimators=("eskf",))}
    assert by_name["pixelmpc_eskf_none"].cell.spec == grid["pixelmpc_eskf_none"]
    assert by_name["mppi_eskf_wind_3"].cell.spec == grid["mppi_eskf_wind_moderate"]


def test_levers_fly_both_controllers_again_and_only_those_both_filters_take():
    points = C.curve_cells(estimators=("eskf",), levers=("model",))
    model = [p for p in points if p.levers == "model"]
    per_controller = len(C.WIND_M_S) + len(C.DELAY_TICKS) - 1
    assert {p.controller for p in model} == {"mppi", "pixelmpc"} and len(model) == 2 * per_controller
    assert all(p.cell.spec.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S for p in model)
    with pytest.raises(ValueError, match="do not fly on both filters"):
        C.curve_cells(levers=("gate",))
    with pytest.raises(ValueError, match="unknown estimator 'truth'"):
        C.curve_cells(estimators=("truth",))
    with pytest.raises(ValueError, match="unknown curve"):
        C.faults_at("rain", 1.0)


def test_one_curve_alone_keeps_its_points_and_the_fault_free_one():
    wind = C.curve_cells(estimators=("eskf",), levers=("model",), curves=("wind",))
    assert {p.curve for p in wind} == {None, "wind"}
    assert len(wind) == len(R.CONTROLLERS) * 2 * len(C.WIND_M_S)  # with and without the observer
    both = {p.cell.name for p in C.curve_cells(estimators=("eskf",), levers=("model",))}
    assert {p.cell.name for p in wind} < both
    with pytest.raises(ValueError, match="unknown curve 'rain'"):
        C.curve_cells(curves=("rain",))


@pytest.fixture
def flown(monkeypatch):
    """race.run_laps replaced: a lap fails when the wind is at least 4 m/s or the delay at least 2 ticks, and the
    particle filter's laps fail one in two beyond that too; records the races flown."""
    from pixelmpc_jax.sim.metrics import MEASURE, aggregate

    calls = []

    def run_laps(spec, **kwargs):
        calls.append(spec)
        bad = spec.faults.wind[0] >= 4.0 or spec.faults.detection_delay_ticks >= 2
        laps = [{"success": not bad, "crash": None if not bad else "gate", "lap_time_s": 32.0 if not bad else None,
                 "rms_position_error_m": 0.1 if spec.estimator == "eskf" else 0.3, "max_position_error_m": 0.5,
                 "flipped": False, "seed": spec.seed + i, "time_vis_below_50_s": 1.0} for i in range(spec.laps)]
        return {"laps": laps, "aggregate": aggregate(laps), "interrupted": False, "seed": spec.seed,
                "trajectories": [np.zeros((2, 10))] * spec.laps, "covariances": [], "measure": MEASURE}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls


def test_a_quick_run_writes_both_curves_and_resumes(tmp_path, flown):
    rows = C.fault_curves_experiment(tmp_path, quick=True, progress=False)
    assert len(flown) == len(rows) == len(C.curve_cells(quick=True)) and {s.laps for s in flown} == {C.QUICK_LAPS}
    report = (tmp_path / "REPORT.md").read_text()
    # wind 0 (fault-free), 3 (the middle) and 6: the last fails for every loop
    assert "| loop | 0 m/s | 3 m/s | 6 m/s |" in report and "| nominal MPPI, ESKF | 2/2 | 2/2 | 0/2 |" in report
    assert "| PixelMPC (best), particle filter | 2/2 | 2/2 | 0/2 |" in report
    assert "| loop | 0 ticks | 2 ticks | 3 ticks |" in report
    saved = json.loads((tmp_path / "curves.json").read_text())
    eskf = next(r for r in saved["rows"] if r["cell"] == "pixelmpc_eskf_none")
    assert eskf["rms_position_error_m"] == pytest.approx(0.1) and eskf["successes"] == 2
    assert (tmp_path / "fault_curves.png").stat().st_size > 10_000
    flown.clear()
    C.fault_curves_experiment(tmp_path, quick=True, progress=False)
    assert flown == []  # every point kept
