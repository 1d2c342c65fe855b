"""Nominal MPPI's committed frontier shipped in the package (apps/racing/nominal_frontier.py): the file is what its
folder gives (`pixelmpc report --frontier-data`, experiments/reporting/frontier_data.py), it is read at PixelMPC's lap
time, only for a race it speaks for, and the main job prints that beside its table (apps/racing/compare.py)."""

import json
from pathlib import Path

import pytest
import result_folders as rf

from experiments.reporting import frontier_data
from pixelmpc_jax import cli
from pixelmpc_jax.apps.racing import compare, nominal_frontier, presets
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.commands import EXIT_FAILED
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.sim import metrics
from pixelmpc_jax.sim.faults import Faults

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data"
# nominal MPPI's two points of the shipped frontier either side of 28.3875 s (lap time s, avoidable s, share in view)
AT_10_M_S = (26.54, 19.425, 0.5296458945298397)
AT_8_5_M_S = (30.230000000000008, 13.242500000000001, 0.7891274738199557)
PROJECTION = RaceSpec("pixelmpc", ControllerConfig(pixel_model="projection"), speed=8.5)


def _lap(lap_time_s, avoidable_s=1.0, share=0.97) -> dict:
    return {"success": lap_time_s is not None, "lap_time_s": lap_time_s, "time_vis_avoidable_s": avoidable_s,
            "time_vis_below_50_s": avoidable_s + 2.0, "share_target_in_view": share, "mean_target_angle_deg": 28.0,
            "gates_passed": 11 if lap_time_s is not None else 4, "crash": None if lap_time_s is not None else "gate"}


def _results(laps: list[dict], measure: str | None = metrics.MEASURE) -> dict:
    """A controller's results in a comparison's record, as the race's lap book keeps them."""
    return {"measure": measure, "laps": laps, "aggregate": metrics.aggregate(laps)}


def test_the_shipped_frontier_is_what_its_folder_gives():
    """``pixelmpc report --frontier-data --check`` passes on this checkout: the package's copy is what the committed
    folder the index names gives (run ``pixelmpc report --frontier-data`` when the folder changes)."""
    old, new = frontier_data.rewrite(ROOT, check=True)
    assert old == new, "pixelmpc_jax/data/nominal_frontier.json is stale: run `pixelmpc report --frontier-data`"
    shipped = nominal_frontier.load()
    assert shipped == json.loads(new) and shipped["source"] == frontier_data.source(ROOT).as_posix()
    assert (shipped["course"], shipped["estimator"], shipped["perturb"], shipped["camera_tilt_deg"],
            shipped["faults"]) == ("alphapilot", "truth", False, 0.0, {})
    assert shipped["measure"] == metrics.MEASURE
    assert nominal_frontier.FILE == ROOT / frontier_data.IN_PACKAGE  # the package's copy is the checkout's


HELD_OUT = Path("experiments/results/held_out")


def _checkout(tmp_path) -> Path:
    """A checkout whose index ships the package's frontier from a synthetic frontier folder (nominal MPPI at 6 and
    8 m/s: 40 s laps with 1 s avoidable, 30 s laps with 5 s), without the shipped file yet."""
    rf.frontier_folder(tmp_path / HELD_OUT)
    folders = {HELD_OUT.name: {"status": "current", "claim": "a frontier", "command": None, "record_schema": 1,
                               "ships": frontier_data.IN_PACKAGE.as_posix()}}
    return rf.checkout(tmp_path, folders, [], "# a checkout\n", "# results\n")


