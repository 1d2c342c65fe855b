"""Self-supervised DOF training, the paper's Algorithm 1, and the `pixelmpc train` entry point.

Data: per frame ``f`` the orientation ``q[f]`` (4,), the control ``u[f]`` (4,) and the dense optical
flow ``flow[f]`` (H, W, 2) to the next frame, in PIXELS PER FRAME (``flow[y, x] = (du, dv)``, frames
``dt = 1/40`` s apart; :mod:`pixelmpc_jax.learn.dataset`). Every pixel of every frame is a training row:
pixel (i, j) has ``uv = ((i + 0.5) / W, (j + 0.5) / H)`` and target ``u_dot = du / W / dt``, ``v_dot = dv / H / dt``,
``l = hypot(u_dot, v_dot)``, ``theta = atan2(v_dot, u_dot)``. Rows are never materialised: each step
draws ``batch_size`` random (frame, x, y) triples with ``jax.random`` inside the compiled step and
gathers from the device-resident arrays (float16 flow is fine: 14,000 frames at 204 x 153 is 1.7 GB).

Loss (an MSE on (l, theta) in spirit, Algorithm 1 line 12)::

    L = mean[ (l_hat - l)^2 + l^2 * 2 (1 - cos(theta_hat - theta)) ] / s^2,   s = rms(l) on the data

* ``2 (1 - cos d) = (2 sin(d / 2))^2 = d^2 + O(d^4)`` is the squared angle error with the wrap-around
  handled: it is periodic and smooth, so theta = pi - e and theta = -pi + e are close, as they should be
  (the paper's plain MSE would call them 2 pi apart). Unlike ``atan2(sin d, cos d)^2`` its gradient has
  no jump at d = +-pi.
* The weight ``l^2`` (of the target, no gradient) measures the angle error as a chord at the flow's own
  radius, i.e. in the same units as ``l``: the direction of a near-zero flow (Farneback noise in
  textureless regions) counts for nothing, and a large flow's direction counts as much as its length.
  The two terms sum to the squared endpoint error up to ``l_hat ~ l``:
  ``|v_hat - v|^2 = (l_hat - l)^2 + 2 l_hat l (1 - cos d)``, so training and the AEE metric agree.
* ``s`` makes the loss dimensionless (order 1 at a zero prediction).

``TrainConfig.loss = "endpoint"`` trains the same network (its (l, theta) output, PolarToEuler after it) on
the squared endpoint error instead, ``L = mean |PolarToEuler(l_hat, theta_hat) - (u_dot, v_dot)|^2 / s^2``.
The two differ where the flow at a given (q, uv, u) is uncertain, which is most of the flow here: the DOF
does not see the velocity or the depth that make up the translational flow. The polar loss is minimised by
the mean flow LENGTH along the l^2-weighted mean direction; the endpoint loss by the mean flow VECTOR, which
is what the pixel dynamics uv_{t+1} = uv_t + dt * uv_dot integrates (measured: docs/choices.md). A further
loss is one function in :data:`LOSS_FUNCTIONS`.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import shlex
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization, struct
from tqdm.auto import tqdm

from pixelmpc_jax import strict_json, timing
from pixelmpc_jax.devices import batch_shardings
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.learn import curves, rotation_augment
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn.aee import evaluate_aee, zero_flow_aee
from pixelmpc_jax.learn.dataset import INPUTS, FlowData, as_flow_data, pixel_uv
from pixelmpc_jax.perception.flow import flow_to_polar
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH

# --------------------------------------------------------------------------------------------------
# Configuration, state.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration (hashable; JSON-recorded in every checkpoint).

    Attributes:
        steps: total optimizer steps (a resumed run continues up to this number).
        batch_size: random (frame, pixel) rows per step.
        learning_rate: Adam step size (the peak of the schedule).
        schedule: ``"constant"`` or ``"cosine"`` (decay to ``learning_rate * final_lr_fraction``).
        final_lr_fraction: end of the cosine schedule, relative to ``learning_rate``.
        seed: the one PRNG seed (initial weights, batches, dropout, probe batch).
        log_every: steps between history records and progress-bar updates.
        checkpoint_every: steps between checkpoints (0: only at the end and on interrupt).
        checkpoint_path: where checkpoints go (``None``: never written).
        width, height: image size in pixels; must match the flow arrays.
        dt: seconds between the two frames of a flow (the flow is in pixels per ``dt``).
        probe_size: rows of the fixed, seeded probe batch whose deterministic loss is logged.
        eval_chunk_pixels: rows per compiled chunk in :func:`evaluate_aee` (bounds memory).
        progress: show the tqdm progress bar.
        loss: a name in :data:`LOSS_FUNCTIONS`: ``"polar"`` (the paper's MSE on (l, theta), in the form above)
            or ``"endpoint"`` (the squared endpoint error of the flow vector; see the module docstring).
        input: what the data's ``u`` is, one of :data:`INPUTS` (recorded with the weights; the training
            itself is the same: the data loader puts the chosen input in ``u``).
        rotation_augment: std (rad/s) of the extra body rate a row is turned by
            (:mod:`pixelmpc_jax.learn.rotation_augment`: the same frame pair as if the camera had turned
            that much more, label and rate changed exactly); 0 (the paper's) trains on the rows as flown.
            Needs ``input="flown"``: the turn is a rate flown, not commanded.
        rotation_augment_fraction: the share of rows turned when ``rotation_augment`` > 0.
    """

    steps: int = 20_000
    batch_size: int = 4096
    learning_rate: float = 1e-3
    schedule: str = "cosine"
    final_lr_fraction: float = 0.05
    seed: int = 0
    log_every: int = 100
    checkpoint_every: int = 1000
    checkpoint_path: str | None = None
    width: int = PAPER_WIDTH
    height: int = PAPER_HEIGHT
    dt: float = timing.CONTROL_DT
    probe_size: int = 8192
    eval_chunk_pixels: int = 1 << 18
    progress: bool = True
    loss: str = "polar"
    input: str = "command"
    rotation_augment: float = 0.0
    rotation_augment_fraction: float = 1.0

    def __post_init__(self):
        for name in ("steps", "batch_size", "log_every", "width", "height", "probe_size", "eval_chunk_pixels"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.checkpoint_every < 0:
            raise ValueError(f"TrainConfig.checkpoint_every must be >= 0, got {self.checkpoint_every}")
        if self.loss not in LOSSES:
            raise ValueError(f"TrainConfig.loss must be one of {LOSSES}, got {self.loss!r}")
        if self.input not in INPUTS:
            raise ValueError(f"TrainConfig.input must be one of {INPUTS}, got {self.input!r}")
        if self.schedule not in ("constant", "cosine"):
            raise ValueError(f"TrainConfig.schedule must be 'constant' or 'cosine', got {self.schedule!r}")
        if not (self.learning_rate > 0 and self.dt > 0 and 0 <= self.final_lr_fraction <= 1):
            raise ValueError("TrainConfig needs learning_rate > 0, dt > 0, 0 <= final_lr_fraction <= 1")
        if not (0.0 <= self.rotation_augment < float("inf") and 0.0 <= self.rotation_augment_fraction <= 1.0):
            raise ValueError(f"TrainConfig needs finite rotation_augment >= 0 and rotation_augment_fraction in "
                             f"[0, 1], got {self.rotation_augment}, {self.rotation_augment_fraction}")
        if self.rotation_augment > 0 and self.input != "flown":
            raise ValueError("TrainConfig.rotation_augment needs input='flown': it turns the rate flown over "
                             "the frame, which a commanded rate is not")


class Batch(NamedTuple):
    """Training rows. features: (B, 10) ``[q, uv, u]``; l, theta: (B,) targets (normalised units / s)."""

    features: jax.Array
    l: jax.Array
    theta: jax.Array


@struct.dataclass
class TrainState:
    """Everything a step changes. ``key`` is split with purpose names each step, never reused."""

    step: jax.Array  # () int32
    dof_params: dof.DOFParams
    opt_state: Any
    key: jax.Array


# --------------------------------------------------------------------------------------------------
# Targets, normalisation, loss.
# --------------------------------------------------------------------------------------------------


def normalisation_constants(
    data: FlowData, width: int, height: int, dt: float, chunk_frames: int = 256
) -> dict[str, np.ndarray]:
    """Input mean/std per feature and output scale, from all pixels of all training frames.

    q and u are per frame (every frame has the same number of pixels, so frame statistics are row
    statistics); uv is the exact pixel-grid statistic; the l statistics are exact, in float64 chunks.
    theta is periodic and learned under a periodic loss: its offset is the direction of the mean flow
    and its scale 1 rad. A constant feature gets std 1 (instead of a division by zero).
    """
    q = data.q.astype(np.float64)
    u = data.u.astype(np.float64)
    gi = (np.arange(width) + 0.5) / width
    gj = (np.arange(height) + 0.5) / height
    feat_mean = np.concatenate([q.mean(0), [gi.mean(), gj.mean()], u.mean(0)])
    feat_std = np.concatenate([q.std(0), [gi.std(), gj.std()], u.std(0)])
    feat_std = np.where(feat_std > 1e-6, feat_std, 1.0)

    s1 = s2 = su = sv = 0.0
    for start in range(0, data.flow.shape[0], chunk_frames):
        chunk = data.flow[start : start + chunk_frames].astype(np.float32)
        u_dot = chunk[..., 0] / (width * dt)
        v_dot = chunk[..., 1] / (height * dt)
        l = np.hypot(u_dot, v_dot)
        s1 += float(l.sum(dtype=np.float64))
        s2 += float(np.square(l, dtype=np.float64).sum())
        su += float(u_dot.sum(dtype=np.float64))
        sv += float(v_dot.sum(dtype=np.float64))
    if not np.isfinite(s2):
        raise ValueError("flow contains non-finite values; drop or repair those frames before training")
    n = data.flow.shape[0] * height * width
    l_mean = s1 / n
    l_std = float(np.sqrt(max(s2 / n - l_mean**2, 0.0)))
    l_std = l_std if l_std > 1e-6 else max(l_mean, 1.0)
    theta_mean = float(np.arctan2(sv, su)) if (su or sv) else 0.0
    return {
        "input_mean": feat_mean.astype(np.float32),
        "input_std": feat_std.astype(np.float32),
        "output_mean": np.asarray([l_mean, theta_mean], np.float32),
        "output_std": np.asarray([l_std, 1.0], np.float32),
    }


def _loss_scale(dof_params: dof.DOFParams) -> jax.Array:
    """rms(l) of the training data, from the stored output constants (mean^2 + std^2)."""
    return jnp.sqrt(dof_params.output_mean[0] ** 2 + dof_params.output_std[0] ** 2)


def dof_loss(
    weights, dof_params: dof.DOFParams, batch: Batch, dropout_key: jax.Array | None, kind: str = "polar"
) -> tuple[jax.Array, dict]:
    """The module docstring's loss of ``kind`` (a name in :data:`LOSS_FUNCTIONS`) on one batch; returns
    (loss, parts). The parts are the polar loss's two terms whichever loss is trained, so histories compare."""
    chex.assert_shape(batch.features, (None, dof.INPUT_DIM))
    chex.assert_shape([batch.l, batch.theta], batch.features.shape[:1])  # (B,): a (B, 1) target would broadcast
    pred = dof.dof_forward(dof_params.replace(weights=weights), batch.features, dropout_key=dropout_key)
    l_hat, theta_hat = pred[:, 0], pred[:, 1]
    inv_s2 = 1.0 / jnp.square(_loss_scale(dof_params))
    loss_l = jnp.mean(jnp.square(l_hat - batch.l)) * inv_s2
    chord2 = 2.0 * (1.0 - jnp.cos(theta_hat - batch.theta))
    loss_theta = jnp.mean(jnp.square(batch.l) * chord2) * inv_s2
    parts = {"loss_l": loss_l, "loss_theta": loss_theta}
    return LOSS_FUNCTIONS[kind](l_hat, theta_hat, batch, inv_s2, parts), parts


def polar_loss(l_hat, theta_hat, batch: Batch, inv_s2, parts: dict) -> jax.Array:
    """The paper's MSE on (l, theta) in the module docstring's form: the sum of the two parts."""
    return parts["loss_l"] + parts["loss_theta"]


def endpoint_loss(l_hat, theta_hat, batch: Batch, inv_s2, parts: dict) -> jax.Array:
    """The squared endpoint error of the flow vector, ``mean |PolarToEuler(l_hat, theta_hat) - v|^2 / s^2``."""
    error = dof.polar_to_euler(l_hat, theta_hat) - dof.polar_to_euler(batch.l, batch.theta)
    return jnp.mean(jnp.sum(jnp.square(error), axis=-1)) * inv_s2


# The losses by name (TrainConfig.loss): (l_hat, theta_hat (B,), batch, 1 / s^2, the polar parts) -> loss ().
LOSS_FUNCTIONS = {"polar": polar_loss, "endpoint": endpoint_loss}
LOSSES = tuple(LOSS_FUNCTIONS)


# --------------------------------------------------------------------------------------------------
# Compiled steps.
# --------------------------------------------------------------------------------------------------


def make_optimizer(config: TrainConfig) -> tuple[optax.GradientTransformation, Callable]:
    """Adam (Algorithm 1) with the configured schedule; returns (optimizer, schedule)."""
    if config.schedule == "cosine":
        schedule = optax.cosine_decay_schedule(config.learning_rate, config.steps, config.final_lr_fraction)
    else:
        schedule = optax.constant_schedule(config.learning_rate)
    return optax.adam(schedule), schedule


def sample_batch(data: FlowData, key: jax.Array, batch_size: int, config: TrainConfig) -> Batch:
    """``batch_size`` uniform (frame, x, y) rows gathered from device arrays (no row materialisation), turned
    by :func:`rotation_augment.augment_batch` when ``config.rotation_augment`` > 0."""
    if config.rotation_augment:
        key, key_augment = jax.random.split(key)
    key_frame, key_x, key_y = jax.random.split(key, 3)
    n_frames = data.q.shape[0]
    f = jax.random.randint(key_frame, (batch_size,), 0, n_frames)
    i = jax.random.randint(key_x, (batch_size,), 0, config.width)
    j = jax.random.randint(key_y, (batch_size,), 0, config.height)
    uv = pixel_uv(i, j, config.width, config.height)
    u = data.u[f].astype(jnp.float32)  # (B, 4)
    flow = data.flow[f, j, i].astype(jnp.float32)  # (B, 2) pixels per frame
    if config.rotation_augment:
        u, flow = rotation_augment.turn_training_rows(key_augment, u, i, j, flow, config)
    features = dof.dof_features(data.q[f].astype(jnp.float32), uv, u)
    l, theta = flow_to_polar(flow, config.width, config.height, config.dt)  # (B,), (B,)
    return Batch(features, l, theta)


def make_train_step(config: TrainConfig) -> Callable:
    """``train_step(state, batch, key) -> (state, metrics)``, jitted: one Adam step on ``batch`` with
    dropout drawn from ``key``."""
    optimizer, schedule = make_optimizer(config)

    def train_step(state: TrainState, batch: Batch, key: jax.Array) -> tuple[TrainState, dict]:
        grad_fn = jax.value_and_grad(dof_loss, has_aux=True)
        (loss, parts), grads = grad_fn(state.dof_params.weights, state.dof_params, batch, key, config.loss)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.dof_params.weights)
        weights = optax.apply_updates(state.dof_params.weights, updates)
        metrics = {"loss": loss, **parts, "learning_rate": schedule(state.step), "grad_norm": optax.tree.norm(grads)}
        new_state = state.replace(step=state.step + 1, dof_params=state.dof_params.replace(weights=weights),
                                  opt_state=opt_state)
        return new_state, metrics

    return jax.jit(train_step)


