"""The README's results table (apps/readme_table.py, `pixelmpc report`): its rows come from the result folders, a
frontier gain recomputes from a folder's compact per-tick record, and the command rewrites or checks the table."""

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from pixelmpc_jax import cli
from pixelmpc_jax.apps import readme_table
from pixelmpc_jax.apps.experiments import gains
from pixelmpc_jax.commands import EXIT_FAILED
from pixelmpc_jax.sim import metrics, ticks_compact

ROOT = Path(__file__).resolve().parent.parent
DT = 0.025


def _race(speed: float, num_ticks: int, avoidable_ticks: int, laps: int = 2, first_seed: int = 0) -> dict:
    """A compact record of ``laps`` finished laps of ``num_ticks`` ticks, each with ``avoidable_ticks`` ticks at 20 %
    visibility that the floor cannot excuse (a pointed camera would see the whole gate)."""
    visibility = np.ones((laps, num_ticks + 1), np.float32)
    visibility[:, 1:avoidable_ticks + 1] = 0.2
    return {"seed": np.arange(first_seed, first_seed + laps), "num_ticks": np.full(laps, num_ticks),
            "finished": np.ones(laps, bool), "target": np.zeros((laps, num_ticks + 1), np.int8),
            "visibility": visibility, "pointed_visibility": np.ones((laps, num_ticks + 1), np.float32),
            "excused": np.zeros((laps, num_ticks + 1), bool), "target_speed": np.asarray(speed),
            "dt": np.asarray(DT), "measure": np.asarray(metrics.MEASURE)}


def test_a_gain_recomputes_from_a_folders_compact_record_alone(tmp_path):
    """Nominal MPPI: 40 s laps with 1 s avoidable at 6 m/s, 30 s laps with 5 s at 8 m/s; the cell: 35 s laps with
    0.5 s. Flying slower at 35 s would leave 3 s (halfway between the points), so the gain is 3 / 0.5 = 6, and every
    lap being alike, its interval is [6, 6]."""
    ticks_compact.write(tmp_path / ticks_compact.FILE_NAME, {
        "nominal_6": _race(6.0, 1600, 40), "nominal_8": _race(8.0, 1200, 200), "best_v8.5": _race(8.5, 1400, 20)})
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
    against the tail (the races flown before them), and nothing else."""
    from pixelmpc_jax.apps.racing import presets

    best = presets.preset("best")
    assert readme_table.flown_preset({"name": "best_v8.5", **best.record()}) == "`best`"
    before = best.replace(config=presets.LOOK_AHEAD_BEST)
    assert readme_table.flown_preset(before.record()) == "`best` before its tail options"
    results = json.loads((ROOT / "experiments" / "results" / "best_heldout_700" / "results.json").read_text())
    assert readme_table.flown_preset(results["best_v8.5"]["config"]) == "`best` before its tail options"
    with pytest.raises(ValueError, match="'best_projection_v8.5' flew neither"):
        readme_table.flown_preset(results["best_projection_v8.5"]["config"])
    # today's preset with the exact projection (a tilted camera's race), and nothing else with it
    course = json.loads((ROOT / "experiments" / "results" / "best_courses_2500" / "course_2501" / "results.json")
                        .read_text())
    assert readme_table.flown_preset(course["best_projection_v8.5"]["config"]) == "`best` with the exact projection"
    other = best.replace(config=dataclasses.replace(best.config, pixel_model="projection", c_pixel=1e6))
    with pytest.raises(ValueError, match="flew neither"):
        readme_table.flown_preset(other.record())


def test_a_frontier_folder_whose_paired_gain_differs_from_its_per_tick_record_is_refused(tmp_path):
    folder = tmp_path / "experiments" / "results" / "best_onboard_2000"
    folder.mkdir(parents=True)
    for name in ("frontier.json", "results.json", "ticks_compact.npz"):
        shutil.copy(ROOT / "experiments" / "results" / "best_onboard_2000" / name, folder / name)
    row = readme_table.frontier_gain("best_onboard_2000", "{controller}")(tmp_path)
    assert row.claim == "`best` before its tail options" and row.ours.startswith("paired **3.42** [2.92, 4.03]")
    record = json.loads((folder / "frontier.json").read_text())
    record["cells"][0]["gains"]["paired"]["gain"] += 0.01
    (folder / "frontier.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match="best_v8.5's paired gain is"):
        readme_table.frontier_gain("best_onboard_2000", "{controller}")(tmp_path)


def test_a_compact_record_that_disagrees_with_its_results_is_refused(tmp_path):
    race = _race(8.0, 1200, 200)
    ticks_compact.write(tmp_path / ticks_compact.FILE_NAME, {"nominal_8": race})
    laps = [{**lap} for lap in ticks_compact.race_laps(race)]
    readme_table.check_compact_record(tmp_path, {"nominal_8": {"laps": laps}})  # agrees
    laps[1]["time_vis_avoidable_s"] += DT
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


def test_every_row_names_a_folder_that_exists_and_says_whether_it_commits_per_tick_data():
    rows = [make(ROOT) for make in readme_table.ROWS]
    assert len(rows) == len(readme_table.ROWS) >= 8
    for row in rows:
        assert (ROOT / row.folder).is_dir(), row.folder
        assert row.per_tick in ("yes", "no", "n/a")
        assert (row.per_tick == "yes") == bool(readme_table.compact_records(ROOT / row.folder))
        assert all(path.is_file() for path in readme_table.compact_records(ROOT / row.folder))
        assert readme_table.ISO_DATE.search(row.measured_on), row


def test_the_loop_names_an_eskf_told_other_than_its_default_map_accuracy():
    """A race recorded without the Kalman filter's settings flew the map as exact (its default then); today's
    default, a surveyed map's accuracy, adds nothing to the words; any other is named."""
    from pixelmpc_jax.apps.racing.spec import RaceSpec
    from pixelmpc_jax.perception.eskf import ESKFConfig

    then = {"estimator": "eskf", "detector": "image", "gate_switch": "estimate"}
    assert readme_table._loop("eskf", then).startswith("ESKF taking the map as exact, image detector")
    today = RaceSpec("pixelmpc", estimator="eskf").record()
    assert readme_table._loop("eskf", today).startswith("ESKF, ")
    told = RaceSpec("pixelmpc", estimator="eskf", eskf=ESKFConfig(map_sigma_m=0.5)).record()
    assert readme_table._loop("eskf", told).startswith("ESKF told the map to 0.5 m, ")
    assert readme_table._loop("pf", then).startswith("particle filter, ")


