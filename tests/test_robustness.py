"""The robustness grid of issue 28: its cells (every fault at both levels and combined, both controllers, the estimators
the issue names, the laps per cell), the failure causes, the report written from stub results, and a run that flies
each cell with its laps and shares the fault-free ones."""

import dataclasses
import json

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import robustness as R
from pixelmpc_jax.apps.racing import grid, race
from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEED
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.perception.eskf import SURVEYED_MAP_SIGMA_M, ESKFConfig
from pixelmpc_jax.perception.filter_guards import GuardConfig
from pixelmpc_jax.sim.faults import COMBINED, FAULT_LEVELS, Faults, fault_level


def _by_name(cells):
    return {rc.cell.name: rc for rc in cells}


def test_the_grid_flies_every_fault_at_both_levels_and_combined_for_both_controllers():
    cells = _by_name(R.robustness_cells())
    for fault in FAULT_LEVELS:
        for controller in R.CONTROLLERS:
            assert cells[f"{controller}_pf_{fault}_moderate"].laps == 10
            assert cells[f"{controller}_pf_{fault}_severe"].laps == 6
            assert f"{controller}_truth_{fault}_severe" not in cells  # the truth at the moderate level only
    for controller in R.CONTROLLERS:
        assert cells[f"{controller}_pf_{COMBINED}_moderate"].cell.spec.faults == fault_level(COMBINED, "moderate")
        assert cells[f"{controller}_pf_none"].laps == cells[f"{controller}_truth_none"].laps == 10
        assert cells[f"{controller}_truth_wind_moderate"].laps == 10  # lap for lap against the filters' cells
        assert cells[f"{controller}_eskf_{COMBINED}_moderate"].cell.spec.estimator == "eskf"
        assert cells[f"{controller}_eskf_wind_moderate"].laps == 10 and cells[f"{controller}_eskf_none"].laps == 10
    spec = cells["pixelmpc_pf_gust_severe"].cell.spec
    assert spec.speed == PAPER_PACE_SPEED and spec.config.pixel_model == "vdof" and spec.estimator == "pf"
    assert spec.faults == Faults(gust=FAULT_LEVELS["gust"]["severe"].settings["gust"])
    nominal = cells["mppi_pf_none"].cell.spec
    assert nominal == RaceSpec("mppi", speed=PAPER_PACE_SPEED, estimator="pf")  # the paper's MPPI settings
    assert len({rc.cell.spec.key() for rc in cells.values()}) == len(cells)


def test_a_fault_that_cannot_reach_a_loop_is_left_out_and_quick_is_the_moderate_filter_cells():
    names = set(_by_name(R.robustness_cells()))
    assert "pixelmpc_truth_imu_bias_moderate" not in names and "pixelmpc_truth_miss_moderate" in names
    assert "mppi_truth_miss_moderate" not in names and "mppi_truth_map_moderate" in names
    quick = R.robustness_cells(quick=True)
    assert {rc.laps for rc in quick} == {2} and {rc.estimator for rc in quick} == {"pf"}
    assert {rc.level for rc in quick} == {None, "moderate"} and len(quick) == 2 * (len(FAULT_LEVELS) + 2)


def test_each_set_of_levers_flies_the_filter_cells_again_on_its_own():
    cells = _by_name(R.robustness_cells(quick=True, levers=("model", "filter")))
    model = cells["pixelmpc_pf_latency_moderate_model"].cell.spec
    assert model.config.model_latency_ticks == model.faults.latency_ticks == 1
    assert model.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S and model.guards == GuardConfig()
    guarded = cells["pixelmpc_pf_miss_moderate_filter"].cell.spec
    assert guarded.guards == R.GUARDS and guarded.config.disturbance_time_constant_s is None
    assert cells["pixelmpc_pf_none_model"].cell.spec.faults == Faults()  # what the levers cost without faults
    # the guards answer PixelMPC's bar; the controller's model flies nominal MPPI too, on the same cells
    nominal = cells["mppi_pf_wind_moderate_model"].cell.spec
    assert nominal.controller == "mppi" and nominal.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S
    assert nominal.guards == GuardConfig() and "mppi_pf_wind_moderate_filter" not in cells
    nominal_cells = sum(rc.controller == "mppi" for rc in R.robustness_cells(quick=True))
    assert len(cells) == len(R.robustness_cells(quick=True)) + 2 * (len(FAULT_LEVELS) + 2) + nominal_cells
    full = _by_name(R.robustness_cells(levers=("filter",)))
    assert "pixelmpc_pf_wind_severe_filter" not in full and "pixelmpc_pf_wind_moderate_filter" in full
    # the filter set's halves fly alone: the gate and the recovery without the bias states, and the reverse
    gate, bias = R.race("pixelmpc", "pf", levers="gate").guards, R.race("pixelmpc", "pf", levers="bias").guards
    assert gate.detection_gate_px == R.GUARDS.detection_gate_px and gate.imu_bias_std is None
    assert bias.imu_bias_std == R.GUARDS.imu_bias_std and not bias.active
    with pytest.raises(ValueError, match="unknown levers 'magic'"):
        R.race("mppi", "pf", levers="magic")