def test_report_writes_checks_then_rewrites_the_file_when_its_folder_changes(tmp_path, capsys):
    root = _checkout(tmp_path)
    argv = ["report", "--frontier-data", "--root", str(root)]
    (root / frontier_data.IN_PACKAGE).parent.mkdir(parents=True)
    assert cli.main(argv) == 0 and cli.main([*argv, "--check"]) == 0
    written = json.loads((root / frontier_data.IN_PACKAGE).read_text())
    assert written["source"] == HELD_OUT.as_posix() and written["seeds"] == [0, 1]
    assert [(p["speed"], p["lap_time_s"], p["avoidable_s"]) for p in written["points"]] == [(6.0, 40.0, 1.0),
                                                                                             (8.0, 30.0, 5.0)]
    path = root / HELD_OUT / "frontier.json"
    record = json.loads(path.read_text())
    record["nominal"][1]["avoidable_s"] = 8.25  # nominal_8
    path.write_text(json.dumps(record))
    capsys.readouterr()
    before = (root / frontier_data.IN_PACKAGE).read_text()
    assert cli.main([*argv, "--check"]) == EXIT_FAILED
    assert '+      "avoidable_s": 8.25,' in capsys.readouterr().out
    assert (root / frontier_data.IN_PACKAGE).read_text() == before  # unchanged
    assert cli.main(argv) == 0
    assert json.loads((root / frontier_data.IN_PACKAGE).read_text())["points"][1]["avoidable_s"] == 8.25
    assert cli.main([*argv, "--check"]) == 0


def test_a_folder_whose_nominal_points_were_flown_in_two_worlds_is_refused(tmp_path):
    root = _checkout(tmp_path)
    path = root / HELD_OUT / "results.json"
    results = json.loads(path.read_text())
    results["nominal_8"]["config"]["estimator"] = "pf"
    path.write_text(json.dumps(results))
    with pytest.raises(ValueError, match="one world under one measure"):
        frontier_data.build(root)


def test_the_frontier_is_read_at_pixelmpcs_mean_lap_time_between_two_points():
    """PixelMPC's completed laps of 28.0 s and 28.77 s (a lost lap aside) average 28.385 s, halfway between
    nominal MPPI's points at 10 m/s (26.54 s) and 8.5 m/s (30.23 s): nominal's figures are their means."""
    assert (AT_10_M_S[0] + AT_8_5_M_S[0]) / 2 == pytest.approx(28.385, abs=1e-12)
    laps = [_lap(28.0, 1.0, 0.96), _lap(28.77, 1.5, 0.98), _lap(None, 6.0, 0.5)]
    entry = nominal_frontier.held_against(PROJECTION.record(), _results(laps))
    assert entry["why"] is None and entry["lap_time_s"] == pytest.approx(28.385, abs=1e-12)
    assert entry["nominal"]["avoidable_s"] == pytest.approx(16.33375, abs=1e-9)  # (19.425 + 13.2425) / 2
    assert entry["nominal"]["share_target_in_view"] == pytest.approx(0.6593866842, abs=1e-9)
    assert entry["pixelmpc"] == pytest.approx({"avoidable_s": 1.25, "vis_below_50_s": 3.25,
                                               "share_target_in_view": 0.97, "mean_target_angle_deg": 28.0,
                                               "laps_completed": 2})
    # at a point's own lap time the read is that point's figures
    point = nominal_frontier.load()["points"][1]
    entry = nominal_frontier.held_against(PROJECTION.record(), _results([_lap(point["lap_time_s"])]))
    assert entry["nominal"]["avoidable_s"] == pytest.approx(point["avoidable_s"], rel=1e-12)
    assert entry["nominal"]["share_target_in_view"] == pytest.approx(point["share_target_in_view"], rel=1e-12)


@pytest.mark.parametrize("race, measure, why", [
    (PROJECTION.replace(course="straight"), metrics.MEASURE,
     "the committed frontier was flown on the AlphaPilot course, this race on the straight lane"),
    ({**PROJECTION.record(), "course": "runs/a_course_no_longer_here.json"}, metrics.MEASURE,
     "the committed frontier was flown on the AlphaPilot course, this race on runs/a_course_no_longer_here.json"),
    (PROJECTION.replace(estimator="pf"), metrics.MEASURE,
     "the committed frontier was flown on estimator truth, this race on pf"),
    (PROJECTION.replace(perturb=True), metrics.MEASURE,
     "this race perturbs the gates; the committed frontier flew them where the map puts them"),
    (PROJECTION.replace(camera_tilt_deg=20.0), metrics.MEASURE,
     "this race's camera is tilted 20 deg; the committed frontier saw through the paper's camera (tilt 0 deg)"),
    (PROJECTION.replace(faults=Faults(wind=(3.0, 0.0, 0.0), gust=1.5)), metrics.MEASURE,
     "this race adds faults (wind, gust); the committed frontier flew without faults"),
    (PROJECTION, "after-first-seen",
     f"this race is measured under after-first-seen, the committed frontier under {metrics.MEASURE}"),
    (PROJECTION, None, f"this race records no measure, the committed frontier under {metrics.MEASURE}"),
])
def test_a_race_the_frontier_does_not_speak_for_says_why_in_one_line(race, measure, why):
    record = race if isinstance(race, dict) else race.record()
    entry = nominal_frontier.held_against(record, _results([_lap(33.5)], measure))
    assert entry["why"] == why and "nominal" not in entry
    assert nominal_frontier.describe(entry) == (
        f"nominal MPPI at PixelMPC's lap time, on the committed frontier: not shown, {why}")
    # the same laps in the race the frontier speaks for are held against it
    assert nominal_frontier.held_against(PROJECTION.record(), _results([_lap(33.5)]))["why"] is None


