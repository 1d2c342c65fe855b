"""The README's results table (experiments/reporting/readme_table.py, `pixelmpc report --readme`): its rows come from
the folders the results index lists, a frontier gain recomputes from a folder's compact per-tick record, and the
command rewrites or checks the table and docs/results.md's list of folders. Every folder here is a small synthetic one
(``result_folders.py``); that the committed table is current is ``tests/test_readme.py``'s."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import result_folders as rf

from experiments.reporting import index, readme_table
from pixelmpc_jax import cli
from pixelmpc_jax.apps.experiments import frontier
from pixelmpc_jax.apps.racing import grid, presets
from pixelmpc_jax.commands import EXIT_FAILED
from pixelmpc_jax.sim import ticks_compact

FRONTIER = Path("experiments/results/a_frontier")


def _entry(kind: str, folder: Path, claim: str = "{controller}", **params) -> dict:
    return {"kind": kind, "folder": folder.as_posix(), "claim": claim, **params}


def test_a_gain_recomputes_from_a_folders_compact_record_alone(tmp_path):
    """Nominal MPPI: 40 s laps with 1 s avoidable at 6 m/s, 30 s laps with 5 s at 8 m/s; the cell: 35 s laps with
    0.5 s. Flying slower at 35 s would leave 3 s (halfway between the points), so the gain is 3 / 0.5 = 6, and every
    lap being alike, its interval is [6, 6]."""
    ticks_compact.write(tmp_path / ticks_compact.FILE_NAME, {
        "nominal_6": rf.compact_race(6.0, 1600, 40), "nominal_8": rf.compact_race(8.0, 1200, 200),
        "best_v8.5": rf.compact_race(8.5, 1400, 20)})
    row = readme_table.frontier_row_from_compact(tmp_path, "best_v8.5")
    assert row["lap_time_s"] == pytest.approx(35.0) and row["avoidable_s"] == pytest.approx(0.5)
    assert row["frontier_avoidable_s"] == pytest.approx(3.0) and row["frontier_gain"] == pytest.approx(6.0)
    assert row["frontier_gain_interval"] == pytest.approx((6.0, 6.0))
    # paired on each seed's own nominal laps: the same 3 s at 35 s, the same gain
    assert row["gains"]["paired"]["gain"] == pytest.approx(6.0) and row["gains"]["laps_paired"] == 2
    with pytest.raises(ValueError, match="no race 'paper_v8.5'"):
        readme_table.frontier_row_from_compact(tmp_path, "paper_v8.5")


def test_a_row_names_the_preset_its_race_flew_and_refuses_another_controller():
    """A row's controller comes from its folder's record: the preset as it is, the preset before its two options
    against the tail (the races flown before them), the preset with the exact projection, and nothing else."""
    best = presets.preset("best")
    assert readme_table.flown_preset({"name": "best_v8.5", **best.record()}) == "`best`"
    before = best.replace(config=presets.LOOK_AHEAD_BEST)
    assert readme_table.flown_preset(before.record()) == "`best` before its tail options"
    projection = dataclasses.replace(best.config, pixel_model="projection")
    assert readme_table.flown_preset(best.replace(config=projection).record()) == "`best` with the exact projection"
    before_projection = dataclasses.replace(presets.LOOK_AHEAD_BEST, pixel_model="projection")
    with pytest.raises(ValueError, match="'best_projection_v8.5' flew neither"):
        readme_table.flown_preset({"name": "best_projection_v8.5",
                                   **best.replace(config=before_projection).record()})
    other = best.replace(config=dataclasses.replace(best.config, pixel_model="projection", c_pixel=1e6))
    with pytest.raises(ValueError, match="flew neither"):
        readme_table.flown_preset(other.record())


def test_a_frontier_row_reads_its_folder_and_refuses_a_gain_its_per_tick_record_does_not_give(tmp_path):
    """The row of a frontier folder: the paired gain 6 [6, 6] of the synthetic laps, at +16.7 % lap time (`best`'s
    35 s against nominal MPPI's 30 s at the same target, 8.5 m/s); a frontier.json whose paired gain differs from what
    the per-tick record gives is refused."""
    folder = rf.frontier_folder(tmp_path / FRONTIER, nominal={6.0: (1600, 40), 8.5: (1200, 200)})
    row = readme_table.frontier_gain(tmp_path, _entry("frontier_gain", FRONTIER, cell=rf.BEST))
    assert row.claim == "`best`" and row.ours.startswith("paired **6.00** [6.00, 6.00] (2 of 2 laps paired)")
    assert "at +16.7% lap time" in row.ours and row.tail.startswith("2/2 laps finished")
    assert row.loop == "true state, detector clipped at the image border, AlphaPilot, 2 laps, seeds 0-1"
    assert row.per_tick == "yes" and row.folder == FRONTIER
    record = json.loads((folder / "frontier.json").read_text())
    record["cells"][0]["gains"]["paired"]["gain"] += 0.01
    (folder / "frontier.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match="best_v8.5's paired gain is"):
        readme_table.frontier_gain(tmp_path, _entry("frontier_gain", FRONTIER, cell=rf.BEST))


def test_a_frontier_row_refuses_a_nominal_point_flown_on_another_loop(tmp_path):
    """A gain compares laps of one loop: a nominal point recorded with other settings (here another sampling
    temperature, then the ESKF) is not the frontier's nominal MPPI, and the row refuses the folder."""
    folder = rf.frontier_folder(tmp_path / FRONTIER, nominal={6.0: (1600, 40), 8.5: (1200, 200)})
    results = json.loads((folder / "results.json").read_text())
    results["nominal_6"]["config"]["config"]["mppi"]["temperature"] = 123.0
    (folder / "results.json").write_text(json.dumps(results))
    with pytest.raises(ValueError, match="nominal_6 is not nominal MPPI on the loop `best` flew"):
        readme_table.frontier_gain(tmp_path, _entry("frontier_gain", FRONTIER, cell=rf.BEST))


def test_the_visibility_row_reads_the_time_under_half_in_view_at_the_same_lap_time(tmp_path):
    """Nominal MPPI spends 1 s (6 m/s) and 5 s (8.5 m/s) a lap under 50 % in view; at `best`'s 35 s lap, halfway,
    3 s; `best` itself 0.5 s."""
    rf.frontier_folder(tmp_path / FRONTIER, nominal={6.0: (1600, 40), 8.5: (1200, 200)})
    row = readme_table.visibility_at_same_lap_time(tmp_path, _entry("visibility_at_same_lap_time", FRONTIER,
                                                                    cell=rf.BEST))
    assert row.ours == "3.00 -> **0.50** s (paired by seed, 2 of 2 laps)" and row.tail == "worst lap 0.50 s"
    assert row.claim == "`best`"


def test_a_compact_record_that_disagrees_with_its_results_is_refused(tmp_path):
    race = rf.compact_race(8.0, 1200, 200)
    ticks_compact.write(tmp_path / ticks_compact.FILE_NAME, {"nominal_8": race})
    laps = [{**lap} for lap in ticks_compact.race_laps(race)]
    readme_table.check_compact_record(tmp_path, {"nominal_8": {"laps": laps}})  # agrees
    laps[1]["time_vis_avoidable_s"] += rf.DT
    with pytest.raises(ValueError, match="seed 1"):
        readme_table.check_compact_record(tmp_path, {"nominal_8": {"laps": laps}})
    with pytest.raises(ValueError, match="its results do not"):
        readme_table.check_compact_record(tmp_path, {})


def test_the_wilson_interval_of_all_or_none_is_hand_computed():
    z2 = 1.6448536269514722 ** 2
    assert readme_table.wilson_interval(25, 25) == pytest.approx((25 / (25 + z2), 1.0))
    assert readme_table.wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))
    low, high = readme_table.wilson_interval(22, 25)
    assert low < 22 / 25 < high and math.isclose(high - low, 0.2, abs_tol=0.05)