def _compile_key(config: TrainConfig) -> TrainConfig:
    """``config`` with the fields that do not reach the compiled step set to fixed values."""
    return dataclasses.replace(config, steps=config.steps if config.schedule == "cosine" else 1, seed=0, log_every=1,
                               checkpoint_every=0, checkpoint_path=None, probe_size=1, eval_chunk_pixels=1,
                               progress=False, input="flown" if config.rotation_augment else "command")


def data_parallel_devices(batch_size: int) -> int:
    """How many devices a training batch is split over: every device present when the batch divides evenly
    among them, else 1 (the run is then single-device, and says so)."""
    count = jax.device_count()
    if count > 1 and batch_size % count:
        print(f"note: batch_size {batch_size} does not split evenly over {count} devices; training on one")
        return 1
    return count


def _make_iteration(config: TrainConfig, num_devices: int = 1) -> Callable:
    """The loop's compiled step; runs differing only in seed, logging or paths share one compilation."""
    return _cached_iteration(_compile_key(config), num_devices)


@functools.lru_cache(maxsize=8)
def _cached_iteration(config: TrainConfig, num_devices: int = 1) -> Callable:
    """The loop's single compiled call: sample a batch on device, then one train step.

    With several devices the batch is split over them along its rows (data parallel: the weights, the
    optimizer state and the dataset are replicated; XLA inserts the gradient all-reduce). The batch and
    the dropout masks are drawn from the same keys either way, so a run matches the single-device run up
    to the order of the gradient's floating-point sums.

    Not donated: the state is ~0.4 MB, and keeping the last completed state valid is what lets a
    KeyboardInterrupt save it.
    """
    train_step = make_train_step(config)
    rows = batch_shardings(num_devices).rows if num_devices > 1 else None

    @jax.jit
    def iteration(state: TrainState, data: FlowData) -> tuple[TrainState, dict]:
        key, key_batch, key_dropout = jax.random.split(state.key, 3)
        batch = sample_batch(data, key_batch, config.batch_size, config)
        if rows is not None:
            batch = jax.lax.with_sharding_constraint(batch, rows)
        return train_step(state.replace(key=key), batch, key_dropout)

    return iteration


