"""The probes (``apps/experiments/speed_probe.py``, ``margin_probe.py``): their cells fly through the experiment
skeleton and leave their reports, on laps faked from the race's target speed."""

import json

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import margin_probe, speed_probe
from pixelmpc_jax.apps.racing import race
from pixelmpc_jax.sim.metrics import LAP_KEYS, MEASURE, aggregate


@pytest.fixture
def flown(monkeypatch):
    """race.run_laps replaced: lap times and visibility from the target speed; a filter lap at 9.1 m/s of the
    ``plain`` clearance (the preset with the vehicle's 0.1 m) hits a gate frame. Records the races flown."""
    calls = []

    def run_laps(spec, **kwargs):
        calls.append(spec)
        plain = spec.config.racing.vehicle_radius < 0.2 and spec.controller == "pixelmpc"
        laps = []
        for i in range(spec.laps):
            success = not (plain and spec.estimator == "pf" and spec.speed > 9.0 and i == 0)
            lap = {key: 1.0 + 0.01 * i for key in LAP_KEYS}
            lap.update(success=success, crash=None if success else "gate", gates_passed=11,
                       lap_time_s=250.0 / spec.speed + 0.1 * i if success else None,
                       time_vis_avoidable_s=0.5 * spec.speed, share_target_in_view=0.8)
            laps.append(lap)
        return {"laps": laps, "aggregate": aggregate(laps), "seed": spec.seed, "interrupted": False,
                "trajectories": [np.zeros((2, 10))] * spec.laps, "covariances": [], "measure": MEASURE}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls


def test_the_speed_probe_flies_nominal_and_each_model_and_weight(tmp_path, flown):
    results = speed_probe.speed_probe(tmp_path, speed=10.0, laps=2, models=("projection",), c_pixels=(9e6, 3e7),
                                      progress=False)
    assert sorted(results) == ["mppi", "pixelmpc_projection_tf1_c3e+07", "pixelmpc_projection_tf1_c9e+06"]
    assert {spec.speed for spec in flown} == {10.0} and len(flown) == 3
    report = (tmp_path / "REPORT.md").read_text()
    assert report.startswith("# Visibility against lap time at a 10 m/s target") and "| mppi | 2/2 |" in report
    assert (tmp_path / "tradeoff.png").stat().st_size > 0


def test_the_margin_probe_sets_the_clearance_against_the_frontier_and_on_the_filter(tmp_path, flown):
    done = margin_probe.margin_probe(tmp_path, seed=3, progress=False)
    truth = json.loads((tmp_path / "truth" / "frontier.json").read_text())
    assert [row["name"] for row in truth["cells"]] == ["margin_v8.5", "plain_v8.5"] == \
        [row["name"] for row in done["truth"]["cells"]]
    assert truth["measured"]["seeds"] == [3, 12] and len(truth["nominal"]) == 8
    rows = json.loads((tmp_path / "pf" / "summary.json").read_text())
    assert [(r["cell"], r["successes"], r["num_laps"], r["failures"]) for r in rows] == [
        ("margin_9.1ms_pf", 25, 25, {}), ("plain_9.1ms_pf", 24, 25, {"gate": 1}),
        ("margin_8.5ms_pf", 25, 25, {}), ("plain_8.5ms_pf", 25, 25, {})]
    assert "| plain_9.1ms_pf | 9.1 | 24/25 |" in (tmp_path / "pf" / "REPORT.md").read_text()
    assert "margin_v8.5" in (tmp_path / "truth" / "REPORT.md").read_text()
