"""The main job: PixelMPC beside nominal MPPI (apps/racing/compare.py), the presets, and the two visibility families of
the lap metrics (the share of time with the target in view, the angle to it)."""

import dataclasses
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import standard_race
from standard_race import BATCH, TICKS

from pixelmpc_jax.apps.racing import compare, presets, race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.sim import metrics, ticks_compact
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

SMALL = standard_race.PIXELMPC.config


def test_both_controllers_alternate_batch_by_batch_and_record_every_tick(monkeypatch, tmp_path):
    """PixelMPC and nominal MPPI fly a batch each in turn; metrics.json and ticks_<controller>.npz hold matching
    laps of both after every batch, and the per-tick record alone gives back each lap's visibility figures."""
    order, saved_laps = [], []
    fly_batches, write = race.fly_batches, compare.write_json_atomic

    def recorded_batches(prepared):
        for laps in fly_batches(prepared):
            order.append((prepared.spec.controller, [lap.record["seed"] for lap in laps]))
            yield laps

    def recorded_write(path, record):
        saved_laps.append({name: len(res["laps"]) for name, res in record["controllers"].items()})
        write(path, record)

    monkeypatch.setattr(race, "fly_batches", recorded_batches)
    monkeypatch.setattr(compare, "write_json_atomic", recorded_write)
    spec = standard_race.PIXELMPC.replace(laps=3, seed=7)
    record = compare.run_compare(spec, out=tmp_path, preset="small", batch_size=BATCH, progress=False)
    assert order == [("pixelmpc", [7, 8]), ("mppi", [7, 8]), ("pixelmpc", [9]), ("mppi", [9])]
    assert saved_laps == [{"pixelmpc": 2}, {"pixelmpc": 2, "mppi": 2}, {"pixelmpc": 3, "mppi": 2},
                          {"pixelmpc": 3, "mppi": 3}]
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["preset"] == "small" and not saved["interrupted"]
    assert saved["controllers"]["mppi"]["race"] == json.loads(json.dumps(presets.nominal_of(spec).record()))
    assert saved["controllers"]["mppi"]["measure"] == metrics.MEASURE
    # no lap finishes in 1 s: nothing to read on the committed frontier, and metrics.json says why
    assert saved["nominal_frontier"] == compare.frontier_entry(saved)
    assert saved["nominal_frontier"]["why"] == "PixelMPC completed no lap"
    for name in ("pixelmpc", "mppi"):
        record_ticks = ticks_lib.load(tmp_path / f"ticks_{name}.npz")
        laps = saved["controllers"][name]["laps"]
        assert record_ticks["seed"].tolist() == [7, 8, 9] and record_ticks["states"].shape[:2] == (3, TICKS + 1)
        assert record_ticks["num_ticks"].tolist() == [TICKS] * 3 and record_ticks["gate_centre"].shape[2] == 3
        np.testing.assert_array_equal(record_ticks["states"][0], record["flown"][name]["trajectories"][0])
        assert np.isnan(record_ticks["estimates"][0, TICKS]).all()
        assert np.isfinite(record_ticks["estimates"][0, :TICKS]).all()
        for i, lap in enumerate(laps):
            recomputed = ticks_lib.lap_visibility(record_ticks, i)
            for key, value in recomputed.items():
                assert lap[key] == pytest.approx(value, abs=1e-9), key
    compact = ticks_compact.load(ticks_compact.convert_folder(tmp_path))  # what a result folder commits
    for name in ("pixelmpc", "mppi"):
        for lap, recomputed in zip(saved["controllers"][name]["laps"], ticks_compact.race_laps(compact[name])):
            for key, value in recomputed.items():
                assert lap[key] == pytest.approx(value, abs=1e-9), (name, key)
    assert (tmp_path / "trajectories.png").stat().st_size > 0 and (tmp_path / "visibility.png").stat().st_size > 0
    table = compare.side_by_side(record)
    assert "PixelMPC" in table.splitlines()[0] and "avoidable vis < 50 %" in table and "paper's rule" in table


def test_the_side_by_side_table_holds_the_tail():
    """PixelMPC finished 3 of 4 laps, the worst 39 s over a median of 33 s (+18.2 %, 1 of 3 more than 10 % over);
    nominal MPPI all 3, the worst 1.6 % over."""
    def laps(times):
        return [{"success": t is not None, "lap_time_s": t, "gates_passed": 11, "crash": None if t else "gate"}
                for t in times]

    pixel, nominal = laps([33.0, 32.0, 39.0, None]), laps([32.0, 32.0, 32.5])
    record = {"race": RaceSpec("pixelmpc", SMALL, speed=8.5).record(),
              "controllers": {"pixelmpc": {"laps": pixel, "aggregate": metrics.aggregate(pixel)},
                              "mppi": {"laps": nominal, "aggregate": metrics.aggregate(nominal)}}}
    lines = compare.side_by_side(record).splitlines()
    start = len(lines[0]) - 30  # the label column, two spaces, then a value in 14 characters, two spaces, a value
    rows = {line[:start].strip(): [line[start:start + 14].strip(), line[start + 16:].strip()] for line in lines[1:]}
    assert rows["laps completed"] == ["3/4", "3/3"]
    assert rows["worst lap vs median"] == ["+18.2 %", "+1.6 %"]
    assert rows["laps > 10 % over median"] == ["1 (33.3 %)", "0 (0.0 %)"]