def test_the_robust_set_turns_on_the_model_and_gate_sets_together():
    latency = fault_level("latency", "moderate")
    robust = R.race("pixelmpc", "pf", latency, levers="robust")
    assert robust.config.model_latency_ticks == latency.latency_ticks == 1
    assert robust.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S
    assert robust.guards == R.GATE_GUARDS and robust.guards.imu_bias_std is None  # not the bias states
    assert dataclasses.replace(robust, guards=GuardConfig(), config=dataclasses.replace(
        robust.config, model_latency_ticks=0, disturbance_time_constant_s=None)) == R.race("pixelmpc", "pf", latency)
    cells = _by_name(R.robustness_cells(levers=("robust",)))
    assert cells["pixelmpc_pf_gust_moderate_robust"].cell.spec.faults == fault_level("gust", "moderate")
    assert not any(name.endswith("_robust") and not name.startswith("pixelmpc_pf") for name in cells)


def test_the_controller_levers_fly_on_every_loop_and_the_guards_on_the_particle_filter_only():
    cells = _by_name(R.robustness_cells(levers=("model", "filter", "robust")))
    for estimator in ("eskf", "truth"):  # each filter cell with a lever has its true-state cell with the same lever
        spec = cells[f"pixelmpc_{estimator}_wind_moderate_model"].cell.spec
        assert spec.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S and spec.estimator == estimator
        assert f"pixelmpc_{estimator}_wind_moderate_filter" not in cells
        assert f"pixelmpc_{estimator}_wind_moderate_robust" not in cells
        assert f"pixelmpc_{estimator}_wind_severe_model" not in cells
    assert "pixelmpc_pf_wind_moderate_robust" in cells and "mppi_pf_wind_moderate_robust" not in cells
    for estimator in ("eskf", "truth", "pf"):  # nominal MPPI flies the observer on every loop, as PixelMPC does
        spec = cells[f"mppi_{estimator}_drag_moderate_model"].cell.spec
        assert spec.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S and spec.controller == "mppi"
        assert dataclasses.replace(spec.config, disturbance_time_constant_s=None) == \
            cells[f"mppi_{estimator}_drag_moderate"].cell.spec.config


def test_the_exact_map_setting_flies_on_the_kalman_filter_only_for_both_controllers():
    cells = _by_name(R.robustness_cells(levers=("exact",)))
    for controller in ("mppi", "pixelmpc"):  # a filter's setting changes no controller: both fly it
        for fault in ("none", "map_moderate", "wind_moderate"):
            spec = cells[f"{controller}_eskf_{fault}_exact"].cell.spec
            assert spec.eskf.map_sigma_m == 0.0 and spec.estimator == "eskf"
            assert spec.config == cells[f"{controller}_eskf_{fault}"].cell.spec.config
        assert f"{controller}_eskf_map_severe_exact" not in cells
        for estimator in ("pf", "truth"):
            assert not any(name.endswith("_exact") and name.startswith(f"{controller}_{estimator}_") for name in cells)
    # the Kalman filter's default: a surveyed map's accuracy
    assert cells["pixelmpc_eskf_none"].cell.spec.eskf.map_sigma_m == SURVEYED_MAP_SIGMA_M > 0
    # the setting belongs to the Kalman filter: a race on another loop drops it
    lever_spec = cells["pixelmpc_eskf_map_moderate_exact"].cell.spec
    assert lever_spec.replace(estimator="pf").eskf == RaceSpec().eskf
    assert RaceSpec.from_record(lever_spec.record()) == lever_spec
    default_spec = cells["pixelmpc_eskf_none"].cell.spec
    assert RaceSpec.from_record(default_spec.record()) == default_spec


def test_a_race_on_the_kalman_filter_records_the_map_accuracy_it_was_told():
    """Today's default, a surveyed map's accuracy, is written out with the race; the map taken as exact is another
    race; a race on another loop keeps the Kalman filter's defaults, which fly nothing there."""
    then = RaceSpec("pixelmpc", speed=8.5, estimator="eskf", seed=200)
    assert then.record()["eskf"]["map_sigma_m"] == SURVEYED_MAP_SIGMA_M
    exact = then.replace(eskf=ESKFConfig(map_sigma_m=0.0))
    assert exact.key() != then.key() and RaceSpec.from_record(json.loads(json.dumps(exact.record()))) == exact
    assert RaceSpec.from_record(then.record()) == then
    assert RaceSpec("pixelmpc", speed=8.5, estimator="pf", eskf=ESKFConfig(map_sigma_m=0.0)).eskf == ESKFConfig()


