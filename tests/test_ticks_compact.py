"""The compact per-tick record (sim/ticks_compact.py): what the visibility measure reads, kept small enough to commit,
giving back the figures of the race it was written from."""

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pixelmpc_jax.sim import metrics, ticks_compact
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

DATA = Path(__file__).resolve().parent / "data"
DT = 0.025


def _approach_lap(seed: int = 3) -> dict:
    """A hand-made lap of 40 ticks flown straight at gate 0's centre from 2.525 m, 0.05 m a tick (2 m/s): in full view
    until tick 20, then at 20 % visibility; from 2 m on (tick 11) a camera pointed at the gate sees under half of it."""
    gates = course_lib.load_course().gates
    distance = 2.525 - 0.05 * np.arange(41)
    states = np.zeros((41, 10), np.float32)
    states[:, :3] = np.asarray(gates.centre[0]) - np.outer(distance, [1.0, 0.0, 0.0])
    states[:, 3] = 1.0
    return {"seed": seed, "num_ticks": 40, "finished": True, "target": np.zeros(41, np.int32),
            "visibility": np.r_[np.ones(21), np.full(20, 0.2)].astype(np.float32),
            "pointed_visibility": np.where(distance <= 2.0, 0.3, 1.0).astype(np.float32), "states": states,
            "estimates": states.copy(), **{f"gate_{f}": np.asarray(getattr(gates, f)) for f in ticks_lib.GATE_FIELDS}}


def test_a_hand_made_lap_gives_its_hand_computed_figures():
    """Ticks 21-40 are under 50 % where the pointed camera sees under half: the floor could excuse all 20, but the
    farthest lies 1.475 m from the gate, which a straight flight at the race's 4 m/s covers in 15 ticks (0.1 m a
    tick). The 15 nearest are excused; the 5 the slow approach lingered are avoidable."""
    record = ticks_lib.stack([_approach_lap()], camera_lib.default_camera(), target_speed=4.0)
    race = ticks_compact.from_record(record)
    assert race["excused"].dtype == bool
    assert np.flatnonzero(race["excused"][0]).tolist() == list(range(26, 41))  # the 15 nearest the gate
    figures = ticks_compact.lap_figures(race, 0)
    assert figures["success"] and figures["lap_time_s"] == pytest.approx(40 * DT)
    assert figures["time_vis_below_50_s"] == pytest.approx(20 * DT)
    assert figures["time_vis_avoidable_s"] == pytest.approx(5 * DT)
    assert figures["time_vis_zero_s"] == 0.0 and figures["share_target_in_view"] == 1.0
    assert figures["time_vis_below_50_after_seen_s"] == pytest.approx(20 * DT)  # gate 0 was seen from the start


def test_the_record_round_trips_and_an_update_keeps_the_other_races(tmp_path):
    race = ticks_compact.from_record(ticks_lib.stack([_approach_lap(3), _approach_lap(4)],
                                                     camera_lib.default_camera(), target_speed=4.0))
    path = tmp_path / ticks_compact.FILE_NAME
    ticks_compact.write(path, {"nominal_8": race})
    ticks_compact.update(path, {"best_v8.5": race})
    loaded = ticks_compact.load(path)
    assert sorted(loaded) == ["best_v8.5", "nominal_8"]
    assert list(ticks_compact.load(path, ["nominal_8"])) == ["nominal_8"]  # one race read alone
    for field in ticks_compact.FIELDS:
        np.testing.assert_array_equal(loaded["nominal_8"][field], race[field])
    assert loaded["best_v8.5"]["target"].dtype == np.int8 and str(loaded["best_v8.5"]["measure"]) == metrics.MEASURE
    assert [lap["seed"] for lap in ticks_compact.race_laps(loaded["best_v8.5"])] == [3, 4]


def test_a_record_that_kept_the_distances_reads_as_one_with_the_excused_ticks(tmp_path):
    """A folder's record written before the excused ticks (``floor_distance``: the distances where the pointed
    camera sees under half, NaN elsewhere, zlib members) gives the same laps and, rewritten, the current fields."""
    record = ticks_lib.stack([_approach_lap(3), _approach_lap(4)], camera_lib.default_camera(), target_speed=4.0)
    race = ticks_compact.from_record(record)
    distance = 2.525 - 0.05 * np.arange(41)
    old = {**{k: v for k, v in race.items() if k != "excused"},
           "floor_distance": np.tile(np.where(distance <= 2.0, distance, np.nan), (2, 1)).astype(np.float32)}
    path = tmp_path / ticks_compact.FILE_NAME
    np.savez_compressed(path, **{f"best/{field}": value for field, value in old.items()})
    loaded = ticks_compact.load(path)["best"]
    assert "floor_distance" not in loaded
    np.testing.assert_array_equal(loaded["excused"], race["excused"])
    assert ticks_compact.race_laps(loaded) == ticks_compact.race_laps(race)
    ticks_compact.update(path, {"nominal": race})
    assert sorted(ticks_compact.load(path)) == ["best", "nominal"]
    with np.load(path) as data:  # the members LZMA-compressed, the file a plain npz still
        assert "best/floor_distance.npy" not in data.zip.namelist()
        assert data.zip.getinfo("best/excused.npy").compress_type == zipfile.ZIP_LZMA


def test_a_record_measured_otherwise_or_named_with_a_slash_is_refused(tmp_path):
    race = ticks_compact.from_record(ticks_lib.stack([_approach_lap()], camera_lib.default_camera(), 4.0))
    with pytest.raises(ValueError, match="'/'"):
        ticks_compact.write(tmp_path / "x.npz", {"a/b": race})
    with pytest.raises(ValueError, match="after-first-seen"):
        ticks_compact.lap_figures({**race, "measure": np.asarray("after-first-seen")}, 0)
    with pytest.raises(ValueError, match="no per-tick record"):
        ticks_compact.convert_folder(tmp_path)


def test_the_committed_race_record_gives_back_the_figures_its_race_recorded():
    """A small race (`pixelmpc race --laps 2 --max-time 5 --samples 64`, both controllers) and its compact record: each
    lap's time below 50 %, avoidable time and share in view recompute from the record alone."""
    races = ticks_compact.load(DATA / "small_race_ticks_compact.npz")
    recorded = json.loads((DATA / "small_race_metrics.json").read_text())["controllers"]
    assert sorted(races) == sorted(recorded) == ["mppi", "pixelmpc"]
    for name, race in races.items():
        laps = ticks_compact.race_laps(race)
        assert len(laps) == len(recorded[name]["laps"]) == 2
        for lap, want in zip(laps, recorded[name]["laps"]):
            assert lap["seed"] == want["seed"] and lap["success"] == want["success"]
            for key in ("time_vis_below_50_s", "time_vis_zero_s", "time_vis_avoidable_s", "share_target_in_view",
                        "time_vis_below_50_after_seen_s"):
                assert lap[key] == pytest.approx(want[key], abs=1e-9), (name, key)
        assert any(lap["time_vis_below_50_s"] > 0 for lap in laps), "a lap with nothing to recompute proves little"
