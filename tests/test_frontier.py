"""The speed frontier: interpolation and gain, strict JSON, report and plot, the CLI, a tiny flight."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import standard_race

from pixelmpc_jax import cli
from pixelmpc_jax.apps.experiments import frontier as F
from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.racing import frontier_curve, grid
from pixelmpc_jax.sim.metrics import LOSS_CAUSES, MEASURE


def lap(lap_time, vis, unavoidable, above=None, success=True):
    """A lap's metrics: ``vis`` s below 50 %, ``unavoidable`` of it unavoidable, the rest above the image."""
    causes = dict.fromkeys(LOSS_CAUSES[1:], 0.0)
    causes["above"] = vis - unavoidable if above is None else above
    return {"success": success, "lap_time_s": lap_time if success else None, "time_vis_below_50_s": vis,
            "time_vis_avoidable_s": vis - unavoidable, "time_vis_below_50_excused_s": unavoidable,
            **{f"time_vis_below_50_{k}_s": v for k, v in causes.items()}}


def nominal_results():
    # avoidable 1 s at 40 s laps (6 m/s), 5 s at 32 s (8 m/s), 8 s at 26 s (10 m/s)
    return {"nominal_6": {"laps": [lap(39.0, 3.0, 2.0), lap(41.0, 3.0, 2.0)]},
            "nominal_8": {"laps": [lap(32.0, 7.5, 2.5), lap(32.0, 7.5, 2.5)]},
            "nominal_10": {"laps": [lap(26.0, 10.0, 2.0), lap(26.0, 10.0, 2.0)]}}


CELL_IN = F.pixel_cell("projection", "border")
CELL_OUT = F.pixel_cell("projection", "l1", c_pixel=3e7)
CELL_ZERO = F.pixel_cell("dof", "border")
CELL_LOST = F.pixel_cell("dof", "l1")
CELLS = (CELL_IN, CELL_OUT, CELL_ZERO, CELL_LOST)


def hand_made_results():
    results = nominal_results()
    results[CELL_IN.name] = {"laps": [lap(35.0, 4.0, 2.5), lap(37.0, 4.0, 2.5)]}  # lap 36 s, avoidable 1.5 s
    results[CELL_OUT.name] = {"laps": [lap(45.0, 4.0, 3.0)]}  # slower than every nominal lap
    results[CELL_ZERO.name] = {"laps": [lap(34.0, 2.0, 2.0)]}  # nothing avoidable
    results[CELL_LOST.name] = {"laps": [lap(33.0, 5.0, 2.0), lap(None, 1.0, 0.5, success=False)]}
    return results


def hand_made():
    return F.build(hand_made_results(), (6.0, 8.0, 10.0), CELLS, laps=2, seed=0)


def by_name(frontier):
    return {c["name"]: c for c in frontier["cells"]}


def test_a_cell_between_two_nominal_points_gets_the_interpolated_frontier_and_gain():
    frontier = hand_made()
    assert [p["speed"] for p in frontier["nominal"]] == [6.0, 8.0, 10.0]
    assert frontier["nominal"][0]["lap_time_s"] == pytest.approx(40.0)
    assert frontier["nominal"][0]["avoidable_s"] == pytest.approx(1.0)
    assert frontier["nominal"][0]["causes"]["above"] == pytest.approx(1.0)
    cell = by_name(frontier)[CELL_IN.name]
    assert cell["lap_time_s"] == pytest.approx(36.0) and cell["lap_time_two_sigma_s"] == pytest.approx(2.0)
    assert cell["avoidable_s"] == pytest.approx(1.5)
    # halfway between (40 s, 1 s) and (32 s, 5 s): 3 s; gain 3 / 1.5
    assert cell["frontier_avoidable_s"] == pytest.approx(3.0)
    assert cell["frontier_gain"] == pytest.approx(2.0)
    assert cell["bracketed"] and cell["all_laps_completed"] and cell["success_rate"] == 1.0
    assert cell["options"] == {"pixel_cost": "border"} and cell["c_pixel"] == 9e6 and cell["t_f"] == 1.0


def test_a_cell_outside_the_nominal_range_is_not_extrapolated():
    cell = by_name(hand_made())[CELL_OUT.name]
    assert cell["bracketed"] is False
    assert cell["frontier_avoidable_s"] is None and cell["frontier_gain"] is None
    assert cell["suggested_nominal_speed"] == 5.0  # 6 m/s * 40 s / 45 s = 5.3, rounded down to 0.5 m/s
    assert frontier_curve.interpolate(hand_made()["nominal"], 25.0) is None  # faster than the fastest nominal lap