def test_devices_read_from_a_record_or_a_report_line():
    line = "cpu (cpu, 2 device(s)); CPU AMD EPYC, 2 cores; jax 0.10.2, jaxlib 0.10.2"
    assert readme_table.device_name(line) == "2-core AMD EPYC, jax 0.10.2"
    assert readme_table.device_name({"platform": "gpu", "device_kind": "NVIDIA H200", "jax": "0.11.2"}) == (
        "NVIDIA H200, jax 0.11.2")


def test_the_loop_names_an_eskf_told_other_than_its_default_map_accuracy():
    """A race that took the map as exact says so; today's default, a surveyed map's accuracy, adds nothing to the
    words; any other is named."""
    from pixelmpc_jax.apps.racing.spec import RaceSpec
    from pixelmpc_jax.perception.eskf import ESKFConfig

    exact = RaceSpec("pixelmpc", estimator="eskf", detector="image", eskf=ESKFConfig(map_sigma_m=0.0)).record()
    assert readme_table._loop("eskf", exact).startswith("ESKF taking the map as exact, image detector")
    today = RaceSpec("pixelmpc", estimator="eskf").record()
    assert readme_table._loop("eskf", today).startswith("ESKF, ")
    told = RaceSpec("pixelmpc", estimator="eskf", eskf=ESKFConfig(map_sigma_m=0.5)).record()
    assert readme_table._loop("eskf", told).startswith("ESKF told the map to 0.5 m, ")
    assert readme_table._loop("pf", exact).startswith("particle filter, ")


