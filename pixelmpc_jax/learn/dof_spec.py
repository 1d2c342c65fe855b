"""The DOF as the learning pipeline (:mod:`pixelmpc_jax.learn.train`) trains it: the paper's Algorithm 1.

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

``DOFConfig.loss = "endpoint"`` trains the same network (its (l, theta) output, PolarToEuler after it) on
the squared endpoint error instead, ``L = mean |PolarToEuler(l_hat, theta_hat) - (u_dot, v_dot)|^2 / s^2``.
The two differ where the flow at a given (q, uv, u) is uncertain, which is most of the flow here: the DOF
does not see the velocity or the depth that make up the translational flow. The polar loss is minimised by
the mean flow LENGTH along the l^2-weighted mean direction; the endpoint loss by the mean flow VECTOR, which
is what the pixel dynamics uv_{t+1} = uv_t + dt * uv_dot integrates (measured: docs/choices.md). A further
loss is one function in :data:`LOSS_FUNCTIONS`.

One stage ("flow"): Adam on that loss, 10 % dropout drawn from the step's own key. Held out: the AEE on the
test laps (:mod:`pixelmpc_jax.learn.aee`) beside the zero flow's.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn import rotation_augment
from pixelmpc_jax.learn.aee import evaluate_aee, zero_flow_aee
from pixelmpc_jax.learn.dataset import INPUTS, FlowData, as_flow_data, pixel_uv
from pixelmpc_jax.learn.train import SCHEDULES, ModelSpec, Stage, StageData
from pixelmpc_jax.perception.flow import flow_to_polar
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH

# --------------------------------------------------------------------------------------------------
# Configuration.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DOFConfig:
    """The DOF's training settings (hashable; the ``model`` of a ``train.TrainConfig``, recorded with the weights).

    Attributes:
        steps: total optimizer steps (a resumed run continues up to this number).
        batch_size: random (frame, pixel) rows per step.
        learning_rate: Adam step size (the peak of the schedule).
        schedule: ``"constant"`` or ``"cosine"`` (decay to ``learning_rate * final_lr_fraction``).
        final_lr_fraction: end of the cosine schedule, relative to ``learning_rate``.
        width, height: image size in pixels; must match the flow arrays (set from the dataset by ``run_train``).
        dt: seconds between the two frames of a flow (the flow is in pixels per ``dt``; set from the dataset).
        probe_size: rows of the fixed, seeded probe batch whose deterministic loss is logged.
        eval_chunk_pixels: rows per compiled chunk in :func:`evaluate_aee` (bounds memory).
        loss: a name in :data:`LOSS_FUNCTIONS`: ``"polar"`` (the paper's MSE on (l, theta), in the form above)
            or ``"endpoint"`` (the squared endpoint error of the flow vector; see the module docstring).
        input: what the data's ``u`` is, one of :data:`INPUTS` (recorded with the weights; the training
            itself is the same: the data loader puts the chosen input in ``u``).
        rotation_augment: std (rad/s) of the extra body rate a row is turned by
            (:mod:`pixelmpc_jax.learn.rotation_augment`: the same frame pair as if the camera had turned
            that much more, label and rate changed exactly); 0 (the paper's) trains on the rows as flown.
            Needs ``input="flown"``: the turn is a rate flown, not commanded.
        rotation_augment_fraction: the share of rows turned when ``rotation_augment`` > 0.
        camera_tilt_deg: the upward tilt (deg) of the camera the data were seen through (set from the dataset:
            ``dataset.camera_tilt_deg``); the turned rows turn that camera, and the weights' record states it as the
            camera they serve.
    """

    # facts of the dataset, not settings
    DATA_FIELDS: ClassVar[tuple[str, ...]] = ("width", "height", "dt", "camera_tilt_deg")

    steps: int = 20_000
    batch_size: int = 4096
    learning_rate: float = 1e-3
    schedule: str = "cosine"
    final_lr_fraction: float = 0.05
    width: int = PAPER_WIDTH
    height: int = PAPER_HEIGHT
    dt: float = timing.CONTROL_DT
    probe_size: int = 8192
    eval_chunk_pixels: int = 1 << 18
    loss: str = "polar"
    input: str = "command"
    rotation_augment: float = 0.0
    rotation_augment_fraction: float = 1.0
    camera_tilt_deg: float = 0.0

    def __post_init__(self):
        for name in ("steps", "batch_size", "width", "height", "probe_size", "eval_chunk_pixels"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DOFConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.loss not in LOSSES:
            raise ValueError(f"DOFConfig.loss must be one of {LOSSES}, got {self.loss!r}")
        if self.input not in INPUTS:
            raise ValueError(f"DOFConfig.input must be one of {INPUTS}, got {self.input!r}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"DOFConfig.schedule must be 'constant' or 'cosine', got {self.schedule!r}")
        if not (self.learning_rate > 0 and self.dt > 0 and 0 <= self.final_lr_fraction <= 1):
            raise ValueError("DOFConfig needs learning_rate > 0, dt > 0, 0 <= final_lr_fraction <= 1")
        if not (0.0 <= self.rotation_augment < float("inf") and 0.0 <= self.rotation_augment_fraction <= 1.0):
            raise ValueError(f"DOFConfig needs finite rotation_augment >= 0 and rotation_augment_fraction in "
                             f"[0, 1], got {self.rotation_augment}, {self.rotation_augment_fraction}")
        if self.rotation_augment > 0 and self.input != "flown":
            raise ValueError("DOFConfig.rotation_augment needs input='flown': it turns the rate flown over "
                             "the frame, which a commanded rate is not")

    def with_data(self, manifest: dict) -> DOFConfig:
        """This config with the dataset's image size, frame interval and camera tilt."""
        width, height = manifest["image_size_wh"]
        return dataclasses.replace(self, width=int(width), height=int(height), dt=float(manifest["frame_dt_s"]),
                                   camera_tilt_deg=dataset_lib.camera_tilt_deg(manifest))

    def spec(self) -> ModelSpec:
        """The DOF as the pipeline trains it: one stage of Adam on :func:`dof_loss` over every pixel's row."""
        turned = f", rows turned by {self.rotation_augment:g} rad/s" if self.rotation_augment else ""
        stage = Stage("flow", self.steps, self.batch_size, self.learning_rate, self.final_lr_fraction,
                      draw=draw_batch, loss=flow_loss, settings=self, schedule=self.schedule)
        return ModelSpec(
            name="dof", label=f"{self.input} input, {self.loss} loss{turned}", stages=(stage,),
            init=functools.partial(init_params, self), stage_data=functools.partial(stage_data, self),
            held_out=functools.partial(held_out, self), summary=summary, describe=functools.partial(describe, self),
            data_record=functools.partial(data_record, self), load_data=functools.partial(load_data, self),
            save=dof.save_checkpoint, read=dof.read_checkpoint, packaged=dof.PACKAGED_WEIGHTS)


class Batch(NamedTuple):
    """Training rows. features: (B, 10) ``[q, uv, u]``; l, theta: (B,) targets (normalised units / s)."""

    features: jax.Array
    l: jax.Array
    theta: jax.Array


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


# The losses by name (DOFConfig.loss): (l_hat, theta_hat (B,), batch, 1 / s^2, the polar parts) -> loss ().
LOSS_FUNCTIONS = {"polar": polar_loss, "endpoint": endpoint_loss}
LOSSES = tuple(LOSS_FUNCTIONS)


# --------------------------------------------------------------------------------------------------
# The stage: its batches and its loss.
# --------------------------------------------------------------------------------------------------


def sample_batch(data: FlowData, key: jax.Array, batch_size: int, config: DOFConfig) -> Batch:
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


def draw_batch(config: DOFConfig, key: jax.Array, data: FlowData, batch_size: int):
    """The stage's draw: ``(key, batch, key_dropout)``, the state's key split in three (next, batch, dropout)."""
    key, key_batch, key_dropout = jax.random.split(key, 3)
    return key, sample_batch(data, key_batch, batch_size, config), key_dropout


def flow_loss(config: DOFConfig, weights, dof_params: dof.DOFParams, batch: Batch, dropout_key):
    """The stage's loss: :func:`dof_loss` of the configured kind, dropout from ``dropout_key`` (None: none)."""
    return dof_loss(weights, dof_params, batch, dropout_key, config.loss)


# --------------------------------------------------------------------------------------------------
# The spec's data, weights and record.
# --------------------------------------------------------------------------------------------------


def init_params(config: DOFConfig, key: jax.Array, train_data) -> dof.DOFParams:
    """Fresh weights with the normalisation constants of every pixel of ``train_data``'s frames."""
    host = as_flow_data(train_data, config.width, config.height)
    return dof.init_dof_params(key, **normalisation_constants(host, config.width, config.height, config.dt))


def stage_data(config: DOFConfig, train_data, test_data, seed: int) -> tuple[StageData]:
    """The frames on the device, and the fixed probe batch (key ``seed + 1``) of their rows."""
    host = as_flow_data(train_data, config.width, config.height)
    data = FlowData(jnp.asarray(host.q, jnp.float32), jnp.asarray(host.u, jnp.float32), jnp.asarray(host.flow))
    probe = sample_batch(data, jax.random.key(seed + 1), config.probe_size, config)
    return (StageData(data, probe, None),)


def held_out(config: DOFConfig, dof_params: dof.DOFParams, test_data) -> dict:
    """The AEE (px/frame) of the trained DOF on the held-out frames, and the zero flow's."""
    test = as_flow_data(test_data, config.width, config.height)
    return {"test_aee_px": evaluate_aee(dof_params, test.q, test.u, test.flow, config.width, config.height,
                                        config.dt, chunk_pixels=config.eval_chunk_pixels),
            "test_zero_flow_aee_px": zero_flow_aee(test.q, test.u, test.flow)}


def summary(results: dict | None) -> str:
    """The held-out figures in one line."""
    if not results:
        return "no held-out AEE"
    return f"held-out AEE {results['test_aee_px']:.2f} px/frame (zero flow {results['test_zero_flow_aee_px']:.2f})"


def describe(config: DOFConfig) -> dict:
    """The DOF's part of every record: the variant (input, loss, layers, turned rows), read back by
    ``dof.checkpoint_variant``."""
    return {"variant": {"input": config.input, "loss": config.loss, "layer_sizes": list(dof.LAYER_SIZES),
                        "input_means": ("the body rates commanded at the frame's tick (the paper's)"
                                        if config.input == "command" else
                                        "the body rates flown over the frame interval (dataset w_flown), commanded "
                                        "thrust"),
                        "rotation_augment": {"sigma_rad_s": float(config.rotation_augment),
                                             "fraction": float(config.rotation_augment_fraction)}}}


def data_record(config: DOFConfig, train_data, test_data) -> dict:
    """What the DOF trained on: every pixel of the training frames."""
    def frames(data) -> int:
        return int(as_flow_data(data, config.width, config.height).q.shape[0])

    return {"train_frames": frames(train_data), "test_frames": None if test_data is None else frames(test_data),
            "rows": f"every pixel of every frame at {config.width} x {config.height}"}


def load_data(config: DOFConfig, data_dir, manifest: dict) -> tuple[FlowData, FlowData | None]:
    """The dataset's train frames and its test frames (``None`` without test laps), ``u`` the config's input."""
    train_data = dataset_lib.load_dataset(data_dir, "train", input=config.input)
    has_test = bool(manifest["split"]["test"]) and manifest["frames"]["test"] > 0
    return train_data, dataset_lib.load_dataset(data_dir, "test", input=config.input) if has_test else None