def test_no_avoidable_time_uses_the_floor_and_lost_laps_are_flagged():
    cells = by_name(hand_made())
    zero = cells[CELL_ZERO.name]
    assert zero["avoidable_s"] == 0.0
    assert zero["frontier_avoidable_s"] == pytest.approx(5.0 - 4.0 * 2 / 8)  # at 34 s between 32 s and 40 s
    assert zero["frontier_gain"] == pytest.approx(zero["frontier_avoidable_s"] / F.AVOIDABLE_FLOOR_S)
    lost = cells[CELL_LOST.name]
    assert lost["all_laps_completed"] is False and lost["success_rate"] == 0.5 and lost["laps_completed"] == 1
    assert lost["avoidable_s"] == pytest.approx(3.0)  # from the completed lap only
    assert lost["frontier_gain"] == pytest.approx((5.0 - 4.0 / 8) / 3.0)


def test_paper_pace_interpolates_the_speed_on_the_lap_time():
    frontier = hand_made()
    # 31.8 s lies between 32 s (8 m/s) and 26 s (10 m/s)
    assert frontier["paper_pace"] == pytest.approx(8.0 + 2.0 * 0.2 / 6.0)
    slow = F.build(nominal_results(), (6.0, 8.0), (), laps=2, seed=0)
    assert slow["paper_pace"] is None  # 32-40 s laps do not bracket 31.8 s


def test_frontier_json_is_strict_and_the_report_and_plot_are_written(tmp_path):
    frontier = hand_made()
    frontier["cells"][0]["two_sigma_nan"] = math.nan  # a non-finite value must not reach the file
    skeleton.write(F.frontier_experiment((6.0, 8.0, 10.0), CELLS, 2, 0), frontier, [], tmp_path)

    def reject(name):
        raise ValueError(f"non-strict JSON constant {name}")

    loaded = json.loads((tmp_path / "frontier.json").read_text(), parse_constant=reject)
    assert loaded["cells"][0]["two_sigma_nan"] is None
    assert {"nominal", "cells", "paper_pace", "measured"} <= set(loaded)
    for key in ("speed", "lap_time_s", "avoidable_s", "vis_below_50_s", "success_rate"):
        assert key in loaded["nominal"][0]
    for key in ("name", "pixel_model", "speed", "lap_time_s", "avoidable_s", "vis_below_50_s", "success_rate",
                "frontier_avoidable_s", "frontier_gain", "bracketed", "all_laps_completed", "causes", "options"):
        assert key in loaded["cells"][0]
    assert loaded["measured"]["device"]["platform"]
    text = (tmp_path / "REPORT.md").read_text()
    assert "![avoidable low-visibility time against lap time](frontier.png)" in text
    assert "not bracketed" in text and "about 5 m/s" in text and "lost laps" in text
    assert "| 2.00 |" in text  # the gain of the bracketed cell
    assert (tmp_path / "frontier.png").stat().st_size > 10_000


def test_an_interrupted_run_writes_what_finished_and_raises_again(tmp_path, monkeypatch):
    def interrupted(cells, out, **kwargs):
        first = cells[0]
        results = {first.name: {"laps": nominal_results()["nominal_6"]["laps"], "config": grid.cell_record(first),
                                "measure": MEASURE}}
        (Path(out) / "results.json").parent.mkdir(parents=True, exist_ok=True)
        (Path(out) / "results.json").write_text(json.dumps(results))
        raise KeyboardInterrupt

    monkeypatch.setattr(grid, "run_grid", interrupted)
    with pytest.raises(KeyboardInterrupt):
        F.run_frontier((6.0, 8.0), (CELL_IN,), tmp_path, laps=2, seed=0, progress=False)
    saved = json.loads((tmp_path / "frontier.json").read_text())
    assert [p["speed"] for p in saved["nominal"]] == [6.0]
    assert saved["missing"] == ["nominal_8", CELL_IN.name]
    assert "Not yet run" in (tmp_path / "REPORT.md").read_text()


