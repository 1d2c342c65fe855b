"""vdof (:mod:`pixelmpc_jax.dynamics.vdof`) as the learning pipeline (:mod:`pixelmpc_jax.learn.train`) trains it.

Self-supervised, as the paper's DOF: the rows are the gate detector's over consecutive frames of the logged laps
(:mod:`pixelmpc_jax.learn.vdof_data`), ``(x_t, p_t = [centre_t, s_t], w_flown_t)`` labelled ``p_dot``. Two stages of
Adam (optax) on minibatches drawn with the state's key: (1) "one_step", the MSE of ``p_dot`` with each component
scaled to unit variance (the box size's as ``s_dot / s`` by default, ``box_loss``); (2) "rollout", fine-tuning on
K-step Euler rollouts of the pixel state along the logged trajectory against the detections (``rollout_steps``,
0 skips it; gradients clipped to norm 1): the one-step fit leaves ``s``'s rate a few percent off, and
``s_dot ~ s^2`` turns that into a box that grows too fast near the gate, which the rollouts correct. ``box_cue``
"per_gate_size" divides ``s`` by the target opening's size (a course fact; the course's openings are 1.8 m and
3.0 m wide, which the apparent size cannot tell apart).

Held out (the dataset's test laps): the target pixel's one-step error and the gate centre predicted k steps ahead
(:mod:`pixelmpc_jax.learn.vdof_eval`'s figures), beside a packaged DOF (``comparison_dof``) on the same frames.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import dof, vdof
from pixelmpc_jax.learn import control_response, vdof_data, vdof_eval
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn.train import ModelSpec, Stage, StageData
from pixelmpc_jax.learn.vdof_data import Rows, Windows
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

BOX_LOSSES = ("absolute", "relative")
BOX_CUES = control_response.VDOF_BOX_CUES
HELD_OUT_HORIZON = 80  # steps of the held-out multi-step prediction (the paper's Fig. 7)

# --------------------------------------------------------------------------------------------------
# Configuration.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class VDOFConfig:
    """vdof's training settings (hashable; the ``model`` of a ``train.TrainConfig``, recorded with the weights).

    Attributes:
        hidden_sizes: widths of g(uv)'s hidden layers.
        steps: Adam steps of the one-step stage; batch_size: rows per step (drawn with replacement).
        learning_rate: peak rate; cosine decay to ``learning_rate * final_lr_fraction`` (both stages).
        box_loss: how the box size's rate is scored: "absolute" (``s_dot`` over its std, as ``uv_dot``) or
            "relative" (``s_dot / s`` over its std: the far gates' small ``s_dot`` count as much as the near ones').
        box_cue: what ``s`` is: "apparent" (``box_size`` of the detected corners, the default) or "per_gate_size"
            (that over the target opening's ``sqrt(width * height)``, m: a course fact, not a position; the
            course's gates come in two sizes, which "apparent" leaves the model to guess).
        rollout_steps: K of the second stage, which fine-tunes on K-step rollouts of the pixel state along the
            logged trajectories against the detections (0: no second stage; see :func:`rollout_loss`).
        rollout_train_steps, rollout_learning_rate, rollout_batch_size: its Adam steps (0: no second stage;
            gradients clipped to norm 1), peak rate (cosine decay) and windows per step.
        dt: seconds between frames, the labels' finite difference and the rollouts' step (set from the dataset).
        comparison_dof: the packaged DOF (``dof.PACKAGED_VARIANTS``) the held-out figures are reported beside.
        camera_tilt_deg: the upward tilt (deg) of the camera the data were seen through (set from the dataset:
            ``dataset.camera_tilt_deg``); its detector gives the rows, and the weights' record states it as the camera
            they serve.
    """

    DATA_FIELDS: ClassVar[tuple[str, ...]] = ("dt", "camera_tilt_deg")  # facts of the dataset, not settings

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
    dt: float = timing.CONTROL_DT
    comparison_dof: str = "turned"
    camera_tilt_deg: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "hidden_sizes", tuple(int(h) for h in self.hidden_sizes))
        if not self.hidden_sizes or min(self.hidden_sizes) < 1:
            raise ValueError(f"VDOFConfig.hidden_sizes must be one or more widths >= 1, got {self.hidden_sizes}")
        for name in ("steps", "batch_size", "rollout_batch_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"VDOFConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.rollout_steps < 0 or self.rollout_train_steps < 0:
            raise ValueError(f"VDOFConfig.rollout_steps and rollout_train_steps must be >= 0, got "
                             f"{self.rollout_steps}, {self.rollout_train_steps}")
        if self.box_loss not in BOX_LOSSES:
            raise ValueError(f"box_loss must be one of {BOX_LOSSES}, got {self.box_loss!r}")
        if self.box_cue not in BOX_CUES:
            raise ValueError(f"box_cue must be one of {BOX_CUES}, got {self.box_cue!r}")
        if not (self.learning_rate > 0 and self.rollout_learning_rate > 0 and self.dt > 0
                and 0 <= self.final_lr_fraction <= 1):
            raise ValueError("VDOFConfig needs learning rates > 0, dt > 0, 0 <= final_lr_fraction <= 1")
        if self.comparison_dof not in dof.PACKAGED_VARIANTS:
            raise ValueError(f"comparison_dof must be one of {tuple(dof.PACKAGED_VARIANTS)}, got "
                             f"{self.comparison_dof!r}")

    @property
    def rollout_stage(self) -> bool:
        """Whether the second stage runs."""
        return self.rollout_steps > 0 and self.rollout_train_steps > 0

    def with_data(self, manifest: dict) -> VDOFConfig:
        """This config with the dataset's frame interval and camera tilt."""
        return dataclasses.replace(self, dt=float(manifest["frame_dt_s"]),
                                   camera_tilt_deg=dataset_lib.camera_tilt_deg(manifest))

    def camera(self) -> camera_lib.Camera:
        """The camera the data were seen through: the paper's, tilted up by ``camera_tilt_deg``."""
        return camera_lib.default_camera(tilt=math.radians(self.camera_tilt_deg))

    def spec(self) -> ModelSpec:
        """vdof as the pipeline trains it: the one-step stage, then the rollout stage (when it runs)."""
        stages = [Stage("one_step", self.steps, self.batch_size, self.learning_rate, self.final_lr_fraction,
                        draw=draw_rows, loss=one_step_stage_loss, settings=self)]
        if self.rollout_stage:
            stages.append(Stage("rollout", self.rollout_train_steps, self.rollout_batch_size,
                                self.rollout_learning_rate, self.final_lr_fraction, draw=draw_rows,
                                loss=rollout_stage_loss, settings=self, clip_norm=1.0))
        return ModelSpec(
            name="vdof", label=f"hidden {list(self.hidden_sizes)}, {self.box_cue} box, {self.box_loss} box loss, "
                               f"rollout K={self.rollout_steps}",
            stages=tuple(stages), init=functools.partial(init_params, self),
            stage_data=functools.partial(stage_data, self), held_out=functools.partial(held_out, self),
            summary=summary, describe=describe, data_record=data_record, load_data=functools.partial(load_data, self),
            save=vdof.save_vdof, read=vdof.read_vdof_checkpoint, packaged=vdof.PACKAGED_VDOF)


class VDOFData(NamedTuple):
    """vdof's data of one split: the detector's rows, the K-step windows (``None`` without the rollout stage; a
    test split's scaled as the train split's) and the laps they come from."""

    rows: Rows
    windows: Windows | None
    laps: list[dataset_lib.Lap]


# --------------------------------------------------------------------------------------------------
# Normalisation and the losses.
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


# --------------------------------------------------------------------------------------------------
# The stages: their batches and their losses.
# --------------------------------------------------------------------------------------------------


def draw_rows(config: VDOFConfig, key: jax.Array, rows, batch_size: int):
    """Both stages' draw: ``(key, batch, None)``, the state's key split in two (next, batch) and ``batch_size``
    rows (or windows) of ``rows`` drawn with replacement; the losses draw nothing."""
    key, key_batch = jax.random.split(key)
    idx = jax.random.randint(key_batch, (batch_size,), 0, jax.tree_util.tree_leaves(rows)[0].shape[0])
    return key, jax.tree_util.tree_map(lambda a: a[idx], rows), None


def one_step_stage_loss(config: VDOFConfig, weights, params: vdof.VDOFParams, batch: LossRows, key_loss):
    """The one-step stage's loss (:func:`one_step_loss`) of ``weights``, no parts."""
    return one_step_loss(params.replace(weights=weights), batch), {}


def rollout_stage_loss(config: VDOFConfig, weights, params: vdof.VDOFParams, batch: Windows, key_loss):
    """The rollout stage's loss (:func:`rollout_loss` at the config's ``dt``) of ``weights``, no parts."""
    return rollout_loss(params.replace(weights=weights), batch, config.dt), {}


# --------------------------------------------------------------------------------------------------
# The spec's data, weights and record.
# --------------------------------------------------------------------------------------------------


def init_params(config: VDOFConfig, key: jax.Array, train: VDOFData) -> vdof.VDOFParams:
    """Fresh weights of the configured widths with the normalisation constants of the train rows."""
    if train.rows.x.shape[0] < 1:
        raise ValueError("no training rows: the target gate is never detected on two consecutive frames")
    return vdof.init_vdof_params(key, config.hidden_sizes, **normalisation(train.rows))


def stage_data(config: VDOFConfig, train: VDOFData, test: VDOFData | None, seed: int) -> tuple[StageData, ...]:
    """Per stage the rows (or windows) on the device; each stage's probes are all its train and held-out rows."""
    rows = loss_rows(train.rows, train.rows, config.box_loss)
    test_rows = None if test is None or test.rows.x.shape[0] == 0 else loss_rows(test.rows, train.rows,
                                                                                  config.box_loss)
    data = [StageData(rows, rows, test_rows)]
    if config.rollout_stage:
        data.append(StageData(train.windows, train.windows, None if test is None else test.windows))
    return tuple(data)


def held_out(config: VDOFConfig, params: vdof.VDOFParams, test: VDOFData) -> dict:
    """The trained vdof's held-out figures beside the packaged ``comparison_dof`` on the same frames: the target
    pixel's one-step error and the gate centre's error k steps ahead (``vdof_eval``'s definitions)."""
    track, camera = course_lib.load_course(), config.camera()
    dof_params, dof_record = dof.load_checkpoint(dof.PACKAGED_VARIANTS[config.comparison_dof])
    dof_input = dof.checkpoint_variant(dof_record)["input"]
    one_step = vdof_eval.target_one_step_errors(params, dof_params, test.laps, track, camera, config.dt,
                                                config.box_cue, dof_input)
    multistep = vdof_eval.multistep_figures(params, dof_params, test.laps, track, camera, HELD_OUT_HORIZON,
                                            config.dt, config.box_cue, dof_input)

    def mean_px(name: str) -> dict:
        return {k: v["mean_px"] for k, v in multistep[name]["multistep_at"].items()}

    return {"comparison_dof": config.comparison_dof, "dof_input": dof_input, "target_one_step": one_step,
            "multistep_px": mean_px("vdof"), "dof_multistep_px": mean_px("dof"),
            "box_size_rel_err_at": multistep["box_size_rel_err_at"]}


def summary(results: dict | None) -> str:
    """The held-out figures in one line."""
    if not results:
        return "no held-out figures"

    def fmt(v):
        return "-" if v is None else f"{v:.2f}"

    one_step, dof_name = results["target_one_step"], f"the {results['comparison_dof']} DOF"
    return (f"held-out target one-step error {fmt(one_step['vdof_px'])} px/frame ({dof_name} "
            f"{fmt(one_step['dof_px'])}); 40-step gate-centre error {fmt(results['multistep_px'].get('40'))} px "
            f"({dof_name} {fmt(results['dof_multistep_px'].get('40'))})")


def describe() -> dict:
    """vdof's part of every record: the model's structure."""
    return {"structure": vdof.STRUCTURE}


def data_record(train: VDOFData, test: VDOFData | None) -> dict:
    """What vdof trained on: the detector's rows and windows."""
    def count(data: VDOFData | None, name: str) -> int | None:
        part = None if data is None else getattr(data, name)
        return None if part is None else int(jax.tree_util.tree_leaves(part)[0].shape[0])

    return {"train_rows": count(train, "rows"), "test_rows": count(test, "rows"),
            "train_windows": count(train, "windows"), "test_windows": count(test, "windows"),
            "labels": "finite differences of detect_from_geometry's centre and box size, same target gate"}


def load_data(config: VDOFConfig, data_dir, manifest: dict) -> tuple[VDOFData, VDOFData | None]:
    """The detector's rows (and windows, for the rollout stage) of the dataset's train and test laps; the test
    windows scaled as the train windows; no test data without test laps. The detector sees through the config's
    camera (``with_data``: the dataset's)."""
    track, camera = course_lib.load_course(), config.camera()

    def split(name: str, scale=None) -> VDOFData:
        laps = dataset_lib.load_laps(data_dir, name, with_flow=False, with_exact=False)
        if not laps:
            return VDOFData(Rows(*(np.zeros((0, n), np.float32) for n in (10, 3, 3, 3))), None, laps)
        rows = vdof_data.load_rows(laps, track, camera, config.dt, config.box_cue)
        windows = (vdof_data.load_windows(laps, track, camera, config.rollout_steps, config.box_cue, scale)
                   if config.rollout_stage else None)
        return VDOFData(rows, windows, laps)

    train = split("train")
    test = split("test", None if train.windows is None else train.windows.scale[0])
    return train, test if test.laps else None
