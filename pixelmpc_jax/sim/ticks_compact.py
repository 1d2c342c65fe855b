"""The compact per-tick record of a result folder (``ticks_compact.npz``): what the visibility measure reads, for
every race of the folder, small enough to commit beside its results.

The full record (:mod:`~pixelmpc_jax.sim.ticks`, ``ticks_<name>.npz``) carries the states, the estimates and the
gates of every lap (megabytes a race); the measure (:func:`~pixelmpc_jax.sim.metrics.visibility_masks`) reads only
the target's visibility, the pointed camera's, the target's index, the ticks flown and the distance to the target
where the floor can excuse a tick. The compact record keeps those, per race of a folder (a grid's cell, a
comparison's controller), under ``<race>/<array>``. L laps, S the longest lap's ticks + 1 (state 0 is the start):

- ``seed`` (L,) int, ``num_ticks`` (L,) int, ``finished`` (L,) bool;
- ``target`` (L, S) int8, the target gate's index (-1 past the lap's end);
- ``visibility`` (L, S) float32, the target's visibility from the true pose (NaN past the lap's end);
- ``pointed_visibility`` (L, S) float32, from a camera at the same position pointed at the target's centre;
- ``floor_distance`` (L, S) float32, the distance to the target's centre, m, where the pointed camera sees under
  half of the target (the only ticks the floor may excuse, so the only ones whose distance the measure reads), NaN
  elsewhere;
- ``target_speed``, ``dt`` (scalars) and ``measure`` (the measure's name, :data:`~pixelmpc_jax.sim.metrics.MEASURE`).

The values are the full record's, not rounded: :func:`lap_figures` gives the same time below 50 %, at 0 %, avoidable
and in view as the race's own metrics. Mean angles and loss causes need the states and stay in the full record.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.strict_json import write_atomic

FILE_NAME = "ticks_compact.npz"
LAP_FIELDS = ("seed", "num_ticks", "finished")
TICK_FIELDS = ("target", "visibility", "pointed_visibility", "floor_distance")
SCALAR_FIELDS = ("target_speed", "dt", "measure")
FIELDS = (*LAP_FIELDS, *TICK_FIELDS, *SCALAR_FIELDS)


def from_record(record: dict) -> dict:
    """A race's compact record from its full per-tick record (:func:`~pixelmpc_jax.sim.ticks.load`)."""
    laps, size = len(record["num_ticks"]), record["target"].shape[1]
    distance = np.full((laps, size), np.nan, np.float32)
    for lap in range(laps):
        n = int(record["num_ticks"][lap])
        pointed = record["pointed_visibility"][lap, : n + 1]
        lap_distance = metrics_lib.target_distance(record["states"][lap, : n + 1], record["target"][lap, : n + 1],
                                                   ticks_lib.gates_of(record, lap))
        distance[lap, : n + 1] = np.where(pointed < 0.5, lap_distance, np.nan)
    if record["target"].max(initial=-1) > np.iinfo(np.int8).max:
        raise ValueError(f"a target index past {np.iinfo(np.int8).max} does not fit the compact record")
    return {"seed": np.asarray(record["seed"], np.int64), "num_ticks": np.asarray(record["num_ticks"], np.int32),
            "finished": np.asarray(record["finished"], bool), "target": record["target"].astype(np.int8),
            "visibility": np.asarray(record["visibility"], np.float32),
            "pointed_visibility": np.asarray(record["pointed_visibility"], np.float32), "floor_distance": distance,
            "target_speed": np.asarray(record["target_speed"]), "dt": np.asarray(record["dt"]),
            "measure": np.asarray(record["measure"])}


def write(path: Path, races: dict[str, dict]) -> None:
    """Write ``{race name: compact record}`` to ``path`` atomically, compressed."""
    if not races:
        raise ValueError("no races to record")
    arrays = {}
    for name, race in races.items():
        if "/" in name:
            raise ValueError(f"a race's name cannot hold '/': {name!r}")
        missing = [field for field in FIELDS if field not in race]
        if missing:
            raise ValueError(f"race {name!r} lacks {missing}")
        arrays.update({f"{name}/{field}": race[field] for field in FIELDS})
    write_atomic(Path(path), lambda f: np.savez_compressed(f, **arrays))


def load(path: Path) -> dict[str, dict]:
    """``{race name: compact record}`` of a file written by :func:`write`."""
    races: dict[str, dict] = {}
    with np.load(Path(path)) as data:
        for key in data.files:
            name, field = key.rsplit("/", 1)
            races.setdefault(name, {})[field] = data[key]
    return races


def update(path: Path, races: dict[str, dict]) -> None:
    """Add (or replace) ``races`` in the compact record at ``path``, keeping the others it holds."""
    path = Path(path)
    write(path, {**(load(path) if path.exists() else {}), **races})


def convert_folder(folder: Path) -> Path:
    """Write ``folder``'s compact record from every full record in it (``ticks_<race>.npz``, the race named by
    the rest of the file's name); returns its path. A ValueError when the folder holds no full record."""
    folder = Path(folder)
    sources = sorted(p for p in folder.glob("ticks_*.npz") if p.name != FILE_NAME)
    if not sources:
        raise ValueError(f"{folder} holds no per-tick record (ticks_<race>.npz) to convert")
    path = folder / FILE_NAME
    write(path, {source.stem.removeprefix("ticks_"): from_record(ticks_lib.load(source)) for source in sources})
    return path


def lap_figures(race: dict, lap: int) -> dict:
    """Lap ``lap``'s figures under the measure (:func:`~pixelmpc_jax.sim.metrics.visibility_masks`) from its compact
    record, with the keys of the race's lap metrics: ``success``, ``lap_time_s`` (None for a lap not finished),
    ``time_vis_below_50_s``, ``time_vis_zero_s``, ``time_vis_avoidable_s``, ``share_target_in_view`` and the paper's
    rule, ``time_vis_below_50_after_seen_s``."""
    if str(race["measure"]) != metrics_lib.MEASURE:
        raise ValueError(f"the record was measured as {str(race['measure'])!r}, this version measures "
                         f"{metrics_lib.MEASURE!r}")
    n, dt, finished = int(race["num_ticks"][lap]), float(race["dt"]), bool(race["finished"][lap])
    target = race["target"][lap, : n + 1].astype(np.int64)
    counted = metrics_lib.flown(n, n + 1)
    visibility = np.where(counted, race["visibility"][lap, : n + 1], 1.0)  # state 0 is never counted
    masks = metrics_lib.visibility_masks(visibility, race["pointed_visibility"][lap, : n + 1], target,
                                         race["floor_distance"][lap, : n + 1], n, float(race["target_speed"]), dt)
    after_seen, _ = metrics_lib.after_seen_ticks(visibility, target)
    return {"success": finished, "lap_time_s": n * dt if finished else None,
            "time_vis_below_50_s": float(np.sum(masks["below_50"])) * dt,
            "time_vis_zero_s": float(np.sum(masks["zero"])) * dt,
            "time_vis_avoidable_s": float(np.sum(masks["avoidable"])) * dt,
            "share_target_in_view": float(np.mean(visibility[counted] > 0.0)) if n else None,
            "time_vis_below_50_after_seen_s": float(np.sum(after_seen)) * dt}


def race_laps(race: dict) -> list[dict]:
    """Every lap's :func:`lap_figures`, with its seed: the ``laps`` of a race's results as the measure sees them."""
    return [{**lap_figures(race, lap), "seed": int(race["seed"][lap])} for lap in range(len(race["num_ticks"]))]