@pytest.mark.parametrize("args", [["--laps", "0"], ["--speeds", "8", "nan"], ["--speeds", "8", "-1"],
                                  ["--speeds", "8", "inf"], ["--speeds", "8"], ["--seed", "-1"],
                                  ["--course", "monza"], ["--cells", "best"], ["--speeds", "9:6:0.25"],
                                  ["--speeds", "6:9:0"], ["--speeds", "6:9"], ["--speeds", "6:9:x"],
                                  ["--speeds", "8:8:0.25"], ["--speeds", "1:50:0.1"]])
def test_the_cli_rejects_bad_arguments_before_writing_anything(tmp_path, args, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["experiment", "frontier", "--out", str(tmp_path / "out"), *args])
    assert exc.value.code == 2
    assert not (tmp_path / "out").exists()
    assert "error:" in capsys.readouterr().err


def test_the_cli_exits_130_on_ctrl_c_and_quick_brackets_the_paper_pace(tmp_path, monkeypatch, capsys):
    seen = {}

    def stop(speeds, cells, out, laps, seed, course=None, camera_tilt_deg=None, reuse=(), loop=None):
        seen.update(speeds=speeds, cells=cells, laps=laps)
        raise KeyboardInterrupt

    monkeypatch.setattr(F, "run_frontier", stop)
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path), "--quick"]) == 130
    assert seen["speeds"] == F.QUICK_SPEEDS and seen["laps"] == 4
    assert [c.spec.config.pixel_cost for c in seen["cells"]] == ["border"] * 2
    assert {c.spec.config.pixel_model for c in seen["cells"]} == {"projection", "dof"}
    assert len(F.default_spec().nominal_speeds) >= 5 and len(F.default_cells()) == 4


def test_the_partial_cells_fly_best_beside_its_target_from_the_detector_and_nothing_else_apart(tmp_path,
                                                                                               monkeypatch):
    """``--cells partial``: the best preset at the paper's pace, which starts a gate cut by the image border from
    the map's pixel, and the same race with ``partial_target="detected"``, the one field apart; that race without
    the plan's look-ahead is the preset before its two options, keyed as every race of it flown before."""
    from pixelmpc_jax.apps.racing import presets
    from pixelmpc_jax.apps.racing.spec import RaceSpec

    seen = {}

    def stop(speeds, cells, out, laps, seed, course=None, camera_tilt_deg=None, reuse=(), loop=None):
        seen.update(cells=cells)
        raise KeyboardInterrupt

    monkeypatch.setattr(F, "run_frontier", stop)
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path), "--cells", "partial"]) == 130
    best, detected = seen["cells"]
    assert (best.name, detected.name) == ("best_v8.5", "best_partial_detected_v8.5")
    assert best.spec == presets.preset("best") and best.spec.config.partial_target == "map"
    assert detected.spec.config.partial_target == "detected" and detected.spec.key() != best.spec.key()
    assert detected.spec.replace(config=dataclasses.replace(detected.spec.config, partial_target="map")) == best.spec
    before = detected.spec.replace(config=dataclasses.replace(detected.spec.config, look_ahead_from="plane"))
    assert before.config == presets.LOOK_AHEAD_BEST
    assert before.key() == RaceSpec("pixelmpc", presets.LOOK_AHEAD_BEST, speed=8.5).key()
    assert (before.record()["config"]["partial_target"], before.record()["config"]["look_ahead_from"]) == (
        "detected", "plane")


def test_a_speed_range_flies_nominal_mppi_every_step_with_clean_cell_names(tmp_path, monkeypatch):
    """``--speeds 6:9:0.25 10`` asks for 6, 6.25, ..., 9 and 10 m/s: a frontier without gaps, its cells named
    nominal_6.25 and so on (so a run resumed with other speeds keeps the points already flown)."""
    seen = {}

    def stop(speeds, cells, out, laps, seed, course=None, camera_tilt_deg=None, reuse=(), loop=None):
        seen.update(speeds=speeds)
        raise KeyboardInterrupt

    monkeypatch.setattr(F, "run_frontier", stop)
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path), "--speeds", "6:9:0.25", "10", "7"]) == 130
    assert seen["speeds"] == tuple(6.0 + 0.25 * i for i in range(13)) + (10.0,)
    assert [F.nominal_cell(v).name for v in seen["speeds"][:3]] == ["nominal_6", "nominal_6.25", "nominal_6.5"]
    from pixelmpc_jax import arguments

    assert arguments.target_speeds("6:6.3:0.1") == (6.0, 6.1, 6.2, 6.3)  # not 6.300000000000001
    assert arguments.target_speeds("6:6.2:0.25") == (6.0,)


