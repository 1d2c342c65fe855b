"""The picture of every lap (apps/experiments/lap_picture.py): read from a frontier's grid folder and from a
comparison's folder, drawn by ``pixelmpc experiment lap-picture``."""

import json

import numpy as np
import pytest

from pixelmpc_jax import cli
from pixelmpc_jax.apps.experiments import lap_picture as P
from pixelmpc_jax.sim.metrics import MEASURE


def lap(lap_time, avoidable, in_view, seed, success=True):
    return {"success": success, "lap_time_s": lap_time if success else None, "time_vis_avoidable_s": avoidable,
            "share_target_in_view": in_view, "seed": seed}


def grid_folder(folder):
    """A frontier's results.json: nominal MPPI at 7 and 8 m/s, a PixelMPC cell (a lap lost), and a cell recorded
    under another measure (its avoidable time means something else: left out)."""
    results = {
        "nominal_7": {"config": {"controller": "mppi", "speed": 7.0}, "measure": MEASURE,
                      "laps": [lap(36.0 + 0.3 * s, 2.5 + 0.1 * s, 0.93, s) for s in range(6)]},
        "nominal_8": {"config": {"controller": "mppi", "speed": 8.0}, "measure": MEASURE,
                      "laps": [lap(32.0 + 0.3 * s, 5.0 + 0.2 * s, 0.90, s) for s in range(6)]},
        "best_v8.5": {"config": {"controller": "pixelmpc", "speed": 8.5}, "measure": MEASURE,
                      "laps": [lap(33.5 + 0.2 * s, 1.2, 0.97, s) for s in range(5)] + [lap(None, 0.4, 0.5, 5, False)]},
        "old": {"config": {"controller": "pixelmpc", "speed": 8.0}, "measure": "after-seen",
                "laps": [lap(30.0, 1.0, 1.0, 0)]},
    }
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps(results))
    return folder


def compare_folder(folder):
    """A ``pixelmpc race --out`` folder: metrics.json with both controllers at 10 m/s."""
    record = {"preset": "best", "race": {"controller": "pixelmpc", "speed": 10.0}, "controllers": {
        "pixelmpc": {"race": {"controller": "pixelmpc", "speed": 10.0}, "measure": MEASURE,
                     "laps": [lap(32.2, 1.5, 0.97, s) for s in range(3)]},
        "mppi": {"race": {"controller": "mppi", "speed": 10.0}, "measure": MEASURE,
                 "laps": [lap(27.4, 18.3, 0.63, s) for s in range(3)]}}}
    folder.mkdir()
    (folder / "metrics.json").write_text(json.dumps(record))
    return folder


def test_the_races_of_a_grid_and_of_a_comparison_are_read_with_their_controller_and_pace(tmp_path):
    races = P.folder_races(grid_folder(tmp_path / "frontier"))
    assert [(r.label, r.controller, r.speed, len(r.laps)) for r in races] == [
        ("nominal_7", "mppi", 7.0, 6), ("nominal_8", "mppi", 8.0, 6), ("best_v8.5", "pixelmpc", 8.5, 6)]
    best = P.finished_points(races[2])
    assert best.shape == (5, 3) and best[:, 2] == pytest.approx([97.0] * 5)  # the lost lap has no dot
    np.testing.assert_allclose(best[:, 0], [33.5, 33.7, 33.9, 34.1, 34.3])
    assert [r.label for r in P.folder_races(tmp_path / "frontier", {"nominal_8"})] == ["nominal_8"]
    pair = P.folder_races(compare_folder(tmp_path / "race"))
    assert [(r.controller, r.speed) for r in pair] == [("pixelmpc", 10.0), ("mppi", 10.0)]
    with pytest.raises(ValueError, match="holds no results.json"):
        P.folder_races(tmp_path)


def test_the_command_draws_every_lap_of_several_folders(tmp_path, capsys):
    grid, race = grid_folder(tmp_path / "frontier"), compare_folder(tmp_path / "race")
    out = tmp_path / "picture.png"
    assert cli.main(["experiment", "lap-picture", str(grid), str(race), "--out", str(out)]) == 0
    assert out.stat().st_size > 20_000 and str(out) in capsys.readouterr().out
    assert cli.main(["experiment", "lap-picture", str(grid)]) == 0
    assert (grid / "laps.png").stat().st_size > 20_000


def test_the_command_refuses_a_folder_without_results(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["experiment", "lap-picture", str(tmp_path)])
    assert exc.value.code == 2 and "no result folder" in capsys.readouterr().err


def test_a_race_a_second_folder_copied_from_the_first_is_drawn_once(tmp_path, monkeypatch):
    """A frontier that reused another's nominal point holds its laps again: drawn once, the folder's own drawn."""
    first = grid_folder(tmp_path / "frontier")
    results = json.loads((first / "results.json").read_text())
    again = {"nominal_8": results["nominal_8"], "nominal_9": {**results["nominal_8"], "config": {
        "controller": "mppi", "speed": 9.0}, "laps": [lap(30.0 + 0.3 * s, 8.0, 0.85, s) for s in range(6)]}}
    (tmp_path / "pace").mkdir()
    (tmp_path / "pace" / "results.json").write_text(json.dumps(again))
    drawn = []
    monkeypatch.setattr(P, "plot_laps", lambda races, path, title=None: drawn.extend(races))
    P.write_lap_picture([first, tmp_path / "pace"], tmp_path / "picture.png")
    assert [(r.controller, r.speed) for r in drawn] == [("mppi", 7.0), ("mppi", 8.0), ("pixelmpc", 8.5),
                                                        ("mppi", 9.0)]