def test_the_tables_row_puts_the_paper_cell_beside_nominal_at_both_paces_from_the_per_tick_record():
    """Tables II-III's row: at the 14 m/s label and at its pace, nominal MPPI -> the `paper` preset under this measure
    and the paper's rule; each mean recomputes from the folder's committed compact per-tick record alone."""
    row = readme_table.paper_main_cell(ROOT)
    folder = ROOT / row.folder
    races = ticks_compact.load(folder / ticks_compact.FILE_NAME)
    summary = {c["cell"]: c for c in json.loads((folder / "summary.json").read_text())}
    for speed in (14.0, 8.5):
        paper = next(c for c in summary.values() if c["preset"] == "paper" and c["speed"] == speed)
        for cell in (f"nominal_{speed:g}", paper["cell"]):
            laps = ticks_compact.race_laps(races[cell])
            for key in ("time_vis_below_50_s", "time_vis_below_50_after_seen_s"):
                mean = float(np.mean([lap[key] for lap in laps]))  # over every lap, as the results aggregate
                assert mean == pytest.approx(summary[cell][key]["mean"], abs=1e-9), (cell, key)
        nominal = summary[f"nominal_{speed:g}"]
        assert (f"{speed:g} m/s: {nominal['time_vis_below_50_s']['mean']:.1f} -> "
                f"**{paper['time_vis_below_50_s']['mean']:.1f}** s") in row.ours
    assert row.per_tick == "yes"


def test_a_row_follows_its_folder(tmp_path):
    """The table reads the folders as they are: a changed figure in a folder changes its row."""
    folder = tmp_path / "experiments" / "results" / "dof_eval"
    shutil.copytree(ROOT / "experiments" / "results" / "dof_eval", folder)
    data = json.loads((folder / "dof_eval.json").read_text())
    (folder / "dof_eval.json").write_text(json.dumps({**data, "aee_px": 9.876}))
    row = readme_table.dof_accuracy(tmp_path)
    assert row.ours == "9.88 px/frame" and row.paper == "2.45 px/frame" and row.per_tick == "n/a"
    assert row.measured_on == f"2-core Intel Xeon @ 2.80 GHz, jax 0.10.2, {data['created'][:10]}"