def test_every_table_holds_the_tail_and_every_cell_its_gain_three_ways():
    """The hand-made frontier: nominal at 6 m/s flies 39 s and 41 s (the worst 2.5 % over the median of 40 s). The
    cell of 35 s and 37 s laps, read on each seed's own nominal laps (lap i flies seed i): seed 0's 35 s between
    (32 s, 5 s) and (39 s, 1 s) gives 5 - 4 * 3/7, seed 1's 37 s between (32 s, 5 s) and (41 s, 1 s) gives
    5 - 4 * 5/9; over its 1.5 s: the paired gain. The joined means are the frontier gain, 2.0, the smallest; no
    nominal lap lies within 2 s of 36 s, so there is no local fit."""
    frontier = hand_made()
    cell = by_name(frontier)[CELL_IN.name]
    paired = ((5.0 - 4.0 * 3 / 7) + (5.0 - 4.0 * 5 / 9)) / 2 / 1.5
    assert cell["gains"]["paired"]["gain"] == pytest.approx(paired)
    assert cell["gains"]["joined_means"]["gain"] == pytest.approx(cell["frontier_gain"])
    assert cell["gains"]["local_fit"]["gain"] is None
    assert cell["gains"]["smallest"]["construction"] == "joined_means"
    assert cell["gains"]["laps_paired"] == 2 and cell["gains"]["widest_gap_s"] == pytest.approx(9.0)
    out = by_name(frontier)[CELL_OUT.name]["gains"]
    assert out["laps_out_of_range"] == 1 and out["paired"]["gain"] is None  # slower than every nominal lap
    assert frontier["nominal"][0]["tail"] == {"laps": 2, "laps_finished": 2, "median_lap_s": 40.0,
                                              "worst_lap_s": 41.0, "worst_over_median": pytest.approx(0.025),
                                              "share_over_median": 0.0}
    assert by_name(frontier)[CELL_LOST.name]["tail"]["laps_finished"] == 1
    text = F.report(frontier)
    assert "| 6 | 2/2 | +2.5 % | 0 (0.0 %) |" in text
    assert f"| {CELL_LOST.name} | dof | - | 8 | 1/2 | +0.0 % | 0 (0.0 %) |" in text
    assert "## The gain three ways" in text
    assert (f"| {CELL_IN.name} | {paired:.2f} [{cell['gains']['paired']['interval'][0]:.2f}, "
            f"{cell['gains']['paired']['interval'][1]:.2f}] | 2 (0) | 9.0 |") in text


def test_reproduce_shares_the_frontier_cells_with_the_tables():
    """The frontier part flies the nominal points at the paper's paces and the presets at its pace: the very races
    of Tables II/III at the pace, so those tables copy them (by key) rather than fly them again."""
    from pixelmpc_jax.apps.experiments import paper
    from pixelmpc_jax.apps.experiments import reproduce as R
    from pixelmpc_jax.apps.racing import presets

    assert R.resolve_parts(["frontier"]) == ["frontier"] and "frontier" in R.RUNNERS and "frontier" in R.TITLES
    assert set(presets.PAPER_PACE_SPEEDS.values()) - {10.3} <= set(F.DEFAULT_SPEEDS)
    frontier_keys = {c.race(10, R.SEED, None).key() for c in
                     [F.nominal_cell(v) for v in F.DEFAULT_SPEEDS] + list(F.preset_cells(presets.PAPER_PACE_SPEED))}
    pace = [c for c in paper.table_cells() if c.spec.speed == presets.PAPER_PACE_SPEED]
    shared = [c.name for c in pace if c.race(10, R.SEED, None).key() in frontier_keys]
    assert sorted(shared) == sorted(["nominal_8.5", "pixelmpc_dof_tf1_c9e+06_v8.5", "best_v8.5"])
    assert paper.preset_of(pace[-1].spec) == "best" and paper.preset_of(pace[3].spec) == "paper"


