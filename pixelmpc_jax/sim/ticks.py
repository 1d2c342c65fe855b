"""The per-tick record of a race's laps (``ticks_<controller>.npz``): what anyone needs to recompute any measure.

L laps, S the longest lap's ticks + 1 (state 0 is the start), G gates; laps shorter than S are padded (NaN for
floats, -1 for the target):

- ``seed`` (L,), ``num_ticks`` (L,), ``finished`` (L,);
- ``target`` (L, S) int, the target gate's index at each state;
- ``visibility`` (L, S), the target's visibility from the true pose;
- ``pointed_visibility`` (L, S), the target's visibility from a camera at the same position pointed at its centre
  (the floor's input, :func:`~pixelmpc_jax.sim.metrics.pointed_visibility`: its optical axis, the tilt included);
- ``states`` (L, S, 10), the true states; ``estimates`` (L, S, 10), the state the controller acted on at each
  state's tick (NaN at the last state, where no tick followed);
- ``association`` (L, S) int8, only where the gates were painted alike: what the estimator made of each state's tick's
  candidates (an index of :data:`~pixelmpc_jax.perception.association.OUTCOMES`: none in view, accepted, rejected,
  ambiguous; -1 at the last state and past the lap's end);
- ``gate_centre`` (L, G, 3), ``gate_rotation`` (L, G, 3, 3), ``gate_width``, ``gate_height``, ``gate_border``,
  ``gate_depth`` (L, G): each lap's gates as flown (perturbed or moved);
- ``camera_fx``, ``camera_fy``, ``camera_cx``, ``camera_cy``, ``camera_tilt``, ``camera_width``,
  ``camera_height`` (scalars), ``target_speed`` and ``dt`` (scalars), ``measure`` (the visibility measure's name,
  :data:`~pixelmpc_jax.sim.metrics.MEASURE`).

:func:`lap_visibility` recomputes a lap's visibility figures from the file alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.perception.association import NOT_ASSOCIATING
from pixelmpc_jax.sim import metrics as metrics_lib
from pixelmpc_jax.strict_json import write_atomic
from pixelmpc_jax.timing import CONTROL_DT
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import track as track_lib

GATE_FIELDS = ("centre", "rotation", "width", "height", "border", "depth")
CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "tilt", "width", "height")


def lap_ticks(log, gates: track_lib.Gate, camera: camera_lib.Camera, seed: int) -> dict:
    """One lap's per-tick arrays (host numpy, unpadded: S = num_ticks + 1) from its unbatched episode log."""
    n = int(log.num_ticks)
    states = np.asarray(log.states)[: n + 1]
    target = np.asarray(log.target)[: n + 1]
    estimates = np.full(states.shape, np.nan, np.float32)
    estimates[:n] = np.asarray(log.estimates)[:n]
    pointed, _ = metrics_lib.tick_geometry(states, target, gates, camera)
    lap = {"seed": seed, "num_ticks": n, "finished": bool(log.finished), "target": target,
           "visibility": np.asarray(log.visibility)[: n + 1], "pointed_visibility": pointed, "states": states,
           "estimates": estimates, **{f"gate_{f}": np.asarray(getattr(gates, f)) for f in GATE_FIELDS}}
    association = np.asarray(log.association)  # none in a log built by hand
    if association.ndim == 1 and np.any(association[:n] != NOT_ASSOCIATING):  # the gates painted alike
        lap["association"] = np.append(association[:n], NOT_ASSOCIATING).astype(np.int8)
    return lap


def _pad(arrays: list[np.ndarray], size: int, fill) -> np.ndarray:
    """Stack (S_i, ...) arrays into (L, size, ...), each padded with ``fill`` past its length."""
    out = np.full((len(arrays), size, *arrays[0].shape[1:]), fill, arrays[0].dtype)
    for i, array in enumerate(arrays):
        out[i, : len(array)] = array
    return out


def stack(laps: list[dict], camera: camera_lib.Camera, target_speed: float, dt: float = CONTROL_DT) -> dict:
    """The laps of :func:`lap_ticks` as one record of padded arrays (the module's layout)."""
    if not laps:
        raise ValueError("no laps to record")
    size = max(len(lap["target"]) for lap in laps)
    record = {"seed": np.asarray([lap["seed"] for lap in laps], np.int64),
              "num_ticks": np.asarray([lap["num_ticks"] for lap in laps], np.int64),
              "finished": np.asarray([lap["finished"] for lap in laps], bool),
              "target": _pad([lap["target"].astype(np.int32) for lap in laps], size, -1)}
    for key in ("visibility", "pointed_visibility", "states", "estimates"):
        record[key] = _pad([np.asarray(lap[key], np.float32) for lap in laps], size, np.nan)
    if all("association" in lap for lap in laps):
        record["association"] = _pad([lap["association"] for lap in laps], size, NOT_ASSOCIATING)
    for field in GATE_FIELDS:
        record[f"gate_{field}"] = np.stack([lap[f"gate_{field}"] for lap in laps])
    for field in CAMERA_FIELDS:
        record[f"camera_{field}"] = np.asarray(getattr(camera, field))
    record.update(target_speed=np.asarray(target_speed), dt=np.asarray(dt), measure=np.asarray(metrics_lib.MEASURE))
    return record


def write(path: Path, laps: list[dict], camera: camera_lib.Camera, target_speed: float) -> None:
    """Write the laps' record to ``path`` atomically (a reader never sees a half-written file)."""
    record = stack(laps, camera, target_speed)
    write_atomic(Path(path), lambda f: np.savez_compressed(f, **record))


def load(path: Path) -> dict:
    """A record written by :func:`write`, as a dict of arrays."""
    with np.load(Path(path)) as data:
        return {key: data[key] for key in data.files}


def gates_of(record: dict, lap: int) -> track_lib.Gate:
    """Lap ``lap``'s gates as flown."""
    return track_lib.Gate(**{f: np.asarray(record[f"gate_{f}"][lap]) for f in GATE_FIELDS})


def camera_of(record: dict) -> camera_lib.Camera:
    """The camera the laps were flown with."""
    values = {f: record[f"camera_{f}"].item() for f in CAMERA_FIELDS}
    return camera_lib.Camera(**{k: (int(v) if k in ("width", "height") else float(v)) for k, v in values.items()})


def lap_visibility(record: dict, lap: int, target_speed: float | None = None) -> dict:
    """Lap ``lap``'s visibility figures (:func:`~pixelmpc_jax.sim.metrics.visibility_metrics`) from the record
    alone; ``target_speed`` (the cap's speed) defaults to the race's."""
    n = int(record["num_ticks"][lap])
    speed = float(record["target_speed"]) if target_speed is None else target_speed
    return metrics_lib.visibility_metrics(record["states"][lap, : n + 1], record["visibility"][lap, : n + 1],
                                          record["target"][lap, : n + 1], n, gates_of(record, lap),
                                          camera_of(record), speed, float(record["dt"]),
                                          pointed=record["pointed_visibility"][lap, : n + 1])


def lap_masks(lap: dict, target_speed: float) -> dict:
    """One lap's visibility masks (:func:`~pixelmpc_jax.sim.metrics.visibility_masks`) from its unpadded
    :func:`lap_ticks`."""
    target = np.asarray(lap["target"])
    gates = track_lib.Gate(**{f: np.asarray(lap[f"gate_{f}"]) for f in GATE_FIELDS})
    distance = metrics_lib.target_distance(lap["states"], target, gates)
    return metrics_lib.visibility_masks(np.asarray(lap["visibility"]), np.asarray(lap["pointed_visibility"]), target,
                                        distance, int(lap["num_ticks"]), target_speed)