EARLIER_ONBOARD_PACE = Path("experiments/results/onboard_16ms_pace")  # `best` flown as two races of 20 laps
EARLIER_ONBOARD_PACE_RACES = {"mppi": ("nominal",), "pixelmpc": ("best_2100", "best_2120")}


def test_the_onboard_pace_row_counts_each_races_laps_and_refuses_a_record_that_disagrees(tmp_path):
    """The row joins each controller's races and reads their laps from their metrics: a lap recorded lost there
    changes the count and the failures; the per-tick record, which still shows it finished, then refuses the
    folder."""
    folder = tmp_path / EARLIER_ONBOARD_PACE
    shutil.copytree(ROOT / EARLIER_ONBOARD_PACE, folder)
    row = readme_table.onboard_pace(EARLIER_ONBOARD_PACE, EARLIER_ONBOARD_PACE_RACES)(tmp_path)
    assert row.ours.startswith("37/40 -> **40/40**") and "target mismatch 2" in row.tail
    assert "40 laps a controller, seeds 2100-2139" in row.loop and row.claim.endswith("(`best`)")
    assert "ESKF taking the map as exact" in row.loop  # flown before a surveyed map's accuracy was the default
    metrics = json.loads((folder / "best_2120" / "metrics.json").read_text())
    metrics["controllers"]["pixelmpc"]["laps"][5].update(success=False, crash="wall")
    (folder / "best_2120" / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match=f"race 'best_2120', seed {metrics['race']['seed'] + 5}"):
        readme_table.onboard_pace(EARLIER_ONBOARD_PACE, EARLIER_ONBOARD_PACE_RACES)(tmp_path)


@pytest.mark.parametrize("change, refusal", [({"estimator": "truth"}, "not pixelmpc on the loop"),
                                             ({"seed": 2121}, "its first seed is 2121, the race before ended at 2119")])
def test_the_onboard_pace_row_refuses_a_race_on_another_loop_or_seeds_with_a_gap(tmp_path, change, refusal):
    """A controller's races join only when each flew the folder's loop and they follow one another in seed."""
    folder = tmp_path / EARLIER_ONBOARD_PACE
    shutil.copytree(ROOT / EARLIER_ONBOARD_PACE, folder)
    metrics = json.loads((folder / "best_2120" / "metrics.json").read_text())
    metrics["controllers"]["pixelmpc"]["race"].update(change)
    (folder / "best_2120" / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match=refusal):
        readme_table.onboard_pace(EARLIER_ONBOARD_PACE, EARLIER_ONBOARD_PACE_RACES)(tmp_path)


def _checkout(tmp_path, readme: str) -> Path:
    for name in ("experiments", "benchmarks"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "README.md").write_text(readme)
    return tmp_path


def test_report_checks_then_rewrites_a_stale_table(tmp_path, capsys):
    stale = f"# title\n\n{readme_table.BEGIN}\n| old | table |\n{readme_table.END}\n\ntail\n"
    root = _checkout(tmp_path, stale)
    assert cli.main(["report", "--readme", "--check", "--root", str(root)]) == EXIT_FAILED
    assert "-| old | table |" in capsys.readouterr().out
    assert (root / "README.md").read_text() == stale  # --check changes nothing
    assert cli.main(["report", "--readme", "--root", str(root)]) == 0
    rewritten = (root / "README.md").read_text()
    assert rewritten.startswith("# title\n") and rewritten.endswith(f"{readme_table.END}\n\ntail\n")
    assert readme_table.table(root) in rewritten
    assert cli.main(["report", "--readme", "--check", "--root", str(root)]) == 0


def test_a_readme_without_its_markers_is_refused(tmp_path, capsys):
    root = _checkout(tmp_path, "# no table here\n")
    assert cli.main(["report", "--readme", "--root", str(root)]) == 2
    assert "results:begin" in capsys.readouterr().err
    for argv in (["report", "--readme", "--compact", str(root)], ["report"], ["report", "--compact", str(root)]):
        with pytest.raises(SystemExit) as done:  # one of the two jobs, and a folder with per-tick records
            cli.main(argv)
        assert done.value.code == 2