# ~50 s (a race process of its own): test_both_controllers_alternate_batch_by_batch_and_record_every_tick covers what
# both controllers record, tests/test_host_signals.py a command stopped by SIGTERM keeping what it finished
@pytest.mark.slow
def test_a_race_stopped_by_sigterm_keeps_the_finished_laps_of_both_controllers(tmp_path):
    """``pixelmpc race --laps 100`` stopped by SIGTERM, as a batch scheduler stops it, once both controllers have
    flown a batch: it exits 130 and its metrics.json and ticks files hold the finished laps of both (the race is
    tests/standard_race.py's, saved as ``pixelmpc tune`` saves one)."""
    saved_race, out = tmp_path / "race.json", tmp_path / "out"
    saved_race.write_text(json.dumps(standard_race.PIXELMPC.record()))
    # one CPU device, as the test processes have: the laps fly the programs the tests compile (split over the cores,
    # a batch is a program of its own)
    command = [sys.executable, "-m", "pixelmpc_jax.cli", "--cpu-devices", "1", "race", "--config", str(saved_race),
               "--out", str(out), "--laps", "100", "--batch", str(BATCH)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    metrics_file, deadline = out / "metrics.json", time.monotonic() + 400
    try:
        while time.monotonic() < deadline and process.poll() is None:
            if metrics_file.exists():
                flown = json.loads(metrics_file.read_text())["controllers"]
                if len(flown) == 2:
                    break
            time.sleep(0.2)
        assert process.poll() is None, process.stderr.read()
        process.send_signal(signal.SIGTERM)
        code = process.wait(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert code == 130
    saved = json.loads(metrics_file.read_text())
    assert saved["interrupted"] is True
    laps = {name: len(res["laps"]) for name, res in saved["controllers"].items()}
    assert set(laps) == {"pixelmpc", "mppi"} and BATCH <= laps["mppi"] <= laps["pixelmpc"] <= laps["mppi"] + BATCH
    assert laps["pixelmpc"] < 100
    for name, count in laps.items():
        assert ticks_lib.load(out / f"ticks_{name}.npz")["seed"].tolist() == list(range(count))


def test_the_presets():
    paper, best = presets.preset("paper"), presets.preset("best")
    assert paper.speed == 14.0 and paper.config.pixel_cost == "l1" and paper.config.c_pixel == 9e6
    assert paper.dof_weights is None  # the paper's own DOF weights
    assert best.speed == presets.PAPER_PACE_SPEED and best.config.pixel_cost == "border"
    assert best.config.pixel_model == "vdof" and best.key() != paper.key()
    # best flies the tuned trial it names (the search's best feasible trial), exactly as the search recorded it, but
    # for the detector (the search flew the ideal projection, the preset the projection cut at the image border) and
    # the two options against its tail: the look-ahead from the plan, the map's pixel for a gate cut by the border
    results = Path(__file__).resolve().parent.parent / "experiments" / "results"
    record = results / "tune_look_ahead" / "best.json"
    trial = RaceSpec.from_record(json.loads(record.read_text())).replace(laps=1, seed=0)
    assert trial.detector == "ideal" and best.detector == "clipped"
    assert trial.config == presets.LOOK_AHEAD_BEST and trial.replace(detector="clipped").key() != best.key()
    options = dataclasses.replace(trial.config, look_ahead_from="plan", partial_target="map")
    assert trial.replace(detector="clipped", config=options).key() == best.key()
    assert best.config.racing.vehicle_radius == presets.BEST_VEHICLE_RADIUS_M == 0.3
    assert best.config.target_prior == "kept" and best.config.look_ahead_model == "projection"
    # the preset before it, the search without the projection look-ahead, as that search recorded it
    former = RaceSpec.from_record(json.loads((results / "tune_levers" / "best.json").read_text()))
    assert former.config == presets.LEVERS_BEST and former.config.look_ahead_model == "own"
    assert best.config != presets.HAND_TUNED_BEST and presets.HAND_TUNED_BEST.box_size_limit == 0.5
    with pytest.raises(ValueError, match="unknown preset 'fast'"):
        presets.preset("fast")


@pytest.mark.parametrize("yaw, angle", [(0.0, 0.0), (np.pi / 2, 90.0), (np.pi / 4, 45.0)])
def test_the_angle_to_the_target_is_the_optical_axis_against_the_ray_to_its_centre(yaw, angle):
    track = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=20.0)
    x = quadrotor.hover_state((0.0, 0.0, 3.0), yaw=yaw)
    states = np.stack([np.asarray(x)] * 3)
    visibility = np.asarray([1.0, 0.0, 1.0])
    view = metrics.view_metrics(states, visibility, np.zeros(3, np.int32), 2, track.gates,
                                camera_lib.default_camera())
    assert view["mean_target_angle_deg"] == pytest.approx(angle, abs=1e-3)
    assert view["share_target_in_view"] == pytest.approx(0.5)  # ticks 1 and 2: hidden, then in view


def test_a_lap_reports_both_view_figures():
    assert {"share_target_in_view", "mean_target_angle_deg"} <= set(metrics.LAP_KEYS)
    assert metrics.view_metrics(jnp.zeros((1, 10)), np.ones(1), np.zeros(1, np.int32), 0, None, None) == {
        "share_target_in_view": None, "mean_target_angle_deg": None}