@pytest.mark.parametrize("pixelmpc, why", [
    (None, "PixelMPC did not fly"),
    (_results([_lap(None), _lap(None)]), "PixelMPC completed no lap"),
    (_results([_lap(40.0)]), "PixelMPC's lap time, 40.00 s, lies outside the committed frontier's lap times "
                             "(26.54-35.96 s), and it is never extrapolated"),
    (_results([_lap(22.0)]), "PixelMPC's lap time, 22.00 s, lies outside the committed frontier's lap times "
                             "(26.54-35.96 s), and it is never extrapolated"),
])
def test_no_figure_without_a_completed_lap_inside_the_frontiers_lap_times(pixelmpc, why):
    entry = nominal_frontier.held_against(PROJECTION.record(), pixelmpc)
    assert entry["why"] == why and "nominal" not in entry
    assert entry["frontier"]["source"] == "experiments/results/best_heldout_700"


def test_the_main_job_prints_nominal_mppi_at_pixelmpcs_lap_time_below_its_table():
    """A race record as the comparison writes it (the `best` preset, PixelMPC's laps of 33.0 s and 34.01 s, nominal
    MPPI's faster one): below the table, nominal MPPI read on the frontier at 33.505 s, between its points at 8 m/s
    (31.735 s, 9.3825 s avoidable) and 7 m/s (35.9575 s, 3.595 s): 9.3825 - 5.7875 * 1.77 / 4.2225 = 6.96 s."""
    pixel, nominal = [_lap(33.0, 1.0, 0.97), _lap(34.01, 1.26, 0.98)], [_lap(30.2, 13.0, 0.79)]
    spec = presets.preset("best").replace(laps=2)
    record = {"preset": "best", "race": spec.record(), "interrupted": False,
              "controllers": {"pixelmpc": {"race": spec.record(), **_results(pixel)},
                              "mppi": {"race": presets.nominal_of(spec).record(), **_results(nominal)}}}
    lines = compare.side_by_side(record).splitlines()
    assert lines[-4:] == [
        "",
        "nominal MPPI at PixelMPC's lap time (33.50 s), on the committed frontier: avoidable 6.96 s below 50 %, in "
        "view 90.3 %",
        "  (PixelMPC here: avoidable 1.13 s, in view 97.5 %, over its 2 completed lap(s))",
        "  from experiments/results/best_heldout_700: nominal MPPI at 7-10 m/s, 10 laps a speed, seeds 700-709 "
        "(2-core AMD EPYC, jax 0.10.2, 2026-11-28)"]
    assert lines[0].split() == ["PixelMPC", "nominal", "MPPI"]  # the table above it as before
    entry = compare.frontier_entry(record)
    assert entry["nominal"]["avoidable_s"] == pytest.approx(9.3825 - 5.7875 * 1.77 / 4.2225, abs=1e-9)


def test_a_recorded_race_without_a_finished_lap_says_so_below_its_table():
    """The committed small race (`pixelmpc race --laps 2 --max-time 5 --samples 64`): no lap finished in 5 s."""
    record = json.loads((DATA / "small_race_metrics.json").read_text())
    assert compare.side_by_side(record).splitlines()[-1] == (
        "nominal MPPI at PixelMPC's lap time, on the committed frontier: not shown, PixelMPC completed no lap")
