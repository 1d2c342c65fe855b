"""Training and evaluation of the velocity-and-depth DOF (:mod:`pixelmpc_jax.dynamics.vdof`).

Self-supervised, as the paper's DOF: the labels come from the run-time sensor, the gate detector
(``perception.detector.detect_from_geometry``, the closed loop's default) over consecutive frames of the
logged laps. For every frame ``t`` where the same target gate is detected at ``t`` and ``t + 1`` one row is
``(x_t, p_t = [centre_t, box_size(corners_t)], w_flown_t)`` with the label ``p_dot = (p_{t+1} - p_t) / dt``.
The detector's per-frame output is what the drone has at run time; the gate's 3-D position and the camera
intrinsics never reach the model (the camera is used here only to run the detector on the logged states,
and, in the evaluation, for the exact rotational flow the rate response is compared with).

Training, two stages of Adam (optax) on minibatches drawn with a seeded key: (1) the MSE of ``p_dot`` with each
component scaled to unit variance (the box size's as ``s_dot / s`` by default, ``box_loss``); (2) fine-tuning on
K-step Euler rollouts of the pixel state along the logged trajectory against the detections (``rollout_steps``,
0 skips it): the one-step fit leaves ``s``'s rate a few percent off, and ``s_dot ~ s^2`` turns that into a box
that grows too fast near the gate, which the rollouts correct. ``box_cue`` "per_gate_size" divides ``s`` by the
target opening's size (a course fact; the course's openings are 1.8 m and 3.0 m wide, which the apparent size
cannot tell apart). Evaluation on the held-out laps
(the dataset's test split): the gate centre predicted k steps ahead by rolling the pixel state forward along
the logged trajectory with the flown rates, against the detected centre, beside the paper's DOF on the same
windows; and the response to the rates at the image centre against the pinhole camera's exact one.

``python -m pixelmpc_jax.learn.vdof_train --data DIR --out DIR --steps N`` writes ``vdof_weights.msgpack``,
``vdof_eval.json`` and ``learning_curve.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import sys
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from pixelmpc_jax import strict_json, timing
from pixelmpc_jax.dynamics import dof, vdof
from pixelmpc_jax.learn import control_response
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

EVAL_HORIZONS = (10, 20, 40, 80)
BOX_LOSSES = ("absolute", "relative")
BOX_CUES = control_response.VDOF_BOX_CUES


@dataclasses.dataclass(frozen=True)
class VDOFTrainConfig:
    """Static training configuration (hashable; recorded with the weights).

    Attributes:
        hidden_sizes: widths of g(uv)'s hidden layers.
        steps: Adam steps; batch_size: rows per step (drawn with replacement).
        learning_rate: peak rate; cosine decay to ``learning_rate * final_lr_fraction``.
        box_loss: how the box size's rate is scored: "absolute" (``s_dot`` over its std, as ``uv_dot``) or
            "relative" (``s_dot / s`` over its std: the far gates' small ``s_dot`` count as much as the near ones').
        box_cue: what ``s`` is: "apparent" (``box_size`` of the detected corners, the default) or "per_gate_size"
            (that over the target opening's ``sqrt(width * height)``, m: a course fact, not a position; the
            course's gates come in two sizes, which "apparent" leaves the model to guess).
        rollout_steps: K of the second stage, which fine-tunes on K-step rollouts of the pixel state along the
            logged trajectories against the detections (0: no second stage; see :func:`rollout_loss`).
        rollout_train_steps, rollout_learning_rate, rollout_batch_size: its Adam steps (gradients clipped to
            norm 1), peak rate (cosine decay) and windows per step.
        seed: weights' initialisation and minibatches.
        log_every: steps per compiled chunk and per learning-curve point.
        progress: show the tqdm bar.
    """

    hidden_sizes: tuple[int, ...] = vdof.HIDDEN_SIZES
    steps: int = 6000
    batch_size: int = 1024
    learning_rate: float = 3e-3
    final_lr_fraction: float = 0.02
    box_loss: str = "relative"
    box_cue: str = "apparent"
    rollout_steps: int = 40
    rollout_train_steps: int = 2000
    rollout_learning_rate: float = 1e-3
    rollout_batch_size: int = 256
    seed: int = 0
    log_every: int = 200
    progress: bool = True

    def __post_init__(self):
        if self.box_loss not in BOX_LOSSES:
            raise ValueError(f"box_loss must be one of {BOX_LOSSES}, got {self.box_loss!r}")
        if self.box_cue not in BOX_CUES:
            raise ValueError(f"box_cue must be one of {BOX_CUES}, got {self.box_cue!r}")


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
# Training.
# --------------------------------------------------------------------------------------------------


def normalisation(rows: Rows) -> dict:
    """VDOFParams constants from the train rows: pixel mean/std, velocity and rate RMS, box RMS and max, and
    the label std (the loss's unit-variance scale)."""
    v_b = np.asarray(jax.vmap(vdof.body_velocity)(jnp.asarray(rows.x)))
    rms = lambda a: np.sqrt(np.mean(np.square(a), axis=0))  # noqa: E731
    return {"uv_mean": rows.p[:, :2].mean(0), "uv_std": np.maximum(rows.p[:, :2].std(0), 1e-3),
            "velocity_scale": np.maximum(rms(v_b), 0.1), "rate_scale": np.maximum(rms(rows.w), 0.1),
            "box_scale": np.float32(max(rms(rows.p[:, 2]), 1e-3)), "box_max": np.float32(rows.p[:, 2].max()),
            "p_dot_scale": np.maximum(rows.p_dot.std(0), 1e-4)}


def _predict(params: vdof.VDOFParams, x, p, w) -> jax.Array:
    """(N, 3) p_dot of N rows; the thrust is not an input of the model (zero here)."""
    u = jnp.concatenate([w, jnp.zeros_like(w[:, :1])], axis=1)
    return jax.vmap(vdof.pixel_state_velocity, in_axes=(None, 0, 0, 0))(params, x, p, u)


def residual_scale(rows: Rows, reference: Rows, box_loss: str) -> np.ndarray:
    """(N, 3) what each row's ``p_dot`` residual is divided by in the loss: the ``reference`` (train) labels'
    std per component; with ``box_loss`` "relative" the box component is ``s * std(s_dot / s)``."""
    scale = np.broadcast_to(np.maximum(reference.p_dot.std(0), 1e-4), rows.p_dot.shape).copy()
    if box_loss == "relative":
        s_ref = np.maximum(reference.p[:, 2], 1e-3)
        scale[:, 2] = np.maximum(rows.p[:, 2], 1e-3) * max(float((reference.p_dot[:, 2] / s_ref).std()), 1e-4)
    return scale.astype(np.float32)


def scaled_mse(params: vdof.VDOFParams, x, p, w, p_dot, scale) -> jax.Array:
    """() mean squared error of p_dot, each residual divided by its ``scale`` (N, 3) (:func:`residual_scale`)."""
    return jnp.mean(jnp.square((_predict(params, x, p, w) - p_dot) / scale))


class LossRows(NamedTuple):
    """Rows on the device with their residual scale (N, 3) (:func:`residual_scale`)."""

    x: jax.Array
    p: jax.Array
    w: jax.Array
    p_dot: jax.Array
    scale: jax.Array


def loss_rows(rows: Rows, reference: Rows, box_loss: str) -> LossRows:
    """``rows`` as float32 device arrays with their residual scale against the ``reference`` (train) rows."""
    scale = residual_scale(rows, reference, box_loss)
    return LossRows(*(jnp.asarray(a, jnp.float32) for a in rows), jnp.asarray(scale))


def one_step_loss(params: vdof.VDOFParams, batch: LossRows) -> jax.Array:
    """The first stage's loss: :func:`scaled_mse` of a batch."""
    return scaled_mse(params, *batch)


class Windows(NamedTuple):
    """K-step windows of logged laps (M of them). x: (M, K, 10) states; w: (M, K, 3) flown rates; p: (M, K+1, 3)
    detected pixel states; mask: (M, K+1) the target still the same and detected; scale: (M, 3) the loss's
    scale of uv error and of the box size's relative error (:func:`rollout_loss`)."""

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


def rollout(params: vdof.VDOFParams, x: jax.Array, w: jax.Array, p0: jax.Array, dt: float) -> jax.Array:
    """Euler rollout of the pixel state (K+1, 3) from p0 (3,) along states x (K, 10) and flown rates w (K, 3)."""
    u = jnp.concatenate([w, jnp.zeros_like(w[:, :1])], axis=1)

    def step(p, xu):
        p = p + dt * vdof.pixel_state_velocity(params, xu[0], p, xu[1])
        return p, p

    _, traj = jax.lax.scan(step, p0, (x, u))
    return jnp.concatenate([p0[None], traj])


def rollout_loss(params: vdof.VDOFParams, batch: Windows, dt: float = timing.CONTROL_DT) -> jax.Array:
    """The second stage's loss: over the masked steps of K-step rollouts from the detected pixel state, the squared
    uv error and the box size's relative error, each over its scale."""
    pred = jax.vmap(rollout, in_axes=(None, 0, 0, 0, None))(params, batch.x, batch.w, batch.p[:, 0], dt)
    scale = batch.scale[:, None, :]
    uv_err = jnp.sum(jnp.square((pred[..., :2] - batch.p[..., :2]) / scale[..., :2]), axis=-1)
    box_err = jnp.square((pred[..., 2] - batch.p[..., 2]) / jnp.maximum(batch.p[..., 2], 1e-3) / scale[..., 2])
    mask = batch.mask.astype(pred.dtype)
    return jnp.sum((uv_err + box_err) * mask) / jnp.maximum(jnp.sum(mask), 1.0)


class TrainState(NamedTuple):
    params: vdof.VDOFParams
    opt_state: optax.OptState
    key: jax.Array
    step: jax.Array


@functools.partial(jax.jit, static_argnames=("loss_fn", "optimizer", "batch_size", "length"), donate_argnums=(0,))
def train_chunk(state: TrainState, data, loss_fn, optimizer, batch_size: int, length: int):
    """``length`` Adam steps on minibatches of ``data`` (a pytree of (N, ...) arrays) in one scan; returns the new
    state and the chunk's mean batch loss. ``loss_fn(params, batch) -> ()``."""
    n = jax.tree_util.tree_leaves(data)[0].shape[0]

    def step(state: TrainState, _):
        key, key_batch = jax.random.split(state.key)
        idx = jax.random.randint(key_batch, (batch_size,), 0, n)
        batch = jax.tree_util.tree_map(lambda a: a[idx], data)
        loss, grads = jax.value_and_grad(lambda wt: loss_fn(state.params.replace(weights=wt), batch))(
            state.params.weights)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params.weights)
        weights = optax.apply_updates(state.params.weights, updates)
        return TrainState(state.params.replace(weights=weights), opt_state, key, state.step + 1), loss

    state, losses = jax.lax.scan(step, state, None, length=length)
    return state, jnp.mean(losses)


def _fit(state: TrainState, stage: str, data, test, loss_fn, optimizer, steps: int, batch_size: int,
         config: VDOFTrainConfig, history: dict) -> TrainState:
    """Run ``steps`` (rounded up to whole chunks of ``log_every``) and append the learning curve to ``history``:
    ``stage``, ``step``, ``train_loss`` / ``test_loss`` (the stage's loss on every train / held-out row or
    window), ``batch_loss``, ``wall_s``."""
    full_loss = jax.jit(loss_fn)
    t0 = time.perf_counter()

    def log(batch_loss) -> None:
        for name, value in (("stage", stage), ("step", int(state.step)),
                            ("train_loss", float(full_loss(state.params, data))),
                            ("test_loss", None if test is None else float(full_loss(state.params, test))),
                            ("batch_loss", None if batch_loss is None else float(batch_loss)),
                            ("wall_s", time.perf_counter() - t0)):
            history.setdefault(name, []).append(value)

    log(None)
    chunks = -(-steps // config.log_every)
    with tqdm(total=chunks * config.log_every, disable=not config.progress, desc=f"vdof {stage}",
              dynamic_ncols=True) as bar:
        for _ in range(chunks):
            state, batch_loss = train_chunk(state, data, loss_fn, optimizer, batch_size, config.log_every)
            log(batch_loss)
            bar.update(config.log_every)
            bar.set_postfix(train=f"{history['train_loss'][-1]:.4f}",
                            test="-" if test is None else f"{history['test_loss'][-1]:.4f}")
    return state


def train(config: VDOFTrainConfig, rows: Rows, test_rows: Rows | None = None, windows: Windows | None = None,
          test_windows: Windows | None = None, dt: float = timing.CONTROL_DT) -> tuple[vdof.VDOFParams, dict]:
    """Stage 1: Adam on the one-step loss of ``rows`` (fresh weights, the rows' normalisation); stage 2, with
    ``windows`` and ``config.rollout_steps`` > 0: fine-tuning on :func:`rollout_loss`. Returns the params and the
    learning curve (:func:`_fit`; ``test_*`` the held-out rows and windows)."""
    if rows.x.shape[0] < 1:
        raise ValueError("no training rows: the target gate is never detected on two consecutive frames")
    data = loss_rows(rows, rows, config.box_loss)
    test = None if test_rows is None or test_rows.x.shape[0] == 0 else loss_rows(test_rows, rows, config.box_loss)
    key_init, key_batches = jax.random.split(jax.random.key(config.seed))
    params = vdof.init_vdof_params(key_init, config.hidden_sizes, **normalisation(rows))
    optimizer = optax.adam(optax.cosine_decay_schedule(config.learning_rate, max(config.steps, 1),
                                                       config.final_lr_fraction))
    state = TrainState(params, optimizer.init(params.weights), key_batches, jnp.asarray(0))
    history: dict = {}
    state = _fit(state, "one_step", data, test, one_step_loss, optimizer, config.steps, config.batch_size, config,
                 history)
    if windows is None or config.rollout_steps < 1 or config.rollout_train_steps < 1:
        return state.params, history
    optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(optax.cosine_decay_schedule(
        config.rollout_learning_rate, config.rollout_train_steps, config.final_lr_fraction)))
    state = state._replace(opt_state=optimizer.init(state.params.weights))
    state = _fit(state, "rollout", windows, test_windows, functools.partial(rollout_loss, dt=float(dt)), optimizer,
                 config.rollout_train_steps, config.rollout_batch_size, config, history)
    return state.params, history


# --------------------------------------------------------------------------------------------------
# Evaluation: multi-step gate-centre error beside the DOF, and the response to the rates.
# --------------------------------------------------------------------------------------------------


def multistep_window_errors(vdof_params, dof_params, laps: list[dataset_lib.Lap], track, camera, horizon: int,
                            dt: float = timing.CONTROL_DT, box_cue: str = "apparent", dof_input: str = "flown") -> dict:
    """The multi-step prediction of vdof and the DOF on the same windows, defined as the DOF evaluation defines
    them (:func:`control_response.multistep_windows`: every start tick whose target gate is detected with its
    centre in the image, counted up to k while it stays so): vdof rolled from the detected ``[centre, s]`` with
    the flown rates, the DOF from the centre with its input ``dof_input``. Per start (rows) and k = 1..horizon:
    ``vdof`` and ``dof`` (the windows' arrays), ``box_rel`` (vdof's box size relative error), ``valid``."""
    model = control_response.pixel_state_model("vdof", box_cue)
    w_vdof = control_response.multistep_windows(model, vdof_params, laps, track, camera, horizon, dt, "flown")
    w_dof = control_response.multistep_windows(control_response.pixel_state_model("dof"), dof_params, laps, track,
                                               camera, horizon, dt, dof_input)
    pred, truth = w_vdof["pred"][..., 2], w_vdof["truth"][..., 2]
    return {"vdof": w_vdof, "dof": w_dof, "valid": w_vdof["valid"],
            "box_rel": np.abs(pred - truth) / np.maximum(truth, 1e-6)}


def multistep_errors(vdof_params, dof_params, laps: list[dataset_lib.Lap], track, camera,
                     horizons=EVAL_HORIZONS, dt: float = timing.CONTROL_DT, box_cue: str = "apparent") -> dict:
    """Mean gate-centre error (px at the camera's size) k steps ahead for vdof and the DOF (flown input) on the
    same windows (:func:`multistep_window_errors`), with the error of a still pixel and vdof's box-size relative
    error; per horizon in ``horizons`` and as full curves."""
    horizon = int(max(horizons))
    windows = multistep_window_errors(vdof_params, dof_params, laps, track, camera, horizon, dt, box_cue)
    valid = windows["valid"]
    err_vdof, err_dof, err_zero = windows["vdof"]["err"], windows["dof"]["err"], windows["vdof"]["err_zero"]

    def at(values, k, fn=np.mean):
        return float(fn(values[valid[:, k - 1], k - 1])) if valid[:, k - 1].any() else None

    table = {str(k): {"vdof_px": at(err_vdof, k), "dof_px": at(err_dof, k), "still_px": at(err_zero, k),
                      "vdof_box_rel_err": at(windows["box_rel"], k), "vdof_median_px": at(err_vdof, k, np.median),
                      "dof_median_px": at(err_dof, k, np.median), "windows": int(valid[:, k - 1].sum())}
             for k in horizons}
    curves = {"steps": list(range(1, horizon + 1)),
              "vdof_px": [at(err_vdof, k) for k in range(1, horizon + 1)],
              "dof_px": [at(err_dof, k) for k in range(1, horizon + 1)],
              "windows": [int(valid[:, k - 1].sum()) for k in range(1, horizon + 1)]}
    return {"by_horizon": table, "curves": curves, "starts": int(valid[:, 0].sum()),
            "windows": "start ticks whose target gate is detected with its centre in the image on every tick up to k"}


@jax.jit
def _vdof_rate_jacobian(params, x, p, uv):
    """(N, 2, 3) d(uv_dot)/d(w) at the pixel ``uv`` for each row's state and box size."""
    def one(xi, pi):
        pc = pi.at[:2].set(uv)
        f = lambda w: vdof.pixel_state_velocity(params, xi, pc, jnp.concatenate([w, jnp.zeros(1)]))[:2]  # noqa: E731
        return jax.jacfwd(f)(jnp.zeros(3))

    return jax.vmap(one)(x, p)


def rate_response(vdof_params, dof_params, rows: Rows, laps: list[dataset_lib.Lap], camera,
                  dt: float = timing.CONTROL_DT, uv=control_response.IMAGE_CENTRE_UV) -> dict:
    """Mean Jacobian of the pixel velocity w.r.t. the body rates at the pixel ``uv`` (default the image centre;
    px/frame per rad/s) of vdof (over the held-out rows) and of the DOF (over the held-out frames, flown input),
    against the pinhole camera's exact rotational flow there; ratio = model / exact (1 is right)."""
    uv = tuple(float(c) for c in uv)
    jac = np.asarray(_vdof_rate_jacobian(vdof_params, jnp.asarray(rows.x), jnp.asarray(rows.p),
                                         jnp.asarray(uv, jnp.float32)), np.float64)
    jac = jac.mean(0) * np.asarray([[camera.width * dt], [camera.height * dt]])
    q = np.concatenate([lap.states[:-1, 3:7] for lap in laps])
    u = np.concatenate([dataset_lib.lap_input(lap, "flown") for lap in laps])
    dof_resp = control_response.rotation_response(dof_params, q, u, camera, dt, uv=uv)
    exact = control_response.exact_rotation_response(camera, dt, uv)

    def entry(axis: int, rate: int, name: str) -> dict:
        e = float(exact[axis, rate])
        return {"exact": e, "vdof": float(jac[axis, rate]), "dof": dof_resp[name]["dof"],
                "vdof_ratio": float(jac[axis, rate]) / e, "dof_ratio": dof_resp[name]["ratio"]}

    return {"yaw_to_u": entry(0, 2, "yaw_to_u"), "pitch_to_v": entry(1, 1, "pitch_to_v"),
            "jacobian_vdof": jac.tolist(), "jacobian_exact": exact.tolist(),
            "uv": list(uv), "units": "px/frame per rad/s at 204 x 153"}


# --------------------------------------------------------------------------------------------------
# The run: train, evaluate, write.
# --------------------------------------------------------------------------------------------------


def plot_learning_curve(history: dict, path) -> None:
    """Training and held-out loss against steps (log scale), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    stages = np.asarray(history["stage"])
    labels = {"one_step": "one-step MSE of p_dot (unit variance)", "rollout": "rollout loss"}
    for stage, colour in (("one_step", "C0"), ("rollout", "C1")):
        at = np.nonzero(stages == stage)[0]
        if at.size == 0:
            continue
        steps = np.asarray(history["step"])[at]
        ax.semilogy(steps, np.asarray(history["train_loss"])[at], colour, label=f"{labels[stage]}, train")
        test = [history["test_loss"][i] for i in at]
        if all(v is not None for v in test):
            ax.semilogy(steps, test, colour, linestyle="--", label=f"{labels[stage]}, held-out laps")
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss of the stage")
    ax.set_title("vdof learning curve")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _record(config: VDOFTrainConfig, data_dir: Path, manifest_sha: str, rows: Rows, test_rows: Rows,
            history: dict, wall: float) -> dict:
    """The provenance stored with the weights."""
    return {"what": "vdof weights (velocity-and-depth DOF), pixelmpc_jax.learn.vdof_train",
            "train_config": dataclasses.asdict(config), "structure": vdof.STRUCTURE,
            "data": {"dir": str(data_dir), "manifest_sha256": manifest_sha, "train_rows": int(rows.x.shape[0]),
                     "test_rows": int(test_rows.x.shape[0]),
                     "labels": "finite differences of detect_from_geometry's centre and box size, same target gate"},
            "steps": int(history["step"][-1]), "train_wall_s": wall,
            "final_loss": {stage: {k: history[k][max(i for i, s in enumerate(history["stage"]) if s == stage)]
                                   for k in ("step", "train_loss", "test_loss")} for stage in set(history["stage"])},
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "versions": {"jax": jax.__version__, "optax": optax.__version__},
            "command": " ".join(sys.argv)}


def run(data_dir, out_dir, config: VDOFTrainConfig = VDOFTrainConfig(), dof_variant: str = "turned") -> dict:
    """Train on the dataset's train laps, evaluate on its test laps beside the packaged DOF ``dof_variant``, and
    write ``vdof_weights.msgpack``, ``vdof_eval.json`` and ``learning_curve.png`` to ``out_dir``."""
    data_dir, out = Path(data_dir), Path(out_dir)
    manifest = dataset_lib.read_manifest(data_dir)
    manifest_sha = dataset_lib.file_sha256(data_dir / dataset_lib.MANIFEST)
    dt = float(manifest.get("frame_dt_s", timing.CONTROL_DT))
    track, camera = course_lib.load_course(), camera_lib.default_camera()
    train_laps = dataset_lib.load_laps(data_dir, "train", with_flow=False, with_exact=False)
    test_laps = dataset_lib.load_laps(data_dir, "test", with_flow=False, with_exact=False)
    rows = load_rows(train_laps, track, camera, dt, config.box_cue)
    test_rows = load_rows(test_laps, track, camera, dt, config.box_cue)
    windows = test_windows = None
    if config.rollout_steps > 0:
        windows = load_windows(train_laps, track, camera, config.rollout_steps, config.box_cue)
        test_windows = load_windows(test_laps, track, camera, config.rollout_steps, config.box_cue, windows.scale[0])
    t0 = time.perf_counter()
    params, history = train(config, rows, test_rows, windows, test_windows, dt)
    wall = time.perf_counter() - t0
    record = _record(config, data_dir, manifest_sha, rows, test_rows, history, wall)
    out.mkdir(parents=True, exist_ok=True)
    vdof.save_vdof(out / "vdof_weights.msgpack", params, record)
    dof_params = dof.load_packaged_dof(dof_variant)
    evaluation = {"record": record, "dof_variant": dof_variant, "trainable_params": vdof.num_trainable_params(params),
                  "multistep": multistep_errors(params, dof_params, test_laps, track, camera, dt=dt,
                                                 box_cue=config.box_cue),
                  "rate_response": rate_response(params, dof_params, test_rows, test_laps, camera, dt),
                  "rate_response_at_median_pixel": rate_response(params, dof_params, test_rows, test_laps, camera,
                                                                 dt, np.median(test_rows.p[:, :2], axis=0)),
                  "history": history}
    strict_json.write_json_atomic(out / "vdof_eval.json", evaluation)
    plot_learning_curve(history, out / "learning_curve.png")
    return evaluation


def summary(evaluation: dict) -> str:
    """A few lines: losses, the multi-step table, the rate response."""
    rec, ms = evaluation["record"], evaluation["multistep"]["by_horizon"]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    losses = ", ".join(f"{stage} loss train {fmt(v['train_loss'])} held-out {fmt(v['test_loss'])}"
                       for stage, v in sorted(rec["final_loss"].items()))
    lines = [f"vdof {rec['train_config']['hidden_sizes']} ({rec['train_config']['box_cue']} box): {rec['steps']} "
             f"steps in {rec['train_wall_s']:.0f} s; {losses}", "steps  vdof_px  dof_px  still_px  windows"]
    lines += [f"{k:>5}  {fmt(v['vdof_px']):>7}  {fmt(v['dof_px']):>6}  {fmt(v['still_px']):>8}  {v['windows']:>7}"
              for k, v in ms.items()]
    for key in ("rate_response", "rate_response_at_median_pixel"):
        uv = evaluation[key]["uv"]
        for name in ("yaw_to_u", "pitch_to_v"):
            e = evaluation[key][name]
            lines.append(f"{name} at uv ({uv[0]:.2f}, {uv[1]:.2f}): exact {e['exact']:.3f} px/frame per rad/s, "
                         f"ratio vdof {e['vdof_ratio']:.3f}, dof {fmt(e['dof_ratio'])}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pixelmpc_jax.learn.vdof_train", description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="DOF dataset directory (pixelmpc collect)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--steps", type=int, default=VDOFTrainConfig.steps)
    parser.add_argument("--hidden", default=",".join(map(str, VDOFTrainConfig.hidden_sizes)),
                        help="hidden widths of g(uv), comma-separated")
    parser.add_argument("--lr", type=float, default=VDOFTrainConfig.learning_rate)
    parser.add_argument("--batch-size", type=int, default=VDOFTrainConfig.batch_size)
    parser.add_argument("--seed", type=int, default=VDOFTrainConfig.seed)
    parser.add_argument("--box-loss", default=VDOFTrainConfig.box_loss, choices=BOX_LOSSES)
    parser.add_argument("--box-cue", default=VDOFTrainConfig.box_cue, choices=BOX_CUES)
    parser.add_argument("--rollout-steps", type=int, default=VDOFTrainConfig.rollout_steps,
                        help="K of the rollout fine-tuning stage (0: none)")
    parser.add_argument("--rollout-train-steps", type=int, default=VDOFTrainConfig.rollout_train_steps)
    parser.add_argument("--rollout-lr", type=float, default=VDOFTrainConfig.rollout_learning_rate)
    parser.add_argument("--dof-variant", default="turned", choices=sorted(dof.PACKAGED_VARIANTS))
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    config = VDOFTrainConfig(hidden_sizes=tuple(int(h) for h in args.hidden.split(",") if h), steps=args.steps,
                             learning_rate=args.lr, batch_size=args.batch_size, seed=args.seed, box_loss=args.box_loss,
                             box_cue=args.box_cue, rollout_steps=args.rollout_steps,
                             rollout_train_steps=args.rollout_train_steps, rollout_learning_rate=args.rollout_lr,
                             progress=not args.no_progress)
    print(summary(run(args.data, args.out, config, args.dof_variant)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
