"""Small synthetic result folders for the tests of the repository's reporting tools (``experiments/reporting/``):
each holds the files its reader needs, written as the jobs write them, with laps made up to give hand-computed
figures. The tests never read the committed ``experiments/results/``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pixelmpc_jax.apps.experiments import frontier
from pixelmpc_jax.apps.racing import grid, presets
from pixelmpc_jax.sim import metrics, ticks_compact

DT = 0.025
BEST = "best_v8.5"  # the frontier job's name for the `best` preset's cell at the paper's pace
# nominal MPPI: 40 s laps with 1 s avoidable at 6 m/s, 30 s laps with 5 s at 8 m/s; `best`: 35 s laps with 0.5 s
NOMINAL = {6.0: (1600, 40), 8.0: (1200, 200)}
CELL = (1400, 20)
DEVICE_LINE = "Device: 2-core AMD EPYC, jax 0.10.2. Flown 2026-11-28."


def compact_race(speed: float, num_ticks: int, avoidable_ticks: int, laps: int = 2, first_seed: int = 0) -> dict:
    """A compact per-tick record of ``laps`` finished laps of ``num_ticks`` ticks, each with ``avoidable_ticks`` ticks
    at 20 % visibility that the floor cannot excuse (a pointed camera would see the whole gate)."""
    visibility = np.ones((laps, num_ticks + 1), np.float32)
    visibility[:, 1:avoidable_ticks + 1] = 0.2
    return {"seed": np.arange(first_seed, first_seed + laps), "num_ticks": np.full(laps, num_ticks),
            "finished": np.ones(laps, bool), "target": np.zeros((laps, num_ticks + 1), np.int8),
            "visibility": visibility, "pointed_visibility": np.ones((laps, num_ticks + 1), np.float32),
            "excused": np.zeros((laps, num_ticks + 1), bool), "target_speed": np.asarray(speed),
            "dt": np.asarray(DT), "measure": np.asarray(metrics.MEASURE)}


def cell_results(cell: grid.Cell, race: dict, seed: int) -> dict:
    """A grid cell's results as :func:`~pixelmpc_jax.apps.racing.grid.run_grid` records them, its laps those of the
    compact record ``race`` (so the two agree)."""
    laps = ticks_compact.race_laps(race)
    spec = cell.race(len(laps), seed, None)
    return {"laps": laps, "measure": metrics.MEASURE, "config": grid.cell_record(cell), "seed": seed,
            "dof_weights_sha256": spec.dof_fingerprint()}


def frontier_folder(folder: Path, cell: grid.Cell | None = None, nominal: dict | None = None,
                    cell_ticks: tuple[int, int] = CELL, laps: int = 2, seed: int = 0) -> Path:
    """A frontier folder as ``pixelmpc experiment frontier`` writes it (``results.json``, ``frontier.json``,
    ``ticks_compact.npz``) with a README stating its device: nominal MPPI at the speeds of ``nominal`` (``{speed:
    (ticks a lap, avoidable ticks)}``, :data:`NOMINAL`) and the cell ``cell`` (the `best` preset at the paper's pace)
    with ``cell_ticks``."""
    cell = cell or grid.Cell(BEST, presets.preset("best"))
    nominal = NOMINAL if nominal is None else nominal
    races = {frontier.nominal_cell(speed).name: compact_race(speed, *ticks, laps=laps, first_seed=seed)
             for speed, ticks in nominal.items()}
    races[cell.name] = compact_race(cell.spec.speed, *cell_ticks, laps=laps, first_seed=seed)
    cells = {**{frontier.nominal_cell(speed).name: frontier.nominal_cell(speed) for speed in nominal},
             cell.name: cell}
    results = {name: cell_results(cells[name], race, seed) for name, race in races.items()}
    folder.mkdir(parents=True, exist_ok=True)
    ticks_compact.write(folder / ticks_compact.FILE_NAME, races)
    (folder / "results.json").write_text(json.dumps(results))
    record = frontier.build(results, sorted(nominal), [cell], laps, seed)
    (folder / "frontier.json").write_text(json.dumps(record))
    (folder / "README.md").write_text(f"# A frontier\n\n{DEVICE_LINE}\n")
    return folder


def dof_eval_folder(folder: Path, aee_px: float = 1.17) -> Path:
    """A DOF evaluation folder as ``pixelmpc evaluate`` writes it (``dof_eval.json``) with a README stating its
    device."""
    folder.mkdir(parents=True, exist_ok=True)
    record = {"aee_px": aee_px, "frames": 2139, "created": "2026-11-21T10:00:00", "data": {"test_laps": [2, 7]}}
    (folder / "dof_eval.json").write_text(json.dumps(record))
    (folder / "README.md").write_text("# The DOF's accuracy\n\nDevice: 2-core Intel Xeon @ 2.80 GHz, jax 0.10.2.\n")
    return folder


def checkout(root: Path, folders: dict[str, dict], rows: list[dict], readme: str, results_doc: str) -> Path:
    """A checkout at ``root`` for ``pixelmpc report --readme``: ``README.md`` and ``docs/results.md`` as given, the
    reporting tools (linked from this one) and ``experiments/results/index.json`` listing ``folders`` (``{name: its
    entry}``, the folders themselves made by the caller) and the README ``rows``."""
    tools = Path(__file__).resolve().parent.parent / "experiments" / "reporting"
    (root / "experiments" / "results").mkdir(parents=True, exist_ok=True)
    (root / "experiments" / "reporting").symlink_to(tools)
    index = {"schema": 1, "statuses": {"current": "backs a claim", "exploratory": "a probe",
                                       "superseded": "replaced"},
             "record_schemas": {}, "folders": folders, "readme": rows}
    (root / "experiments" / "results" / "index.json").write_text(json.dumps(index))
    (root / "README.md").write_text(readme)
    (root / "docs").mkdir(exist_ok=True)
    (root / "docs" / "results.md").write_text(results_doc)
    return root