def _small_frontier(cells) -> skeleton.Experiment:
    """The frontier of nominal MPPI at 8 m/s and ``cells``, laps of tests/standard_race.py's length, 2 laps, its
    nominal MPPI flying the standard race's sampler."""
    experiment = F.frontier_experiment((8.0,), cells, standard_race.BATCH, 0, max_time_s=standard_race.MAX_TIME_S)
    small = standard_race.NOMINAL.config
    return dataclasses.replace(experiment, cells=tuple(
        dataclasses.replace(c, spec=c.spec.replace(config=small)) if c.spec.controller == "mppi" else c
        for c in experiment.cells))


def test_a_tiny_frontier_flies_writes_and_resumes(tmp_path, capsys):
    pixel = standard_race.PIXELMPC
    cell = grid.Cell("pixelmpc_small", pixel.replace(speed=8.0))
    frontier = skeleton.run(_small_frontier((cell,)), tmp_path, standard_race.BATCH, 0, progress=False)
    assert [p["speed"] for p in frontier["nominal"]] == [8.0] and frontier["missing"] == []
    row = frontier["cells"][0]
    assert row["success_rate"] == 0.0 and row["lap_time_s"] is None and row["frontier_gain"] is None
    json.loads((tmp_path / "frontier.json").read_text(), parse_constant=lambda name: 1 / 0)
    assert (tmp_path / "frontier.png").exists() and "completed no lap" in (tmp_path / "REPORT.md").read_text()
    assert (tmp_path / "laps.png").exists() and "(laps.png)" in (tmp_path / "REPORT.md").read_text()
    capsys.readouterr()
    skeleton.run(_small_frontier((cell,)), tmp_path, standard_race.BATCH, 0, progress=True)
    assert capsys.readouterr().out.count("kept from") == 2  # resumed: nothing flown again


def test_the_gain_interval_resamples_the_laps_of_the_cell_and_of_every_nominal_point():
    nominal = [np.asarray([[30.0, 8.0]] * 5), np.asarray([[40.0, 2.0]] * 5)]
    cell = np.asarray([[35.0, 1.0]] * 5)  # the frontier gives 5.0 s at 35 s: a gain of 5
    low, high = F.gain_interval(cell, nominal)
    assert low == pytest.approx(5.0) and high == pytest.approx(5.0)  # identical laps: no spread
    spread = np.asarray([[34.0, 0.5], [36.0, 1.5], [35.0, 1.0], [35.0, 0.8], [35.0, 1.2]])
    low, high = F.gain_interval(spread, nominal)
    assert low < 5.0 < high and high - low > 1.0
    assert F.gain_interval(np.asarray([[50.0, 1.0]]), nominal) is None  # never bracketed
    assert F.gain_interval(cell, nominal[:1]) is None  # one nominal point is no frontier


def test_a_frontier_on_the_onboard_loop_flies_every_cell_nominal_mppi_included_on_it():
    """``loop``: nominal MPPI's points and every PixelMPC cell fly the onboard loop (so the gain compares laps of one
    loop), with every other setting their own; without it, the cells' own loop (the true state)."""
    from pixelmpc_jax.apps.racing.presets import LOOPS

    onboard = F.frontier_experiment((7.5, 8.0), CELLS, 2, 0, loop="onboard")
    truth = F.frontier_experiment((7.5, 8.0), CELLS, 2, 0)
    assert [cell.name for cell in onboard.cells] == [cell.name for cell in truth.cells]
    for cell, own in zip(onboard.cells, truth.cells):
        assert own.spec.estimator == "truth"
        for field, value in LOOPS["onboard"].items():
            assert getattr(cell.spec, field) == value, (cell.name, field)
        assert cell.spec.replace(**{field: getattr(own.spec, field) for field in LOOPS["onboard"]}) == own.spec


def test_the_report_names_the_state_every_point_flew_nominal_mppi_included():
    """A frontier whose nominal points and cells all flew the ESKF says so, with no true state in it; points
    recorded without an estimator (nominal MPPI's, before frontiers flew other loops) read as the true state."""
    results = hand_made_results()
    for result in results.values():
        result["config"] = {"estimator": "eskf"}
    frontier = F.build(results, (6.0, 8.0, 10.0), CELLS, laps=2, seed=0)
    for cell in frontier["cells"]:
        cell["estimator"] = "eskf"
    assert {p["estimator"] for p in frontier["nominal"]} == {"eskf"}
    assert "laps per point (seeds 0-1), eskf state, on " in F.report(frontier)
    for point in frontier["nominal"]:
        del point["estimator"]
    assert "laps per point (seeds 0-1), eskf and ground-truth state, on " in F.report(frontier)