def test_a_row_follows_its_folder(tmp_path):
    """The table reads the folders as they are: a changed figure in a folder changes its row."""
    folder = Path("experiments/results/dof_eval")
    rf.dof_eval_folder(tmp_path / folder, aee_px=9.876)
    row = readme_table.dof_accuracy(tmp_path, _entry("dof_accuracy", folder, "The DOF's flow error"))
    assert row.ours == "9.88 px/frame" and row.paper == "2.45 px/frame" and row.per_tick == "n/a"
    assert row.measured_on == "2-core Intel Xeon @ 2.80 GHz, jax 0.10.2, 2026-11-21"
    assert row.claim == "The DOF's flow error" and row.folder == folder


ONBOARD_PACE = Path("experiments/results/onboard_pace")
RACES = {"mppi": ["nominal"], "pixelmpc": ["best_0", "best_2"]}


def _onboard_pace_folder(root: Path) -> Path:
    """Nominal MPPI flown as one race of 4 laps (seeds 0-3, the last lost at a gate frame) and `best` as two of 2
    (seeds 0-1, 2-3), each a `pixelmpc race --loop onboard` at the 16 m/s label's pace in a folder of its own."""
    folder = root / ONBOARD_PACE
    pace = presets.PAPER_PACE_SPEEDS[16.0]
    best = presets.preset("best").replace(estimator="eskf", detector="image", speed=pace)
    races = {"nominal": ("mppi", presets.nominal_of(best), rf.compact_race(pace, 1200, 40, laps=4)),
             "best_0": ("pixelmpc", best, rf.compact_race(pace, 1300, 10, laps=2)),
             "best_2": ("pixelmpc", best, rf.compact_race(pace, 1310, 10, laps=2, first_seed=2))}
    races["nominal"][2]["finished"][3] = False
    for name, (controller, spec, race) in races.items():
        laps = ticks_compact.race_laps(race)
        if controller == "mppi":
            laps[3].update(crash="gate_frame")
        record = spec.replace(laps=len(laps), seed=int(race["seed"][0])).record()
        (folder / name).mkdir(parents=True)
        (folder / name / "metrics.json").write_text(json.dumps({"race": record, "controllers": {
            controller: {"race": record, "laps": laps}}}))
    ticks_compact.write(folder / ticks_compact.FILE_NAME, {name: race for name, (_, _, race) in races.items()})
    (folder / "README.md").write_text(f"# Onboard\n\n{rf.DEVICE_LINE}\n")
    return folder


def test_the_onboard_pace_row_counts_each_races_laps_and_refuses_a_record_that_disagrees(tmp_path):
    """The row joins each controller's races and reads their laps from their metrics: a lap recorded lost there
    changes the count and the failures; the per-tick record, which still shows it finished, then refuses the
    folder."""
    folder = _onboard_pace_folder(tmp_path)
    entry = _entry("onboard_pace", ONBOARD_PACE, "{label:g} m/s, {controller}", races=RACES)
    row = readme_table.onboard_pace(tmp_path, entry)
    assert row.ours.startswith("3/4 -> **4/4**") and "gate frame 1" in row.tail
    assert "4 laps a controller, seeds 0-3" in row.loop and row.claim == "16 m/s, `best`"
    assert row.measured_on == "2-core AMD EPYC, jax 0.10.2, 2026-11-28"
    metrics = json.loads((folder / "best_2" / "metrics.json").read_text())
    metrics["controllers"]["pixelmpc"]["laps"][1].update(success=False, crash="wall")
    (folder / "best_2" / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match="race 'best_2', seed 3"):
        readme_table.onboard_pace(tmp_path, entry)


@pytest.mark.parametrize("change, refusal", [({"estimator": "truth"}, "not pixelmpc on the loop"),
                                             ({"seed": 3}, "its first seed is 3, the race before ended at 1")])
