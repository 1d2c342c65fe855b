"""vdof's training data, self-supervised from the gate detector as the DOF's is from the optical flow.

The labels come from the run-time sensor, the gate detector (``perception.detector.detect_from_geometry``, the
closed loop's default) over consecutive frames of the logged laps (:mod:`pixelmpc_jax.learn.dataset`). For every
frame ``t`` where the same target gate is detected at ``t`` and ``t + 1`` one row is
``(x_t, p_t = [centre_t, box_size(corners_t)], w_flown_t)`` with the label ``p_dot = (p_{t+1} - p_t) / dt``
(:func:`lap_rows`). The detector's per-frame output is what the drone has at run time; the gate's 3-D position and
the camera intrinsics never reach the model (the camera is used here only to run the detector on the logged
states). The rollout stage trains on K-step windows of the logged laps (:func:`lap_windows`): the states, the
flown rates and the detected pixel states along them, masked where the target changes or is lost.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import vdof
from pixelmpc_jax.learn import control_response
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.world import camera as camera_lib


class Rows(NamedTuple):
    """Training rows. x: (N, 10) state; p: (N, 3) pixel state; w: (N, 3) flown rates; p_dot: (N, 3) label."""

    x: np.ndarray
    p: np.ndarray
    w: np.ndarray
    p_dot: np.ndarray


# --------------------------------------------------------------------------------------------------
# Rows from the detector.
# --------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("box_cue",))
def lap_detections(track, camera, states: jax.Array, target: jax.Array, box_cue: str = "apparent"):
    """Each frame's detection of its target gate: pixel state p (F+1, 3) ``[centre, s]`` (``s`` as ``box_cue``
    says), found (F+1,), and the centre inside the image (F+1,). states: (F+1, 10); target: (F+1,) int."""

    def one(x, gate_id):
        gate = track.gate(gate_id)
        det = detector_lib.detect_from_geometry(gate, x, camera)
        return control_response.vdof_detected_state(box_cue, det, gate), det.found, camera_lib.in_image(det.centre)

    return jax.vmap(one)(states, target)


def lap_rows(track, camera, states, w_flown, target, dt: float = timing.CONTROL_DT,
             box_cue: str = "apparent", detections: dict | None = None) -> Rows:
    """The rows of one lap: every frame t whose target is detected at t and t+1 (same gate); the label is the
    finite difference of the detector's pixel state. states: (F+1, 10); w_flown: (F, 3); target: (F+1,).
    ``detections``: the detector's per-frame output as the lap file stores it (``Lap.detections``); without
    it (older files) the geometric detector is run on the states, which gives the same."""
    states, w_flown, target = np.asarray(states, np.float32), np.asarray(w_flown, np.float32), np.asarray(target)
    if states.shape[0] != w_flown.shape[0] + 1 or target.shape != states.shape[:1]:
        raise ValueError(f"states (F+1, 10), w_flown (F, 3), target (F+1,) expected, got {states.shape}, "
                         f"{w_flown.shape}, {target.shape}")
    if detections is not None and box_cue == "apparent":
        corners = jnp.asarray(detections["gate_corners"])
        p = np.concatenate([detections["gate_centre"], np.asarray(jax.vmap(vdof.box_size)(corners))[:, None]], 1)
        found = np.asarray(detections["gate_found"], bool)
    else:
        p, found, _ = (np.asarray(a) for a in lap_detections(track, camera, jnp.asarray(states),
                                                                jnp.asarray(target), box_cue))
    keep = np.nonzero(found[:-1] & found[1:] & (target[:-1] == target[1:]))[0]
    return Rows(x=states[keep], p=p[keep], w=w_flown[keep], p_dot=((p[keep + 1] - p[keep]) / dt).astype(np.float32))


def load_rows(laps: list[dataset_lib.Lap], track, camera, dt: float = timing.CONTROL_DT,
              box_cue: str = "apparent") -> Rows:
    """:func:`lap_rows` of every lap, concatenated."""
    parts = [lap_rows(track, camera, lap.states, lap.w_flown, lap.target, dt, box_cue, lap.detections)
             for lap in laps]
    return Rows(*(np.concatenate(a) for a in zip(*parts, strict=True)))


# --------------------------------------------------------------------------------------------------
# Windows of the laps, for the rollout stage.
# --------------------------------------------------------------------------------------------------


class Windows(NamedTuple):
    """K-step windows of logged laps (M of them). x: (M, K, 10) states; w: (M, K, 3) flown rates; p: (M, K+1, 3)
    detected pixel states; mask: (M, K+1) the target still the same and detected; scale: (M, 3) the loss's
    scale of uv error and of the box size's relative error (``vdof_spec.rollout_loss``)."""

    x: jax.Array
    w: jax.Array
    p: jax.Array
    mask: jax.Array
    scale: jax.Array


def lap_windows(track, camera, states, w_flown, target, steps: int, box_cue: str = "apparent") -> Windows:
    """Every start frame's window of ``steps`` frames (host arrays, ``scale`` ones) whose target is detected on the
    next frame; states: (F+1, 10), w_flown: (F, 3), target: (F+1,)."""
    states, w_flown, target = np.asarray(states, np.float32), np.asarray(w_flown, np.float32), np.asarray(target)
    p, found, _ = (np.asarray(a) for a in lap_detections(track, camera, jnp.asarray(states), jnp.asarray(target),
                                                            box_cue))
    F = w_flown.shape[0]
    ahead = np.arange(F)[:, None] + np.arange(steps + 1)[None]  # (F, K+1)
    idx = np.minimum(ahead, F)
    seen = found[idx] & (target[idx] == target[:F, None]) & (ahead <= F)
    mask = np.cumprod(seen, axis=1).astype(bool)
    keep = np.nonzero(mask[:, 1])[0]
    frame = np.minimum(idx[keep, :-1], F - 1)
    return Windows(states[frame], w_flown[frame], p[idx[keep]], mask[keep], np.ones((keep.size, 3), np.float32))


def load_windows(laps: list[dataset_lib.Lap], track, camera, steps: int, box_cue: str = "apparent",
                 scale=None) -> Windows:
    """:func:`lap_windows` of every lap, concatenated, on the device, with the loss scale ``scale`` (3,) (default:
    these windows' std of the uv displacement over K steps and of the log box-size change)."""
    parts = [lap_windows(track, camera, lap.states, lap.w_flown, lap.target, steps, box_cue) for lap in laps]
    windows = Windows(*(np.concatenate(a) for a in zip(*parts, strict=True)))
    if scale is None:
        full = windows.mask[:, -1]
        shift = windows.p[full, -1] - windows.p[full, 0]
        log_box = np.log(np.maximum(windows.p[full, -1, 2], 1e-6) / np.maximum(windows.p[full, 0, 2], 1e-6))
        scale = np.maximum(np.r_[shift[:, :2].std(0), log_box.std()], 1e-3) if full.any() else np.ones(3)
    scale = np.broadcast_to(np.asarray(scale, np.float32), windows.scale.shape)
    return Windows(*(jnp.asarray(a) for a in windows[:-1]), jnp.asarray(scale))