def init_train_state(config: TrainConfig, train_data: FlowData) -> TrainState:
    """Fresh weights with normalisation constants from ``train_data``, Adam state, step 0."""
    key_init, key_train = jax.random.split(jax.random.key(config.seed))
    constants = normalisation_constants(train_data, config.width, config.height, config.dt)
    dof_params = dof.init_dof_params(key_init, **constants)
    optimizer, _ = make_optimizer(config)
    return TrainState(step=jnp.asarray(0, jnp.int32), dof_params=dof_params,
                      opt_state=optimizer.init(dof_params.weights), key=key_train)


# --------------------------------------------------------------------------------------------------
# Checkpoints with optimizer state.
# --------------------------------------------------------------------------------------------------


def _run_record(config: TrainConfig, data: FlowData) -> dict:
    return {
        "train_config": dataclasses.asdict(config),
        "variant": {"input": config.input, "loss": config.loss, "layer_sizes": list(dof.LAYER_SIZES)},
        "command": shlex.join(sys.argv),
        "data": {"frames": int(data.q.shape[0]), "height": config.height, "width": config.width},
        "versions": {"jax": jax.__version__, "optax": optax.__version__},
    }


def save_train_checkpoint(path, state: TrainState, record: dict, history: dict) -> None:
    """Weights + normalisation + config, and what resuming needs: step, Adam state, key, history."""
    extra = {"train": {"step": np.asarray(state.step), "opt_state": serialization.to_state_dict(state.opt_state),
                       "key": np.asarray(jax.random.key_data(state.key)), "history": strict_json.dumps(history)}}
    record = {**record, "step": int(state.step)}
    dof.save_checkpoint(path, state.dof_params, record, extra=extra)


