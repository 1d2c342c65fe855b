"""The compact per-tick record of a result folder (``ticks_compact.npz``): what the visibility measure reads, for
every race of the folder, small enough to commit beside its results.

The full record (:mod:`~pixelmpc_jax.sim.ticks`, ``ticks_<name>.npz``) carries the states, the estimates and the
gates of every lap (megabytes a race); the measure (:func:`~pixelmpc_jax.sim.metrics.visibility_masks`) reads only
the target's visibility, the pointed camera's, the target's index, the ticks flown and, where the floor could
excuse a tick, the distance to the target, which only picks the ticks it excuses. The compact record keeps those
ticks rather than the distances, per race of a folder (a grid's cell, a comparison's controller), under
``<race>/<array>``. L laps, S the longest lap's ticks + 1 (state 0 is the start):

- ``seed`` (L,) int, ``num_ticks`` (L,) int, ``finished`` (L,) bool;
- ``target`` (L, S) int8, the target gate's index (-1 past the lap's end);
- ``visibility`` (L, S) float32, the target's visibility from the true pose (NaN past the lap's end);
- ``pointed_visibility`` (L, S) float32, from a camera at the same position pointed at the target's centre;
- ``excused`` (L, S) bool, the ticks the floor excuses under the record's measure
  (:func:`~pixelmpc_jax.sim.metrics.visibility_masks`' ``excused``: below 50 % where a pointed camera sees under
  half of the target too, at most as many per gate as the target speed needs to fly through the zone, the nearest);
- ``target_speed``, ``dt`` (scalars) and ``measure`` (the measure's name, :data:`~pixelmpc_jax.sim.metrics.MEASURE`).

The values are the full record's, not rounded: :func:`lap_figures` gives the same time below 50 %, at 0 %, avoidable
and in view as the race's own metrics. The excused ticks are the measure's own, so a record is read only under the
measure it names (a changed floor is a new measure). Mean angles and loss causes need the states and stay in the
full record. The file is a NumPy ``.npz`` whose members are LZMA-compressed (``np.load`` reads it): a third smaller
than zlib's on these floats. A record written before the excused ticks (``floor_distance``, the distances there) is
read as one with them (:func:`load`).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.strict_json import write_atomic

FILE_NAME = "ticks_compact.npz"
LAP_FIELDS = ("seed", "num_ticks", "finished")
TICK_FIELDS = ("target", "visibility", "pointed_visibility", "excused")
SCALAR_FIELDS = ("target_speed", "dt", "measure")
FIELDS = (*LAP_FIELDS, *TICK_FIELDS, *SCALAR_FIELDS)


def _excused(record: dict, distance_of) -> np.ndarray:
    """(L, S) the ticks the floor excuses in each lap of ``record`` (its ``num_ticks``, ``target``, ``visibility``,
    ``pointed_visibility``, ``target_speed`` and ``dt``), ``distance_of(lap, n)`` the lap's (n + 1,) distances to
    its target: the measure's own mask, as :func:`lap_figures` counts the lap."""
    excused = np.zeros(record["target"].shape, bool)
    for lap in range(len(record["num_ticks"])):
        n = int(record["num_ticks"][lap])
        visibility = np.where(metrics_lib.flown(n, n + 1), record["visibility"][lap, : n + 1], 1.0)
        excused[lap, : n + 1] = metrics_lib.visibility_masks(
            visibility, record["pointed_visibility"][lap, : n + 1], record["target"][lap, : n + 1].astype(np.int64),
            distance_of(lap, n), n, float(record["target_speed"]), float(record["dt"]))["excused"]
    return excused


def from_record(record: dict) -> dict:
    """A race's compact record from its full per-tick record (:func:`~pixelmpc_jax.sim.ticks.load`)."""
    excused = _excused(record, lambda lap, n: metrics_lib.target_distance(
        record["states"][lap, : n + 1], record["target"][lap, : n + 1], ticks_lib.gates_of(record, lap)))
    if record["target"].max(initial=-1) > np.iinfo(np.int8).max:
        raise ValueError(f"a target index past {np.iinfo(np.int8).max} does not fit the compact record")
    return {"seed": np.asarray(record["seed"], np.int64), "num_ticks": np.asarray(record["num_ticks"], np.int32),
            "finished": np.asarray(record["finished"], bool), "target": record["target"].astype(np.int8),
            "visibility": np.asarray(record["visibility"], np.float32),
            "pointed_visibility": np.asarray(record["pointed_visibility"], np.float32), "excused": excused,
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
    write_atomic(Path(path), lambda f: _savez_lzma(f, arrays))


def _savez_lzma(f, arrays: dict) -> None:
    """``np.savez_compressed``'s layout (one ``<key>.npy`` member per array) with LZMA members."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_LZMA) as archive:
        for key, value in arrays.items():
            with archive.open(f"{key}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def load(path: Path, names=None) -> dict[str, dict]:
    """``{race name: compact record}`` of a file written by :func:`write`, or by a version that kept the distances
    (``floor_distance``) instead of the excused ticks, which are computed from them; only the races ``names`` (an
    iterable of race names; None: every race), whose other members are not read."""
    races: dict[str, dict] = {}
    keep = None if names is None else set(names)
    with np.load(Path(path)) as data:
        for key in data.files:
            name, field = key.rsplit("/", 1)
            if keep is None or name in keep:
                races.setdefault(name, {})[field] = data[key]
    for race in races.values():
        if "floor_distance" in race and "excused" not in race:
            distance = race.pop("floor_distance")
            race["excused"] = _excused(race, lambda lap, n, distance=distance: distance[lap, : n + 1])
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
    masks = metrics_lib.visibility_masks(visibility, race["pointed_visibility"][lap, : n + 1], target, None, n,
                                         float(race["target_speed"]), dt, excused=race["excused"][lap, : n + 1])
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
