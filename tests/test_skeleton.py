"""The experiment skeleton: cells -> grid -> summary -> report -> plot, resumable, the same for every experiment;
and the failed laps counted by cause."""

import json

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import skeleton
from pixelmpc_jax.apps.racing import grid, race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.sim.metrics import MEASURE

CELLS = (grid.Cell("slow", RaceSpec("mppi", speed=6.0)), grid.Cell("fast", RaceSpec("mppi", speed=12.0)),
         grid.Cell("faster", RaceSpec("mppi", speed=14.0)))


@pytest.fixture
def flown(monkeypatch):
    """race.run_laps replaced: a lap succeeds below 13 m/s; ``stop_at`` (a speed) interrupts that cell's race."""
    calls, stop_at = [], []

    def run_laps(spec, **kwargs):
        if stop_at and spec.speed == stop_at[0]:
            raise KeyboardInterrupt
        calls.append((spec.speed, spec.laps))
        laps = [{"success": spec.speed < 13.0, "crash": None if spec.speed < 13.0 else "gate", "seed": spec.seed + i}
                for i in range(spec.laps)]
        return {"laps": laps, "aggregate": {}, "seed": spec.seed, "interrupted": False,
                "trajectories": [np.zeros((2, 10))] * spec.laps, "covariances": [], "measure": MEASURE}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls, stop_at


def experiment(**changes) -> skeleton.Experiment:
    """Counts each finished cell's laps; its report names the missing cells; its plot writes a file."""

    def plot(summary, out):
        (out / "figure.txt").write_text("drawn")
        return "\n![figure](figure.txt)\n"

    return skeleton.Experiment(CELLS, summarise=lambda results: {name: len(r["laps"]) for name, r in results.items()},
                               report=lambda summary, missing: f"# laps {summary}\nmissing {missing}\n", plot=plot,
                               record=lambda summary: summary, **changes)


def test_a_run_flies_summarises_and_writes_the_record_the_report_and_the_figures(tmp_path, flown):
    calls, _ = flown
    summary = skeleton.run(experiment(), tmp_path, laps=2, seed=3, progress=False)
    assert summary == {"slow": 2, "fast": 2, "faster": 2} and len(calls) == 3
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert (tmp_path / "REPORT.md").read_text() == f"# laps {summary}\nmissing []\n\n![figure](figure.txt)\n"
    assert (tmp_path / "figure.txt").read_text() == "drawn"
    assert skeleton.run(experiment(), tmp_path, laps=2, seed=3, progress=False) == summary and len(calls) == 3
    skeleton.run(experiment(), tmp_path, laps=2, seed=4, progress=False)  # other seeds: flown again
    assert len(calls) == 6


def test_an_interrupted_run_writes_the_finished_cells_and_raises_again(tmp_path, flown):
    calls, stop_at = flown
    stop_at.append(12.0)
    with pytest.raises(KeyboardInterrupt):
        skeleton.run(experiment(), tmp_path, laps=2, seed=0, progress=False)
    assert json.loads((tmp_path / "summary.json").read_text()) == {"slow": 2}
    assert "missing ['fast', 'faster']" in (tmp_path / "REPORT.md").read_text()
    stop_at.clear()
    assert skeleton.run(experiment(), tmp_path, laps=2, seed=0, progress=False) == {"slow": 2, "fast": 2,
                                                                                     "faster": 2}
    assert [speed for speed, _ in calls] == [6.0, 12.0, 14.0]  # the finished cell was kept


def test_cells_fly_their_own_laps_most_first_and_only_finished_races_count(tmp_path, flown):
    calls, _ = flown
    own = experiment(cell_laps={"faster": 5})
    assert skeleton.run(own, tmp_path, laps=2, seed=0, progress=False) == {"slow": 2, "fast": 2, "faster": 5}
    assert calls == [(14.0, 5), (6.0, 2), (12.0, 2)]
    assert skeleton.run(own, tmp_path, laps=2, seed=0, flies=False) == {"slow": 2, "fast": 2, "faster": 5}
    assert skeleton.run(experiment(), tmp_path, laps=2, seed=0, flies=False) == {"slow": 2, "fast": 2}


def test_cell_names_must_not_repeat():
    with pytest.raises(ValueError, match="cell names repeat"):
        skeleton.Experiment(CELLS + CELLS[:1], summarise=dict, report=lambda summary, missing: "")


def test_failed_laps_are_counted_by_cause():
    laps = [{"success": True, "crash": None}, {"success": False, "crash": "gate"}, {"success": False, "crash": "gate"},
            {"success": False, "crash": None}, {"success": False, "crash": "wall", "flipped": True}]
    assert skeleton.failure_counts(laps) == {"gate": 2, None: 1, "wall": 1}
    flips = skeleton.failure_counts(laps, lambda lap: "flip" if lap.get("flipped") else lap["crash"] or "timeout")
    assert flips == {"gate": 2, "timeout": 1, "flip": 1}
