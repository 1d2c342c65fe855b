"""The state-estimation experiment's bookkeeping: cells, summary and report from recorded laps."""

import numpy as np

from pixelmpc_jax.apps import estimation as E
from pixelmpc_jax.sim import metrics


def _lap(success, lap_time, cov_max, error, crash=None):
    return {"success": success, "lap_time_s": lap_time, "crash": crash, "gates_passed": 11 if success else 3,
            "max_position_cov_trace": cov_max, "mean_position_error_m": error, "time_vis_below_50_s": 1.0,
            "time_vis_zero_s": 0.0, "total_variation_roll": 1.0, "total_variation_pitch": 1.0,
            "total_variation_yaw": 1.0, "mean_linear_acc": 1.0, "mean_angular_acc": 1.0, "mean_speed": 9.0,
            "flight_time_s": lap_time or 5.0}


def test_cells_cover_the_paper_grid():
    names = [c.name for c in E.race_cells()]
    assert len(names) == 4 and len(set(names)) == 4
    assert all(c.spec.estimator == "pf" and c.spec.config.t_f == 1.0 and c.spec.config.c_pixel == 9e6
               for c in E.race_cells())
    assert {(c.spec.controller, c.spec.speed) for c in E.race_cells()} == set(E.PAPER_TABLE_IV)
    assert all(c.spec.course == "straight" and c.spec.speed == 20.0 for c in E.straight_cells())


def test_summary_counts_successes_failures_and_covariance_maxima():
    cells = E.race_cells((16.0,)) + E.straight_cells()
    laps = [_lap(True, 30.0, 2.0, 0.3), _lap(False, None, 9.0, 1.2, "gate"), _lap(False, None, 4.0, 0.8, "gate"),
            _lap(True, 32.0, 1.0, 0.2)]
    results = {c.name: {"laps": laps, "aggregate": metrics.aggregate(laps), "wall_time_s": 60.0} for c in cells}
    race_rows = E.summarise(results, cells[:2])
    straight_rows = E.summarise(results, cells[2:])
    row = race_rows[0]
    assert row["success_rate"] == 0.5 and row["failures"] == {"gate": 2}
    assert abs(row["lap_time_s"]["mean"] - 31.0) < 1e-9
    maxima = np.asarray([2.0, 9.0, 4.0, 1.0])
    assert abs(row["sigma_max"]["mean"] - maxima.mean()) < 1e-9 and row["sigma_max"]["max"] == 9.0
    assert abs(row["mean_position_error_m"] - 0.625) < 1e-9
    report = E.markdown_report(race_rows, straight_rows, "cpu")
    assert "| mppi | 16 m/s | 50% of 4 | 52% |" in report
    assert "| pixelmpc | 16 m/s | 50% of 4 | 60% |" in report
    assert "9.2" in report and "5.7" in report  # the paper's straight-lane figures beside ours
    assert "Wall time of the cells run: 4.0 min" in report


def test_courses_by_name():
    import pytest

    from pixelmpc_jax.apps.race import make_course

    assert make_course("alphapilot").num_gates == 11
    straight = make_course("straight")
    assert straight.num_gates == 5
    np.testing.assert_allclose(np.diff(np.asarray(straight.gates.centre)[:, 0]), 20.0)
    with pytest.raises(ValueError, match="unknown course"):
        make_course("monza")


def test_cpu_cells_fly_in_small_batches():
    import jax

    from pixelmpc_jax.apps import grid

    assert jax.default_backend() == "cpu"
    assert grid.default_batch_size(25) == grid.CPU_BATCH < 25
    assert grid.default_batch_size(1) == 1