def load_train_state(path, config: TrainConfig) -> tuple[TrainState, dict]:
    """Restore a TrainState and its history from :func:`save_train_checkpoint`'s file."""
    checkpoint = dof.read_checkpoint(path)
    saved = checkpoint.extra.get("train")
    if saved is None:
        raise ValueError(f"{path}: weights-only DOF checkpoint, no optimizer state to resume from")
    optimizer, _ = make_optimizer(config)
    template = optimizer.init(checkpoint.dof_params.weights)
    try:
        opt_state = serialization.from_state_dict(template, saved["opt_state"])
        state = TrainState(
            step=jnp.asarray(saved["step"], jnp.int32),
            dof_params=checkpoint.dof_params,
            opt_state=jax.tree_util.tree_map(jnp.asarray, opt_state),
            key=jax.random.wrap_key_data(jnp.asarray(saved["key"])),
        )
        history = json.loads(saved["history"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: training state is damaged or from another optimizer: {err!r}") from err
    return state, history


# --------------------------------------------------------------------------------------------------
# The loop.
# --------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames="kind")
def _deterministic_loss(dof_params: dof.DOFParams, batch: Batch, kind: str = "polar") -> jax.Array:
    return dof_loss(dof_params.weights, dof_params, batch, None, kind)[0]


def _probe_loss_fn(config: TrainConfig, data: FlowData) -> Callable:
    """Deterministic (no dropout) loss on a fixed seeded batch: a noise-free progress measure."""
    probe = sample_batch(data, jax.random.key(config.seed + 1), config.probe_size, config)
    return functools.partial(_deterministic_loss, batch=probe, kind=config.loss)


def train(config: TrainConfig, train_data, test_data=None, resume_from=None) -> tuple[dof.DOFParams, dict]:
    """Train the DOF network (Algorithm 1) and return ``(dof_params, history)``.

    Args:
        config: static settings.
        train_data, test_data: ``(q, u, flow)`` as :class:`FlowData`, a mapping or a tuple.
        resume_from: a checkpoint written by this function; training continues at its step with its
            Adam state, key and normalisation (``config.steps`` is the total to reach).

    Returns:
        dof_params: the trained parameters (with their normalisation constants).
        history: lists, one entry per ``log_every`` steps: ``step``; ``loss``, ``loss_l``,
        ``loss_theta``, ``learning_rate``, ``grad_norm`` of that step; ``loss_window`` (mean training
        loss since the previous entry, the progress bar's running loss); ``wall_s``; ``probe_loss``
        (deterministic loss on a fixed batch, at ``probe_step``, step 0 included). Also
        ``interrupted`` (bool) and, with ``test_data``, ``test_aee_px`` and ``test_zero_flow_aee_px``.
    """
    host_data = as_flow_data(train_data, config.width, config.height)
    if resume_from is not None:
        state, history = load_train_state(resume_from, config)
    else:
        state = init_train_state(config, host_data)
        history = {}
    for name in ("step", "loss", "loss_window", "loss_l", "loss_theta", "learning_rate", "grad_norm", "wall_s",
                 "probe_step", "probe_loss"):
        history.setdefault(name, [])
    history["interrupted"] = False

    data = FlowData(jnp.asarray(host_data.q, jnp.float32), jnp.asarray(host_data.u, jnp.float32),
                    jnp.asarray(host_data.flow))
    record = _run_record(config, host_data)
    num_devices = data_parallel_devices(config.batch_size)
    if num_devices > 1:  # replicate the dataset and the state on every device; the batch is split in the step
        data, state = jax.device_put((data, state), batch_shardings(num_devices).replicated)
    iteration = _make_iteration(config, num_devices)
    probe_loss = _probe_loss_fn(config, data)
    start = int(state.step)
    if start == 0:
        history["probe_step"].append(0)
        history["probe_loss"].append(float(probe_loss(state.dof_params)))
    checkpoint_path = Path(config.checkpoint_path) if config.checkpoint_path else None

    t0 = time.perf_counter()
    window = []  # this log window's per-step losses, still on device
    bar = tqdm(total=config.steps, initial=start, disable=not config.progress, desc="DOF", dynamic_ncols=True)
    try:
        for step in range(start + 1, config.steps + 1):
            state, metrics = iteration(state, data)
            window.append(metrics["loss"])
            bar.update(1)
            if step % config.log_every == 0 or step == config.steps:
                host = jax.device_get(metrics)
                history["step"].append(step)
                for name, value in host.items():
                    history[name].append(float(value))
                history["loss_window"].append(float(jnp.mean(jnp.stack(window))))
                window = []
                history["wall_s"].append(time.perf_counter() - t0)
                history["probe_step"].append(step)
                history["probe_loss"].append(float(probe_loss(state.dof_params)))
                bar.set_postfix(loss=f"{history['loss_window'][-1]:.4f}", probe=f"{history['probe_loss'][-1]:.4f}")
            if checkpoint_path and config.checkpoint_every and step % config.checkpoint_every == 0:
                save_train_checkpoint(checkpoint_path, state, record, history)
    except KeyboardInterrupt:
        history["interrupted"] = True
    finally:
        bar.close()
    if checkpoint_path:
        save_train_checkpoint(checkpoint_path, state, record, history)

    if test_data is not None and not history["interrupted"]:
        test = as_flow_data(test_data, config.width, config.height)
        history["test_aee_px"] = evaluate_aee(state.dof_params, test.q, test.u, test.flow, config.width, config.height,
                                              config.dt, chunk_pixels=config.eval_chunk_pixels)
        history["test_zero_flow_aee_px"] = zero_flow_aee(test.q, test.u, test.flow)
    return state.dof_params, history


# --------------------------------------------------------------------------------------------------
# The `pixelmpc train` entry point.
# --------------------------------------------------------------------------------------------------


def export_weights(path, dof_params: dof.DOFParams, record: dict) -> None:
    """Weights-only checkpoint (parameters + normalisation, ~140 KB) with ``record`` as its config, and the
    same record as readable JSON beside it (``.json``)."""
    path = Path(path)
    dof.save_checkpoint(path, dof_params, record)
    strict_json.write_json_atomic(path.with_suffix(".json"), record)


def run_train(data_dir, out_dir="runs/dof_train", config: TrainConfig = TrainConfig(), resume: bool = False,
              ship: bool = False) -> dict:
    """Train the DOF on ``data_dir``'s train laps (:func:`train`, Algorithm 1), report the test-lap AEE, and
    write ``out_dir/checkpoint.msgpack`` (resumable: Adam state), ``out_dir/dof_weights.msgpack`` (weights only,
    with the provenance record), ``history.json`` and ``learning_curve.png``. ``ship=True`` also copies the
    weights into the package (``pixelmpc_jax/data``). Prints a short summary; returns the record.
    ``config``: every training setting (:class:`TrainConfig`); its ``width``, ``height``, ``dt`` and
    ``checkpoint_path`` are set from the dataset and ``out_dir``. The variant (input, loss) is recorded in the
    weights' record (``variant``, read back by ``dof.checkpoint_variant``)."""
    data_dir, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest = dataset_lib.read_manifest(data_dir)
    W, H = manifest["image_size_wh"]
    checkpoint = out / "checkpoint.msgpack"
    config = dataclasses.replace(config, width=W, height=H, dt=float(manifest["frame_dt_s"]),
                                 checkpoint_path=str(checkpoint))
    train_data = dataset_lib.load_dataset(data_dir, "train", input=config.input)
    has_test = bool(manifest["split"]["test"]) and manifest["frames"]["test"] > 0
    test_data = dataset_lib.load_dataset(data_dir, "test", input=config.input) if has_test else None
    t0 = time.perf_counter()
    dof_params, history = train(config, train_data, test_data,
                                resume_from=checkpoint if (resume and checkpoint.exists()) else None)
    wall = time.perf_counter() - t0
    strict_json.write_json_atomic(out / "history.json", history)
    curves.plot_learning_curve(history, out / "learning_curve.png")
    record = _weights_record(config, data_dir, out, manifest, history, wall)
    weights = out / dof.PACKAGED_WEIGHTS.name  # dof_weights.msgpack, with its record dof_weights.json
    export_weights(weights, dof_params, record)
    if ship:
        shutil.copyfile(weights, dof.PACKAGED_WEIGHTS)
        shutil.copyfile(weights.with_suffix(".json"), dof.PACKAGED_WEIGHTS.with_suffix(".json"))
    aee, zero = history.get("test_aee_px"), history.get("test_zero_flow_aee_px")
    turned = f", rows turned by {config.rotation_augment:g} rad/s" if config.rotation_augment else ""
    print(f"trained {record['steps_done']} steps ({config.input} input, {config.loss} loss{turned}) in "
          f"{wall / 60:.1f} min on {manifest['frames']['train']} frames; test AEE "
          f"{'-' if aee is None else f'{aee:.2f}'} px/frame (zero flow {'-' if zero is None else f'{zero:.2f}'}); "
          f"weights: {weights}")
    return record


def _train_call(config: TrainConfig, data_dir: Path, out: Path) -> str:
    """The :func:`run_train` call that repeats this run, every training setting spelled out (not the fields
    run_train sets from the dataset and ``out_dir``, nor the progress bar)."""
    derived = ("width", "height", "dt", "checkpoint_path", "progress")
    settings = ", ".join(f"{f.name}={getattr(config, f.name)!r}" for f in dataclasses.fields(TrainConfig)
                         if f.name not in derived)
    return f"pixelmpc_jax.learn.train.run_train({str(data_dir)!r}, {str(out)!r}, TrainConfig({settings}))"


def _weights_record(config: TrainConfig, data_dir: Path, out: Path, manifest: dict, history: dict,
                    wall: float) -> dict:
    """The provenance record shipped with the weights: config, variant, data, results, calls, versions."""
    return {
        "what": "DOF weights (parameters + input/output normalisation), pixelmpc_jax.learn",
        "train_config": {**dataclasses.asdict(config), "checkpoint_path": None},
        "variant": {"input": config.input, "loss": config.loss, "layer_sizes": list(dof.LAYER_SIZES),
                    "input_means": ("the body rates commanded at the frame's tick (the paper's)"
                                    if config.input == "command" else
                                    "the body rates flown over the frame interval (dataset w_flown), commanded thrust"),
                    "rotation_augment": {"sigma_rad_s": float(config.rotation_augment),
                                         "fraction": float(config.rotation_augment_fraction)}},
        "train_wall_s": wall,
        "steps_done": history["step"][-1] if history["step"] else 0,
        "interrupted": history["interrupted"],
        "data": {"dir": str(data_dir), "collect_config": manifest["config"], "policy": manifest.get("policy"),
                 "format_version": manifest.get("format_version"), "excited_laps": manifest.get("excited_laps", []),
                 "frames": manifest["frames"], "bytes": manifest.get("bytes"),
                 "laps": [{k: e[k] for k in ("lap", "split", "speed", "seed", "frames", "end", "gates_passed")}
                          for e in manifest["laps"]]},
        "results": {"test_aee_px": history.get("test_aee_px"),
                    "test_zero_flow_aee_px": history.get("test_zero_flow_aee_px")},
        "calls": [
            f"pixelmpc_jax.learn.collect.collect({str(data_dir)!r}, "
            f"CollectConfig(**{json.dumps(manifest['config'])}))",
            _train_call(config, data_dir, out),
        ],
        "versions": manifest.get("versions", {}) | {"jax": jax.__version__},
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
