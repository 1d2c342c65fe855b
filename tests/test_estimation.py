"""The state-estimation experiment's bookkeeping: cells, summary and report from recorded laps."""

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import estimation as E
from pixelmpc_jax.sim import metrics


def _lap(success, lap_time, cov_max, error, crash=None):
    return {"success": success, "lap_time_s": lap_time, "crash": crash, "gates_passed": 11 if success else 3,
            "max_position_cov_trace": cov_max, "mean_position_error_m": error, "rms_position_error_m": error,
            "time_vis_below_50_s": 1.0,
            "time_vis_zero_s": 0.0, "total_variation_roll": 1.0, "total_variation_pitch": 1.0,
            "total_variation_yaw": 1.0, "mean_linear_acc": 1.0, "mean_angular_acc": 1.0, "mean_speed": 9.0,
            "flight_time_s": lap_time or 5.0}


def test_cells_cover_the_paper_grid_at_the_labels_and_the_paces():
    cells = E.race_cells()
    names = [c.name for c in cells]
    assert len(names) == 10 and len(set(names)) == 10
    assert all(c.spec.estimator == "pf" and c.spec.course == "alphapilot" for c in cells)
    at = {(E.who_of(c), c.spec.speed) for c in cells}
    assert at == {("mppi", 14.0), ("paper", 14.0), ("mppi", 16.0), ("paper", 16.0),
                  ("mppi", 8.5), ("paper", 8.5), ("best", 8.5), ("mppi", 9.1), ("paper", 9.1), ("best", 9.1)}
    for cell in cells:
        who = E.who_of(cell)
        assert cell.spec.controller == ("mppi" if who == "mppi" else "pixelmpc")
        if who == "paper":
            assert cell.spec.config.t_f == 1.0 and cell.spec.config.c_pixel == 9e6
            assert cell.spec.config.pixel_model == "dof" and cell.spec.config.pixel_cost == "l1"
        if who == "best":
            assert cell.spec.config.pixel_model == "vdof"
    assert {E.label_of(c) for c in cells} == {14.0, 16.0}
    lanes = E.straight_cells()
    assert all(c.spec.course == "straight" for c in lanes)
    assert {(E.who_of(c), c.spec.speed) for c in lanes} == {("mppi", 20.0), ("paper", 20.0), ("mppi", 10.3),
                                                           ("paper", 10.3), ("best", 10.3)}
    assert [c.spec.speed for c in E.race_cells(quick=True)] == [9.1] * 3
    # Table IV on the Kalman filter: the same races on its estimate, beside the paper's filter's
    both = E.race_cells(estimators=E.ESTIMATORS)
    assert len(both) == 20 and [c.spec.estimator for c in both] == ["pf"] * 10 + ["eskf"] * 10
    assert [c.spec.replace(estimator="pf") for c in both[10:]] == [c.spec for c in cells]
    assert both[10].name == cells[0].name.replace("_pf", "_eskf")


def test_table_iv_on_the_onboard_loop_flies_the_same_races_with_only_what_the_drone_has():
    """`--estimators onboard --paces-only`: the races of the ESKF's cells at the two paces, on the onboard loop (the
    image detector, the switch from the estimate, the surveyed map), each named and reported by its loop."""
    eskf = E.race_cells(estimators=("eskf",), at_labels=False)
    onboard = E.race_cells(estimators=("onboard",), at_labels=False)
    assert [c.spec.speed for c in onboard] == [9.1] * 3 + [8.5] * 3
    assert [E.who_of(c) for c in onboard] == ["mppi", "paper", "best"] * 2
    assert [c.name for c in onboard] == [c.name.replace("_eskf", "_onboard") for c in eskf]
    for ours, theirs in zip(onboard, eskf):
        assert (ours.spec.detector, ours.spec.estimator, ours.spec.gate_switch, ours.spec.map) == \
            ("image", "eskf", "estimate", "surveyed")
        assert ours.spec.replace(detector=theirs.spec.detector, map=theirs.spec.map) == theirs.spec
        assert E.loop_of(ours) == "onboard" and E.loop_of(theirs) == "eskf"
    assert {E.loop_of(c) for c in E.race_cells(estimators=E.ESTIMATORS) + E.straight_cells()} == {"pf", "eskf"}
    assert [c.spec.speed for c in E.race_cells(at_labels=False)] == [9.1] * 3 + [8.5] * 3
    # a run split by label: each process flies its label's cells, together the table
    halves = [E.race_cells((label,), estimators=("onboard",), at_labels=False) for label in (16.0, 14.0)]
    assert [c.name for half in halves for c in half] == [c.name for c in onboard]
    with pytest.raises(ValueError, match="unknown estimator 'ukf'"):
        E.race_cells(estimators=("ukf",))