def test_the_onboard_pace_row_refuses_a_race_on_another_loop_or_seeds_with_a_gap(tmp_path, change, refusal):
    """A controller's races join only when each flew the folder's loop and they follow one another in seed."""
    folder = _onboard_pace_folder(tmp_path)
    metrics = json.loads((folder / "best_2" / "metrics.json").read_text())
    metrics["controllers"]["pixelmpc"]["race"].update(change)
    (folder / "best_2" / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match=refusal):
        readme_table.onboard_pace(tmp_path, _entry("onboard_pace", ONBOARD_PACE, races=RACES))


def test_the_pace_row_pairs_each_lap_with_nominal_laps_of_the_seeds_best_flew_only(tmp_path):
    """`best` at the 16 m/s label's pace flew seeds 0-1 of a frontier that holds seeds 0-3: its joined means read
    nominal MPPI's laps of those seeds alone. Nominal's laps of seeds 2-3 avoid twice as long; read with them, the
    joined means would differ."""
    pace = presets.PAPER_PACE_SPEEDS[16.0]
    frontier_path, pace_path = Path("experiments/results/validation"), Path("experiments/results/pace")
    rf.frontier_folder(tmp_path / frontier_path, nominal={6.0: (1600, 40)}, laps=4)
    folder = rf.frontier_folder(tmp_path / pace_path, nominal={pace: (1200, 200)}, laps=4)
    results = json.loads((folder / "results.json").read_text())
    races = ticks_compact.load(folder / ticks_compact.FILE_NAME)
    nominal_name = frontier.nominal_cell(pace).name
    races[nominal_name]["visibility"][2:, 1:401] = 0.2  # seeds 2-3: 10 s avoidable
    results[nominal_name]["laps"] = ticks_compact.race_laps(races[nominal_name])
    best = rf.compact_race(pace, 1400, 20, laps=2)
    races["best"] = best
    ticks_compact.write(folder / ticks_compact.FILE_NAME, races)
    (folder / "results.json").write_text(json.dumps(results))
    record = presets.preset("best").replace(speed=pace, laps=2, seed=0).record()
    (folder / "best").mkdir()
    (folder / "best" / "metrics.json").write_text(json.dumps({"race": record, "controllers": {
        "pixelmpc": {"race": record, "laps": ticks_compact.race_laps(best)}}}))
    entry = _entry("pace_paired_gain", pace_path, "{controller} at {label:g} ({speed:g} m/s)",
                   frontiers=[frontier_path.as_posix(), pace_path.as_posix()])
    row = readme_table.pace_paired_gain(tmp_path, entry)
    # seeds 0-1: nominal 1 s at 40 s and 5 s at 30 s; at `best`'s 35 s, 3 s against its 0.5 s
    assert "joined means 6.00" in row.ours and "paired **6.00**" in row.ours
    assert row.claim == "`best` at 16 (9.1 m/s)" and "median lap +16.7%" in row.ours
    assert "[validation](experiments/results/validation/) and [pace](experiments/results/pace/)" in row.loop


def test_every_kind_of_row_the_index_may_name_has_a_reader():
    assert set(readme_table.KINDS) >= {"frontier_gain", "courses_gain", "onboard_pace", "real_time", "dof_accuracy",
                                       "table_iv_filter", "table_iv_eskf", "paper_main_cell", "nominal_lap",
                                       "pace_paired_gain", "aggressive_paired_gain", "visibility_at_same_lap_time"}
    with pytest.raises(ValueError, match="no row of kind 'guess'"):
        readme_table.row(Path("."), _entry("guess", Path("experiments/results/x")))


# --------------------------------------------------------------------------------------------------
# The index and the command on a synthetic checkout.
# --------------------------------------------------------------------------------------------------


def _checkout(tmp_path: Path, readme: str, results_doc: str | None = None) -> Path:
    """A checkout of two folders: a DOF evaluation the README's one row reads (current) and a probe (exploratory),
    beside a superseded folder gone from disk."""
    rf.dof_eval_folder(tmp_path / "experiments/results/dof_eval")
    (tmp_path / "experiments/results/probe").mkdir(parents=True)
    (tmp_path / "experiments/results/probe/README.md").write_text("# A probe\n")
    folders = {"dof_eval": {"status": "current", "claim": "The DOF's flow error", "command": "pixelmpc evaluate",
                            "record_schema": None},
               "probe": {"status": "exploratory", "claim": "A probe", "command": None, "record_schema": 1},
               "old_eval": {"status": "superseded", "claim": "An earlier evaluation", "command": None,
                            "record_schema": None, "superseded_by": "dof_eval", "commit": "abc1234"}}
    rows = [_entry("dof_accuracy", Path("experiments/results/dof_eval"), "The DOF's flow error")]
    doc = f"# Results\n\n{index.BEGIN}\n{index.END}\n" if results_doc is None else results_doc
    return rf.checkout(tmp_path, folders, rows, readme, doc)