def _copy_tracked(name: str, into: Path) -> Path:
    """A result folder copied with the files its checkout commits (the full per-tick records left out)."""
    folder = into / readme_table.RESULTS / name
    shutil.copytree(ROOT / readme_table.RESULTS / name, folder,
                    ignore=shutil.ignore_patterns("trajectories_*.npz", "ticks_[!c]*.npz", "covariances_*.npz"))
    return folder


def test_the_pace_row_pairs_each_lap_with_nominal_laps_of_the_seeds_best_flew_only(tmp_path):
    """`best` at the 16 m/s label's pace flew fewer seeds than the validation frontier holds: its joined means and
    local fit read nominal MPPI's laps of those seeds alone, which differs from reading them all."""
    folders = [_copy_tracked(folder.name, tmp_path) for folder in readme_table.PACE_FRONTIER]
    row = readme_table.pace_paired_gain(tmp_path)
    metrics_ = json.loads((folders[1] / "best" / "metrics.json").read_text())["controllers"]["pixelmpc"]
    cell = gains.completed_laps({"laps": metrics_["laps"]})
    seeds = set(cell.seed.tolist())
    points = {}
    for folder in folders:
        record = json.loads((folder / "frontier.json").read_text())
        results = json.loads((folder / "results.json").read_text())
        for point in record["nominal"]:
            points.setdefault(point["name"], (point["speed"], results[point["name"]]))
    everyone = [gains.completed_laps(result) for _, result in sorted(points.values(), key=lambda p: p[0])]
    mine = [gains.Laps(*(field[np.isin(laps.seed, sorted(seeds))] for field in laps)) for laps in everyone]
    joined_mine = gains.frontier_gains(cell, mine)["joined_means"]["gain"]
    joined_all = gains.frontier_gains(cell, everyone)["joined_means"]["gain"]
    assert f"joined means {joined_mine:.2f}" in row.ours and f"{joined_mine:.2f}" != f"{joined_all:.2f}"
    assert len(seeds) == 50 and "50/50 laps finished" in row.tail


def test_the_pace_row_refuses_a_nominal_point_flown_with_other_settings(tmp_path):
    """A nominal point of the pace folder flown at another sampling temperature is not the frontier's nominal MPPI."""
    folders = [_copy_tracked(folder.name, tmp_path) for folder in readme_table.PACE_FRONTIER]
    results = json.loads((folders[1] / "results.json").read_text())
    results["nominal_9.1"]["config"]["config"]["mppi"]["temperature"] = 123.0
    (folders[1] / "results.json").write_text(json.dumps(results))
    with pytest.raises(ValueError, match="nominal_9.1 is not nominal MPPI on the loop"):
        readme_table.pace_paired_gain(tmp_path)


def test_the_onboard_row_reads_a_frontier_whose_every_point_flew_the_onboard_loop(tmp_path):
    """The onboard row is its frontier folder's `best` cell against nominal MPPI flown slower, all on the onboard
    loop; a nominal point flown on another loop (here, the ESKF told the map is exact) is refused, as the gain would
    compare laps of two loops."""
    path = readme_table.RESULTS / readme_table.ONBOARD_FRONTIER
    shutil.copytree(ROOT / path, tmp_path / path, ignore=shutil.ignore_patterns("*.png"))
    row = readme_table.onboard_gain(tmp_path)
    assert row.claim.startswith("The same (`best`) on the onboard loop") and row.folder == path
    assert row.loop.startswith("ESKF, image detector, gate switch from the estimate, AlphaPilot, 20 laps")
    assert row.tail.startswith("20/20 laps finished")
    results = json.loads((tmp_path / path / "results.json").read_text())
    results["nominal_8"]["config"]["eskf"] = {**results["nominal_8"]["config"].get("eskf", {}), "map_sigma_m": 0.0}
    (tmp_path / path / "results.json").write_text(json.dumps(results))
    with pytest.raises(ValueError, match="nominal_8 is not nominal MPPI on the loop `best` flew"):
        readme_table.onboard_gain(tmp_path)