def test_a_run_split_by_controller_flies_each_cell_once_in_the_grids_order():
    """`pixelmpc experiment table4 --controllers`: each process flies its controllers' cells of the full grid, in its
    order, and the processes' cells together are the grid; an unknown name is refused before anything flies."""
    full = [c.name for c in E.race_cells(estimators=E.ESTIMATORS)]
    split = {who: [c.name for c in E.race_cells(estimators=E.ESTIMATORS, who=(who,))] for who in E.WHO}
    assert split["best"] == [name for name in full if name.startswith("best_")] and len(split["best"]) == 4
    assert sorted(sum(split.values(), [])) == sorted(full)
    assert [c.name for c in E.race_cells(quick=True, who=("mppi", "best"))] == ["mppi_9.1ms_pf", "best_9.1ms_pf"]
    assert [c.name for c in E.straight_cells(quick=True, who=("best",))] == ["best_straight_10.3ms_pf"]
    with pytest.raises(ValueError, match="unknown controller 'nominal'"):
        E.race_cells(who=("nominal",))


def test_summary_counts_successes_failures_and_covariance_maxima():
    cells = E.race_cells(quick=True) + E.straight_cells(quick=True)
    laps = [_lap(True, 30.0, 2.0, 0.3), _lap(False, None, 9.0, 1.2, "gate"), _lap(False, None, 4.0, 0.8, "gate"),
            _lap(True, 32.0, 1.0, 0.2)]
    results = {c.name: {"laps": laps, "aggregate": metrics.aggregate(laps), "wall_time_s": 60.0} for c in cells}
    race_rows = E.summarise(results, cells[:3])
    straight_rows = E.summarise(results, cells[3:])
    row = race_rows[0]
    assert row["success_rate"] == 0.5 and row["failures"] == {"gate": 2}
    assert row["label"] == 16.0 and row["point"] == "pace"
    assert abs(row["lap_time_s"]["mean"] - 31.0) < 1e-9
    maxima = np.asarray([2.0, 9.0, 4.0, 1.0])
    assert abs(row["sigma_max"]["mean"] - maxima.mean()) < 1e-9 and row["sigma_max"]["max"] == 9.0
    assert abs(row["mean_position_error_m"] - 0.625) < 1e-9
    report = E.markdown_report(race_rows, straight_rows, "cpu")
    assert "| nominal MPPI | particle filter | 16 m/s | 9.1 m/s | 2/4 (50%) | 52% |" in report
    assert "| PixelMPC, `paper` | particle filter | 16 m/s | 9.1 m/s | 2/4 (50%) | 60% |" in report
    assert "| PixelMPC, `best` | particle filter | 16 m/s | 9.1 m/s | 2/4 (50%) | 60% |" in report
    # the RMS position error over the laps (0.3, 1.2, 0.8, 0.2 m)
    assert abs(row["rms_position_error_m"] - np.sqrt(np.mean(np.square([0.3, 1.2, 0.8, 0.2])))) < 1e-9
    assert "9.2" in report and "5.7" in report  # the paper's straight-lane figures beside ours
    assert "Wall time of the cells flown here: 6.0 min" in report


def test_cpu_cells_fly_in_small_batches():
    import jax

    from pixelmpc_jax.apps.racing import grid

    assert jax.default_backend() == "cpu"
    assert grid.default_batch_size(25) == grid.CPU_BATCH < 25
    assert grid.default_batch_size(1) == 1