def test_report_checks_then_rewrites_a_stale_table_and_folder_list(tmp_path, capsys):
    stale = f"# title\n\n{readme_table.BEGIN}\n| old | table |\n{readme_table.END}\n\ntail\n"
    root = _checkout(tmp_path, stale)
    assert cli.main(["report", "--readme", "--check", "--root", str(root)]) == EXIT_FAILED
    assert "-| old | table |" in capsys.readouterr().out
    assert (root / "README.md").read_text() == stale  # --check changes nothing
    assert cli.main(["report", "--readme", "--root", str(root)]) == 0
    rewritten = (root / "README.md").read_text()
    assert rewritten.startswith("# title\n") and rewritten.endswith(f"{readme_table.END}\n\ntail\n")
    table = readme_table.table(root)
    assert table in rewritten and table.count("\n") == 2  # the head, its rule and the index's one row
    assert "| The DOF's flow error | 1.17 px/frame |" in table
    listed = (root / "docs/results.md").read_text()
    assert "- [dof_eval](../experiments/results/dof_eval/README.md): The DOF's flow error" in listed
    assert "- [probe](../experiments/results/probe/README.md): A probe" in listed
    assert ("- `old_eval/` (at abc1234): An earlier evaluation; superseded by "
            "[dof_eval](../experiments/results/dof_eval/README.md)") in listed
    assert cli.main(["report", "--readme", "--check", "--root", str(root)]) == 0


def test_a_readme_without_its_markers_is_refused(tmp_path, capsys):
    root = _checkout(tmp_path, "# no table here\n")
    assert cli.main(["report", "--readme", "--root", str(root)]) == 2
    assert "results:begin" in capsys.readouterr().err
    for argv in (["report", "--readme", "--compact", str(root)], ["report"], ["report", "--compact", str(root)]):
        with pytest.raises(SystemExit) as done:  # one of the two jobs, and a folder with per-tick records
            cli.main(argv)
        assert done.value.code == 2


def test_report_outside_a_checkout_with_its_tools_is_refused_in_one_line(tmp_path, capsys):
    (tmp_path / "experiments/results").mkdir(parents=True)
    (tmp_path / "README.md").write_text("# a copy without the tools\n")
    assert cli.main(["report", "--readme", "--root", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "tools in experiments/reporting/" in err and err.count("\n") == 1


@pytest.mark.parametrize("change, refusal", [
    (lambda i: i.update(schema=2), "schema 2"),
    (lambda i: i["folders"]["probe"].update(status="kept"), "probe: status 'kept'"),
    (lambda i: i["folders"].pop("probe"), "probe: in experiments/results, not in the index"),
    (lambda i: i["folders"]["old_eval"].pop("commit"), "old_eval: superseded, it must name"),
    (lambda i: i["folders"]["dof_eval"].update(status="exploratory"), "which the index does not mark current"),
])
def test_an_index_that_disagrees_with_its_folders_is_refused(tmp_path, change, refusal):
    root = _checkout(tmp_path, "# title\n")
    path = root / index.INDEX
    data = json.loads(path.read_text())
    assert index.load(root) == data
    change(data)
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=refusal):
        index.load(root)


def test_an_index_refuses_a_kept_folder_without_its_readme_and_a_superseded_one_still_there(tmp_path):
    root = _checkout(tmp_path, "# title\n")
    (root / "experiments/results/probe/README.md").unlink()
    (root / "experiments/results/old_eval").mkdir()
    (root / "experiments/results/old_eval/README.md").write_text("# An earlier evaluation\n")
    found = index.problems(root, json.loads((root / index.INDEX).read_text()))
    assert found == ["old_eval: superseded, yet still in experiments/results",
                     "probe: exploratory, yet experiments/results/probe/README.md is missing"]


def test_a_grid_cell_result_reads_back_as_the_race_it_flew():
    """The synthetic folders record their cells as a grid does: each reads back as its race."""
    cell = grid.Cell(rf.BEST, presets.preset("best"))
    recorded = rf.cell_results(cell, rf.compact_race(8.5, 1400, 20), seed=3)
    assert grid.flies_race(recorded, cell.race(2, 3, None)) and not grid.flies_race(recorded, cell.race(2, 4, None))
    assert np.isclose(recorded["laps"][0]["lap_time_s"], 35.0)