def test_the_alignment_flies_on_the_kalman_filter_only_for_both_controllers():
    cells = _by_name(R.robustness_cells(levers=("align",)))
    for controller in ("mppi", "pixelmpc"):
        for fault in ("none", "imu_bias_moderate", "imu_noise_moderate"):
            spec = cells[f"{controller}_eskf_{fault}_align"].cell.spec
            assert spec.eskf == ESKFConfig(align_s=R.ALIGN_S) and spec.estimator == "eskf"
            assert spec.config == cells[f"{controller}_eskf_{fault}"].cell.spec.config
            assert spec.faults == cells[f"{controller}_eskf_{fault}"].cell.spec.faults
        assert f"{controller}_eskf_imu_bias_severe_align" not in cells
    assert not any(name.endswith("_align") and "_eskf_" not in name for name in cells)
    assert R.applies("align", "eskf") and not R.applies("align", "pf") and R._flies_nominal("align")


def test_a_part_of_the_grid_by_estimator_and_fault():
    cells = R.robustness_cells(estimators=("eskf", "truth"), faults=("none", "wind", "imu_bias"))
    assert {rc.estimator for rc in cells} == {"eskf", "truth"} and {rc.fault for rc in cells} == {"none", "wind",
                                                                                                "imu_bias"}
    names = {rc.cell.name for rc in cells}
    assert "pixelmpc_eskf_imu_bias_severe" in names and "pixelmpc_truth_imu_bias_moderate" not in names
    with pytest.raises(ValueError, match="unknown estimator 'ekf'"):
        R.robustness_cells(estimators=("ekf",))
    with pytest.raises(ValueError, match="unknown fault 'rain'"):
        R.robustness_cells(faults=("rain",))
    moderate = R.robustness_cells(estimators=("eskf",), faults=("none", "wind"), levels=("moderate",))
    assert {rc.cell.name for rc in moderate} == {"mppi_eskf_none", "pixelmpc_eskf_none", "mppi_eskf_wind_moderate",
                                                 "pixelmpc_eskf_wind_moderate"}
    nominal = R.robustness_cells(estimators=("eskf",), faults=("none", "drag"), levels=("moderate",), levers=("model",),
                                 controllers=("mppi",))
    assert [rc.cell.name for rc in nominal] == ["mppi_eskf_none", "mppi_eskf_none_model", "mppi_eskf_drag_moderate",
                                                "mppi_eskf_drag_moderate_model"]
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        R.robustness_cells(controllers=("pid",))


@pytest.mark.parametrize("lap, cause", [
    ({"success": True}, None), ({"success": False, "crash": "gate", "max_position_error_m": 0.4}, "gate"),
    ({"success": False, "crash": "wall", "max_position_error_m": 2.5}, "estimate_diverged"),
    ({"success": False, "crash": "ground", "flipped": True}, "flip"), ({"success": False, "crash": None}, "timeout"),
])
def test_every_failed_lap_has_a_named_cause(lap, cause):
    assert R.failure_cause(lap) == cause


def _lap(success: bool, crash=None, error=0.3) -> dict:
    return {"success": success, "crash": crash, "lap_time_s": 31.0 if success else None, "time_vis_below_50_s": 2.0,
            "time_vis_zero_s": 0.5, "share_target_in_view": 0.9, "mean_target_angle_deg": 12.0,
            "max_position_error_m": error, "rms_position_error_m": error / 2, "flipped": False, "seed": 200}


@pytest.fixture
def flown(monkeypatch):
    """race.run_laps replaced: every lap succeeds without faults, every other lap under a fault fails with a
    diverged estimate; records the races flown."""
    from pixelmpc_jax.sim.metrics import MEASURE, aggregate

    calls = []

    def run_laps(spec, **kwargs):
        calls.append(spec)
        laps = [_lap(not spec.faults.active() or i % 2 == 0, "gate", 3.0 * (i % 2)) for i in range(spec.laps)]
        return {"laps": laps, "aggregate": aggregate(laps), "interrupted": False, "seed": spec.seed,
                "trajectories": [np.zeros((2, 10))] * spec.laps, "covariances": [], "measure": MEASURE}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls


def test_a_run_flies_each_cell_with_its_laps_and_writes_the_report(tmp_path, flown):
    rows = R.robustness_experiment(tmp_path, quick=True, progress=False, levers=("model",))
    assert len(flown) == len(rows) == len(R.robustness_cells(quick=True, levers=("model",)))
    assert {spec.laps for spec in flown} == {2} and {spec.seed for spec in flown} == {R.SEED}
    row = next(r for r in rows if r["cell"] == "pixelmpc_pf_wind_moderate")
    assert row["successes"] == 1 and row["failures"] == {"estimate_diverged": 1}
    # the laps' RMS errors 0 and 1.5 m: the cell's RMS over both laps, and its worst error
    assert row["rms_position_error_m"] == pytest.approx(np.sqrt(1.5**2 / 2)) and row["max_position_error_m"] == 3.0
    report = (tmp_path / "REPORT.md").read_text()
    assert "| wind | moderate | 1/2 | 1/2 | 1/2 |" in report  # glance: both controllers, then PixelMPC with the levers
    assert "PixelMPC (best), particle filter + model levers" in report and R.LEVER_SETS["model"] in report
    assert "estimate diverged 1" in report and FAULT_LEVELS["map"]["severe"].why in report
    saved = json.loads((tmp_path / "robustness.json").read_text())
    assert len(saved["rows"]) == len(rows) and saved["levels"]["gust"]["moderate"]["why"]
    assert (tmp_path / "robustness.png").stat().st_size > 10_000
    flown.clear()
    R.robustness_experiment(tmp_path, quick=True, progress=False, levers=("model",))
    assert flown == []  # every cell kept


def test_the_fault_free_cells_are_copied_from_another_grid(tmp_path, flown):
    other = tmp_path / "table2"
    cells = [rc.cell for rc in R.robustness_cells(quick=True) if rc.fault == R.NONE]
    grid.run_grid(cells, other, laps=2, seed=R.SEED, progress=False)
    flown.clear()
    rows = R.robustness_experiment(tmp_path / "robustness", quick=True, progress=False, reuse=(other,))
    assert all(spec.faults.active() for spec in flown) and len(flown) == len(rows) - len(cells)
    assert {r["shared_from"] for r in rows if r["fault"] == R.NONE} == {f"table2/{c.name}" for c in cells}


def test_a_cell_flown_with_other_settings_counts_as_not_run(tmp_path, flown):
    R.robustness_experiment(tmp_path, quick=True, progress=False)
    results = json.loads((tmp_path / "results.json").read_text())
    name = "pixelmpc_pf_wind_moderate"
    results[name]["config"]["c_pixel"] = 1.0  # as if the best preset had changed since the cell flew
    (tmp_path / "results.json").write_text(json.dumps(results))
    rows = R.robustness_experiment(tmp_path, quick=True, run=False)
    assert name not in {r["cell"] for r in rows} and len(rows) == len(results) - 1
    assert name in (tmp_path / "REPORT.md").read_text().split("Not yet run")[1]


def test_the_report_of_finished_cells_only(tmp_path):
    rows = R.robustness_experiment(tmp_path, quick=True, run=False)
    assert rows == [] and "Not yet run" in (tmp_path / "REPORT.md").read_text()


def test_the_adapted_noise_flies_on_the_kalman_filter_at_both_levels_and_the_other_sets_at_the_moderate_only():
    cells = _by_name(R.robustness_cells(levers=("adapt", "exact")))
    for controller in ("mppi", "pixelmpc"):
        for fault in ("none", "pixel_noise_moderate", "pixel_noise_severe", "false_severe"):
            spec = cells[f"{controller}_eskf_{fault}_adapt"].cell.spec
            assert spec.eskf.noise_adapt_rate == R.NOISE_ADAPT_RATE and spec.estimator == "eskf"
            assert spec.config == cells[f"{controller}_eskf_{fault}"].cell.spec.config
        assert f"{controller}_eskf_combined_moderate_adapt" in cells
        assert f"{controller}_eskf_pixel_noise_severe_exact" not in cells  # the exact set flies the moderate level
        assert not any(name.endswith("_adapt") and "_eskf_" not in name for name in cells)
    severe = [rc for rc in cells.values() if rc.levers == "adapt" and rc.level == "severe"]
    assert len(severe) == 2 * len(FAULT_LEVELS) and all(rc.laps == 6 for rc in severe)
    assert RaceSpec.from_record(cells["pixelmpc_eskf_pixel_noise_severe_adapt"].cell.spec.record()) == \
        cells["pixelmpc_eskf_pixel_noise_severe_adapt"].cell.spec
    both = _by_name(R.robustness_cells(levers=("model-adapt",)))
    spec = both["mppi_eskf_combined_moderate_model-adapt"].cell.spec
    assert spec.eskf.noise_adapt_rate == R.NOISE_ADAPT_RATE
    assert spec.config.disturbance_time_constant_s == R.DISTURBANCE_TIME_CONSTANT_S
    assert not any(name.endswith("model-adapt") and ("_eskf_" not in name or "severe" in name) for name in both)
