"""Experiment grids: which finished cells a rerun keeps (settings, seed, laps, DOF weights)."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from pixelmpc_jax.apps import grid, race
from pixelmpc_jax.dynamics import dof

RESULTS = Path(__file__).resolve().parent.parent / "experiments" / "results"
CELLS = [grid.Cell("nominal"), grid.Cell("dof", "pixelmpc"), grid.Cell("projection", "pixelmpc",
                                                                         pixel_model="projection")]


@pytest.fixture
def flown(monkeypatch):
    """Replace race.run_laps by a fake that records which cells it flies, with which seed and weights."""
    calls = []

    def run_laps(controller, speed, laps, seed, pixel_model, dof_params, **kwargs):
        calls.append((controller, pixel_model, seed, dof_params))
        return {"laps": [{"success": True, "seed": seed + i} for i in range(laps)], "aggregate": {},
                "seed": seed, "interrupted": False, "trajectories": [np.zeros((2, 10))] * laps, "covariances": []}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls


def _names(calls):
    """The cells flown, by name (each cell of CELLS has its own controller and pixel model)."""
    return sorted("nominal" if controller == "mppi" else model for controller, model, _, _ in calls)


def _run(calls, tmp_path, **kwargs):
    calls.clear()
    grid.run_grid(CELLS, tmp_path, progress=False, batch_size=1, **{"laps": 2, **kwargs})
    return _names(calls)


def test_other_seeds_laps_or_weights_fly_the_cell_again(tmp_path, flown):
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    assert _run(flown, tmp_path) == ["dof", "nominal", "projection"]
    assert _run(flown, tmp_path) == []  # the same run: every cell kept
    assert _run(flown, tmp_path, seed=1) == ["dof", "nominal", "projection"]
    assert all(seed == 1 for _, _, seed, _ in flown)
    assert _run(flown, tmp_path, seed=1, dof_params=other) == ["dof"]  # only the cell that uses the DOF
    assert _run(flown, tmp_path, seed=1, dof_params=other) == []
    assert _run(flown, tmp_path, seed=1) == ["dof"]  # back to the packaged weights
    assert _run(flown, tmp_path, seed=1, laps=3) == ["dof", "nominal", "projection"]

    saved = json.loads((tmp_path / "results.json").read_text())
    assert {entry["seed"] for entry in saved.values()} == {1}
    assert saved["dof"]["dof_weights_sha256"] == grid.packaged_dof_hash()
    assert saved["nominal"]["dof_weights_sha256"] is None and saved["projection"]["dof_weights_sha256"] is None


def test_the_weights_hash_follows_the_values():
    packaged = dof.load_packaged_dof()
    assert grid.dof_weights_hash(packaged) == grid.dof_weights_hash(dof.load_packaged_dof())
    changed = jax.tree_util.tree_map(lambda a: a, packaged).replace(input_mean=packaged.input_mean + 1e-3)
    assert grid.dof_weights_hash(changed) != grid.dof_weights_hash(packaged)
    assert len(grid.dof_weights_hash(packaged)) == 16


def test_results_without_seed_or_hash_count_as_the_defaults(tmp_path, flown):
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    _run(flown, tmp_path)
    path = tmp_path / "results.json"
    old = {name: {k: v for k, v in entry.items() if k not in ("seed", "dof_weights_sha256")}
           for name, entry in json.loads(path.read_text()).items()}
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path) == []  # seed 0, packaged weights: what older files were flown with
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path, dof_params=other) == ["dof"]
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path, seed=3) == ["dof", "nominal", "projection"]


@pytest.mark.parametrize("folder", ["reproduce/table2", "reproduce/table2_projection", "reproduce/table4",
                                    "frontier"])
def test_the_committed_results_stay_valid_for_a_default_run(folder):
    results = grid.load_results(RESULTS / folder)
    assert results, f"no committed results in {folder}"
    packaged = grid.packaged_dof_hash()
    for entry in results.values():
        cell = grid.Cell(**entry["config"])
        assert grid.is_current(entry, cell, len(entry["laps"]), 0, packaged if grid.uses_dof(cell) else None)


def test_current_results_are_the_cells_a_rerun_keeps(flown, tmp_path):
    """After a run, current_results gives every cell for the same seed and weights, none for another seed,
    and only the weight-free cells for other DOF weights (what the frontier reports after an interruption)."""
    _run(flown, tmp_path)
    assert sorted(grid.current_results(CELLS, tmp_path, laps=2)) == ["dof", "nominal", "projection"]
    assert grid.current_results(CELLS, tmp_path, laps=2, seed=5) == {}
    assert grid.current_results(CELLS, tmp_path, laps=3) == {}
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    assert sorted(grid.current_results(CELLS, tmp_path, laps=2, dof_params=other)) == ["nominal", "projection"]
