"""The one learning pipeline of the pixel models, and what `pixelmpc train` calls.

A model enters as a :class:`ModelSpec` (the DOF's, the paper's Algorithm 1: :mod:`pixelmpc_jax.learn.dof_spec`;
vdof's: :mod:`pixelmpc_jax.learn.vdof_spec`), made once from its frozen config (``TrainConfig.model.spec()``):
how its weights start (the normalisation constants from the training data), the data each stage trains on, and per
:class:`Stage` how a step draws its batch and which loss it minimises. Everything else is this module's and the
same for every model:

* the train state (:class:`TrainState`: step, parameters, Adam state, key) and Adam (optax) per stage, its state
  fresh at each stage's start;
* the compiled chunk (:func:`train_chunk`): ``lax.scan`` over the steps up to the next log or checkpoint step,
  each splitting the key as the model's draw says;
* the learning curve (the history: the mean training loss per log window, the deterministic loss on fixed
  training and held-out rows at each log step, per stage; drawn by :mod:`pixelmpc_jax.learn.curves`);
* checkpoints with the Adam state (resume bit for bit; Ctrl-C saves the last finished chunk), the data-parallel
  split over devices, and the weights file with its provenance record (:func:`run_train`).
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization, struct
from tqdm.auto import tqdm

from pixelmpc_jax import platform_info, strict_json
from pixelmpc_jax.devices import batch_shardings
from pixelmpc_jax.dynamics import network_weights
from pixelmpc_jax.learn import curves
from pixelmpc_jax.learn import dataset as dataset_lib

SCHEDULES = ("cosine", "constant")

# --------------------------------------------------------------------------------------------------
# The model as the pipeline sees it.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Stage:
    """One run of Adam over one loss (static and hashable: the compiled chunk's key).

    Attributes:
        name: what the stage fits ("flow" for the DOF; "one_step" and "rollout" for vdof), as the history says.
        steps, batch_size: Adam steps; rows (or windows) per step.
        learning_rate: the peak step size; ``schedule`` "cosine" decays it to ``learning_rate * final_lr_fraction``
            over the stage's steps, "constant" keeps it.
        clip_norm: the gradient is clipped to this global norm before Adam (``None``: not clipped).
        draw: ``(settings, key, rows, batch_size) -> (key, batch, key_loss)``: the state's next key and a batch drawn
            from the stage's rows (:class:`StageData`), and the key of the loss's own randomness (``None``: none).
            Each model splits the key its own way, once per step.
        loss: ``(settings, weights, params, batch, key_loss) -> (loss (), parts {name: ()})``; ``key_loss=None`` is
            the deterministic loss (the probes').
        settings: what ``draw`` and ``loss`` read: the model's config.
    """

    name: str
    steps: int
    batch_size: int
    learning_rate: float
    final_lr_fraction: float
    draw: Callable
    loss: Callable
    settings: Any
    schedule: str = "cosine"
    clip_norm: float | None = None

    def __post_init__(self):
        if int(self.steps) < 1 or int(self.batch_size) < 1:
            raise ValueError(f"stage {self.name}: steps and batch_size must be >= 1, got {self.steps}, "
                             f"{self.batch_size}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"stage {self.name}: schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if not (self.learning_rate > 0 and 0 <= self.final_lr_fraction <= 1):
            raise ValueError(f"stage {self.name}: needs learning_rate > 0 and 0 <= final_lr_fraction <= 1")

    def optimizer(self) -> tuple[optax.GradientTransformation, Callable]:
        """Adam with the stage's schedule (after the clip, with ``clip_norm``); returns (optimizer, schedule)."""
        if self.schedule == "cosine":
            schedule = optax.cosine_decay_schedule(self.learning_rate, self.steps, self.final_lr_fraction)
        else:
            schedule = optax.constant_schedule(self.learning_rate)
        adam = optax.adam(schedule)
        if self.clip_norm is None:
            return adam, schedule
        return optax.chain(optax.clip_by_global_norm(self.clip_norm), adam), schedule


class StageData(NamedTuple):
    """A stage's device arrays: ``rows`` (what ``Stage.draw`` draws batches from), ``probe`` and ``test_probe``
    (fixed batches of training and held-out rows whose deterministic loss the history logs; ``None``: none)."""

    rows: Any
    probe: Any
    test_probe: Any


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """A pixel model as the pipeline trains it, made once from its config (``config.spec()``).

    Attributes:
        name: "dof" or "vdof" (the record's ``model``, the curve's title, the progress bar).
        label: its settings in a few words, for the run's summary line.
        stages: the Adam runs, in order; the state's step counts on across them.
        init: ``(key, train) -> params``: fresh weights with the normalisation constants of the training data.
        stage_data: ``(train, test | None, seed) -> tuple[StageData, ...]``, one per stage.
        held_out: ``(params, test) -> dict``: the trained weights' figures on the held-out data (the record's
            ``results``).
        summary: ``(results | None) -> str``: one line of those figures.
        describe: ``() -> dict``: the model's part of every record (the DOF's ``variant``, vdof's ``structure``).
        data_record: ``(train, test | None) -> dict``: what the model trained on, beside the dataset's record.
        load_data: ``(data_dir, manifest) -> (train, test | None)``: the model's training and held-out data.
        save: ``(path, params, record, *, extra=None)``: the model's weights file (``extra``: what resuming needs).
        read: ``path -> (params, record, extra)``.
        packaged: the weights file shipped in the package (``--ship`` copies there).
    """

    name: str
    label: str
    stages: tuple[Stage, ...]
    init: Callable
    stage_data: Callable
    held_out: Callable
    summary: Callable
    describe: Callable
    data_record: Callable
    load_data: Callable
    save: Callable
    read: Callable
    packaged: Path

    def stage_bounds(self) -> list[tuple[int, int]]:
        """``(first step, last step)`` of each stage, counted on from the previous stage's end."""
        ends = np.cumsum([stage.steps for stage in self.stages]).tolist()
        return list(zip([0, *ends[:-1]], ends, strict=True))


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration (hashable; recorded whole with the weights).

    Attributes:
        model: the pixel model's own config (``dof_spec.DOFConfig`` or ``vdof_spec.VDOFConfig``: its stages' steps,
            batch and learning rate, its loss and inputs); ``model.spec()`` is its :class:`ModelSpec`.
        seed: the one PRNG seed (initial weights, batches, dropout, the probe batch).
        log_every: steps between history records and progress-bar updates (also the compiled chunk's length).
        checkpoint_every: steps between checkpoints (0: only at the end and on interrupt).
        checkpoint_path: where checkpoints go (``None``: never written).
        progress: show the tqdm progress bar.
    """

    model: Any
    seed: int = 0
    log_every: int = 100
    checkpoint_every: int = 1000
    checkpoint_path: str | None = None
    progress: bool = True

    def __post_init__(self):
        if int(self.log_every) < 1:
            raise ValueError(f"TrainConfig.log_every must be >= 1, got {self.log_every}")
        if self.checkpoint_every < 0:
            raise ValueError(f"TrainConfig.checkpoint_every must be >= 0, got {self.checkpoint_every}")


@struct.dataclass
class TrainState:
    """Everything a step changes. ``key`` is split by the stage's draw each step, never reused."""

    step: jax.Array  # () int32, counted on across the stages
    params: Any
    opt_state: Any
    key: jax.Array


def init_train_state(config: TrainConfig, spec: ModelSpec, train_data) -> TrainState:
    """Fresh weights with the normalisation constants of ``train_data``, the first stage's Adam state, step 0."""
    key_init, key_train = jax.random.split(jax.random.key(config.seed))
    params = spec.init(key_init, train_data)
    optimizer, _ = spec.stages[0].optimizer()
    return TrainState(step=jnp.asarray(0, jnp.int32), params=params, opt_state=optimizer.init(params.weights),
                      key=key_train)


# --------------------------------------------------------------------------------------------------
# The compiled chunk.
# --------------------------------------------------------------------------------------------------


def data_parallel_devices(batch_size: int) -> int:
    """How many devices a training batch is split over: every device present when the batch divides evenly
    among them, else 1 (the run is then single-device, and says so)."""
    count = jax.device_count()
    if count > 1 and batch_size % count:
        print(f"note: batch_size {batch_size} does not split evenly over {count} devices; training on one")
        return 1
    return count


@functools.partial(jax.jit, static_argnames=("stage", "start", "length", "num_devices"))
def train_chunk(state: TrainState, rows, stage: Stage, start: int, length: int,
                num_devices: int = 1) -> tuple[TrainState, dict]:
    """``length`` Adam steps of ``stage`` (which began at step ``start``) in one ``lax.scan``; returns the new
    state and per-step metrics, each (length,): ``loss``, the loss's parts, ``learning_rate``, ``grad_norm``.

    With several devices the batch is split over them along its rows (data parallel: the weights, the optimizer
    state and the rows are replicated; XLA inserts the gradient all-reduce). The batch and the loss's randomness
    are drawn from the same keys either way, so a run matches the single-device run up to the order of the
    gradient's floating-point sums. Not donated: keeping the last finished state valid is what lets an interrupt
    save it.
    """
    optimizer, schedule = stage.optimizer()
    sharding = batch_shardings(num_devices).rows if num_devices > 1 else None

    def step(state: TrainState, _) -> tuple[TrainState, dict]:
        key, batch, key_loss = stage.draw(stage.settings, state.key, rows, stage.batch_size)
        if sharding is not None:
            batch = jax.lax.with_sharding_constraint(batch, sharding)

        def loss_of(weights):
            return stage.loss(stage.settings, weights, state.params, batch, key_loss)

        (loss, parts), grads = jax.value_and_grad(loss_of, has_aux=True)(state.params.weights)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params.weights)
        weights = optax.apply_updates(state.params.weights, updates)
        metrics = {"loss": loss, **parts, "learning_rate": schedule(state.step - start),
                   "grad_norm": optax.tree.norm(grads)}
        return TrainState(step=state.step + 1, params=state.params.replace(weights=weights), opt_state=opt_state,
                          key=key), metrics

    return jax.lax.scan(step, state, None, length=length)


@functools.partial(jax.jit, static_argnames="stage")
def deterministic_loss(params, batch, stage: Stage) -> jax.Array:
    """() the stage's loss on ``batch`` without the loss's randomness (no dropout): the probes' measure."""
    return stage.loss(stage.settings, params.weights, params, batch, None)[0]


# --------------------------------------------------------------------------------------------------
# Checkpoints with optimizer state.
# --------------------------------------------------------------------------------------------------


def save_train_checkpoint(path, spec: ModelSpec, state: TrainState, record: dict, history: dict) -> None:
    """Weights + normalisation + record, and what resuming needs: step, Adam state, key, history."""
    extra = {"train": {"step": np.asarray(state.step), "opt_state": serialization.to_state_dict(state.opt_state),
                       "key": np.asarray(jax.random.key_data(state.key)), "history": strict_json.dumps(history)}}
    spec.save(path, state.params, {**record, "step": int(state.step)}, extra=extra)


def _stage_ended_in(spec: ModelSpec, step: int) -> Stage:
    """The stage whose Adam state a checkpoint at ``step`` holds: the one running at that step or just finished."""
    for stage, (_, end) in zip(spec.stages, spec.stage_bounds(), strict=True):
        if step <= end:
            return stage
    return spec.stages[-1]


def load_train_state(path, spec: ModelSpec) -> tuple[TrainState, dict]:
    """Restore a TrainState and its history from :func:`save_train_checkpoint`'s file."""
    params, _, extra = spec.read(path)
    saved = extra.get("train")
    if saved is None:
        raise ValueError(f"{path}: weights-only {spec.name} checkpoint, no optimizer state to resume from")
    try:
        optimizer, _ = _stage_ended_in(spec, int(saved["step"])).optimizer()
        opt_state = serialization.from_state_dict(optimizer.init(params.weights), saved["opt_state"])
        state = TrainState(step=jnp.asarray(saved["step"], jnp.int32), params=params,
                           opt_state=jax.tree_util.tree_map(jnp.asarray, opt_state),
                           key=jax.random.wrap_key_data(jnp.asarray(saved["key"])))
        history = json.loads(saved["history"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: training state is damaged or from another optimizer: {err!r}") from err
    return state, history


# --------------------------------------------------------------------------------------------------
# The loop.
# --------------------------------------------------------------------------------------------------


def _log_probes(history: dict, state: TrainState, stage: Stage, data: StageData) -> None:
    history["probe_step"].append(int(state.step))
    history["probe_stage"].append(stage.name)
    history["probe_loss"].append(float(deterministic_loss(state.params, data.probe, stage)))
    history["test_probe_loss"].append(
        None if data.test_probe is None else float(deterministic_loss(state.params, data.test_probe, stage)))


def _log_window(history: dict, state: TrainState, stage: Stage, metrics: dict, window: list, wall: float) -> None:
    """The log step's record: the last step's metrics, the window's mean training loss, the wall time."""
    history["step"].append(int(state.step))
    history["stage"].append(stage.name)
    for name, value in jax.device_get(metrics).items():
        history.setdefault(name, []).append(float(value[-1]))
    history["loss_window"].append(float(jnp.mean(jnp.concatenate(window))))
    history["wall_s"].append(wall)


def _next_stop(step: int, end: int, config: TrainConfig) -> int:
    """The next step that ends a chunk: a log step, a checkpoint step or the stage's end."""
    stops = [end, (step // config.log_every + 1) * config.log_every]
    if config.checkpoint_path and config.checkpoint_every:
        stops.append((step // config.checkpoint_every + 1) * config.checkpoint_every)
    return min(stops)


def _run_stage(state: TrainState, stage: Stage, start: int, end: int, data: StageData, config: TrainConfig,
               spec: ModelSpec, history: dict, record: dict, bar, t0: float) -> TrainState:
    """The stage's chunks from the state's step to ``end``, logging and checkpointing as configured. Ctrl-C (or
    SIGTERM) ends it early with the last finished chunk's state and ``history["interrupted"]`` set."""
    num_devices = data_parallel_devices(stage.batch_size)
    if num_devices > 1:  # replicate the rows and the state on every device; the batch is split in the step
        data, state = jax.device_put((data, state), batch_shardings(num_devices).replicated)
    step = int(state.step)
    if step == start and (history["probe_stage"][-1:], history["probe_step"][-1:]) != ([stage.name], [start]):
        _log_probes(history, state, stage, data)  # (a run resumed at the stage's start has logged them)
    window = []  # this log window's per-step losses, still on device
    try:
        while step < end:
            length = _next_stop(step, end, config) - step
            run_from = state
            if step == start and start > 0:  # the stage's own Adam state from its first chunk on (the state kept
                optimizer, _ = stage.optimizer()  # at the start holds the previous stage's: _stage_ended_in)
                run_from = state.replace(opt_state=optimizer.init(state.params.weights))
            new_state, metrics = train_chunk(run_from, data.rows, stage, start, length, num_devices)
            state, step = new_state, step + length
            window.append(metrics["loss"])
            bar.update(length)
            if step % config.log_every == 0 or step == end:
                _log_window(history, state, stage, metrics, window, time.perf_counter() - t0)
                window = []
                _log_probes(history, state, stage, data)
                bar.set_postfix(stage=stage.name, loss=f"{history['loss_window'][-1]:.4f}",
                                probe=f"{history['probe_loss'][-1]:.4f}")
            if config.checkpoint_path and config.checkpoint_every and step % config.checkpoint_every == 0:
                save_train_checkpoint(config.checkpoint_path, spec, state, record, history)
    except KeyboardInterrupt:
        history["interrupted"] = True
    return state


HISTORY_KEYS = ("step", "stage", "loss", "loss_window", "learning_rate", "grad_norm", "wall_s", "probe_step",
                "probe_stage", "probe_loss", "test_probe_loss")


def train(config: TrainConfig, train_data, test_data=None, resume_from=None) -> tuple[Any, dict]:
    """Train the model ``config.model`` names, stage after stage, and return ``(params, history)``.

    Args:
        config: static settings; ``config.model.spec()`` is the model (:class:`ModelSpec`), made here once.
        train_data, test_data: the model's data as its ``load_data`` gives it (the DOF: ``(q, u, flow)`` frames;
            vdof: the detector's rows and windows with their laps); ``test_data`` may be ``None``.
        resume_from: a checkpoint written by this function; training continues at its step with its Adam state,
            key and normalisation (the stages' steps are the totals to reach).

    Returns:
        params: the trained parameters (with their normalisation constants).
        history: lists, one entry per log step: ``step``, ``stage``; ``loss``, the loss's parts,
        ``learning_rate``, ``grad_norm`` of that step; ``loss_window`` (mean training loss since the previous
        entry); ``wall_s``. At every log step and each stage's start: ``probe_step``, ``probe_stage``,
        ``probe_loss`` (deterministic loss on a fixed batch of training rows) and ``test_probe_loss`` (on held-out
        rows; ``None`` where the model has none). Also ``interrupted`` (bool) and, with ``test_data`` and not
        interrupted, ``results`` (the model's held-out figures).
    """
    spec = config.model.spec()
    if resume_from is not None:
        state, history = load_train_state(resume_from, spec)
    else:
        state, history = init_train_state(config, spec, train_data), {}
    for name in HISTORY_KEYS:
        history.setdefault(name, [])
    history["interrupted"] = False
    data = spec.stage_data(train_data, test_data, config.seed)
    record = _run_record(config, spec, train_data, test_data)
    bounds = spec.stage_bounds()
    t0 = time.perf_counter()
    bar = tqdm(total=bounds[-1][1], initial=int(state.step), disable=not config.progress, desc=spec.name,
               dynamic_ncols=True)
    try:
        for stage, stage_data, (start, end) in zip(spec.stages, data, bounds, strict=True):
            if int(state.step) < end and not history["interrupted"]:
                state = _run_stage(state, stage, start, end, stage_data, config, spec, history, record, bar, t0)
    except KeyboardInterrupt:  # between chunks (a stage's start): the state is the last stage's end
        history["interrupted"] = True
    finally:
        bar.close()
    if config.checkpoint_path:
        save_train_checkpoint(config.checkpoint_path, spec, state, record, history)
    if test_data is not None and not history["interrupted"]:
        history["results"] = spec.held_out(state.params, test_data)
    return state.params, history


def _run_record(config: TrainConfig, spec: ModelSpec, train_data, test_data) -> dict:
    """The record every checkpoint of a run carries: the config whole, the model's description, the data."""
    return {"model": spec.name, "train_config": dataclasses.asdict(config), **spec.describe(),
            network_weights.CAMERA_TILT_KEY: float(config.model.camera_tilt_deg),
            "command": platform_info.invocation(), "data": spec.data_record(train_data, test_data),
            "versions": {"jax": jax.__version__, "optax": optax.__version__}}


# --------------------------------------------------------------------------------------------------
# The `pixelmpc train` entry point.
# --------------------------------------------------------------------------------------------------


def export_weights(spec: ModelSpec, path, params, record: dict) -> None:
    """Weights-only file (parameters + normalisation) with ``record`` as its config, and the same record as
    readable JSON beside it (``.json``)."""
    path = Path(path)
    spec.save(path, params, record)
    strict_json.write_json_atomic(path.with_suffix(".json"), record)


def run_train(data_dir, out_dir, config: TrainConfig, resume: bool = False, ship: bool = False) -> dict:
    """Train ``config.model`` on ``data_dir``'s train laps (:func:`train`), report its held-out figures on the test
    laps, and write ``out_dir/checkpoint.msgpack`` (resumable: Adam state), the weights with their provenance
    record (``dof_weights.msgpack`` or ``vdof_weights.msgpack``, and ``.json`` beside), ``history.json`` and
    ``learning_curve.png``. ``ship=True`` also copies the weights into the package (``pixelmpc_jax/data``). Prints a
    short summary; returns the record. The model's data facts (image size, frame interval) are set from the
    dataset (``config.model.with_data``) and ``checkpoint_path`` from ``out_dir``."""
    data_dir, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest = dataset_lib.read_manifest(data_dir)
    checkpoint = out / "checkpoint.msgpack"
    config = dataclasses.replace(config, model=config.model.with_data(manifest), checkpoint_path=str(checkpoint))
    spec = config.model.spec()
    train_data, test_data = spec.load_data(data_dir, manifest)
    t0 = time.perf_counter()
    params, history = train(config, train_data, test_data,
                            resume_from=checkpoint if (resume and checkpoint.exists()) else None)
    wall = time.perf_counter() - t0
    strict_json.write_json_atomic(out / "history.json", history)
    results = history.get("results")
    curves.plot_learning_curve(history, out / "learning_curve.png", title=f"{spec.name} learning curve",
                               note=spec.summary(results) + (" (interrupted)" if history["interrupted"] else ""))
    record = _weights_record(config, spec, data_dir, out, manifest, train_data, test_data, history, wall)
    weights = out / spec.packaged.name  # dof_weights.msgpack or vdof_weights.msgpack, with its record (.json)
    export_weights(spec, weights, params, record)
    if ship:
        shutil.copyfile(weights, spec.packaged)
        shutil.copyfile(weights.with_suffix(".json"), spec.packaged.with_suffix(".json"))
    print(f"trained {spec.name} {record['steps_done']} steps ({spec.label}) in {wall / 60:.1f} min on "
          f"{manifest['frames']['train']} frames; {spec.summary(results)}; weights: {weights}")
    return record


def _train_call(config: TrainConfig, data_dir: Path, out: Path) -> str:
    """The :func:`run_train` call that repeats this run, every training setting spelled out (not the model's data
    facts, which run_train sets from the dataset, nor the checkpoint path and the progress bar)."""
    model = config.model
    settings = ", ".join(f"{f.name}={getattr(model, f.name)!r}" for f in dataclasses.fields(model)
                         if f.name not in model.DATA_FIELDS)
    loop = ", ".join(f"{f.name}={getattr(config, f.name)!r}" for f in dataclasses.fields(TrainConfig)
                     if f.name not in ("model", "checkpoint_path", "progress"))
    return (f"pixelmpc_jax.learn.train.run_train({str(data_dir)!r}, {str(out)!r}, "
            f"TrainConfig(model={type(model).__name__}({settings}), {loop}))")


def _final_losses(history: dict) -> dict:
    """Per stage, the last logged step's deterministic loss on the training and held-out probes."""
    last = {stage: i for i, stage in enumerate(history["probe_stage"])}
    return {stage: {"step": history["probe_step"][i], "probe_loss": history["probe_loss"][i],
                    "test_probe_loss": history["test_probe_loss"][i]} for stage, i in last.items()}


def _weights_record(config: TrainConfig, spec: ModelSpec, data_dir: Path, out: Path, manifest: dict, train_data,
                    test_data, history: dict, wall: float) -> dict:
    """The provenance record shipped with the weights: config, model, data, losses, results, calls, versions."""
    return {
        "what": f"{spec.name} weights (parameters + normalisation), pixelmpc_jax.learn.train",
        "model": spec.name,
        "train_config": {**dataclasses.asdict(config), "checkpoint_path": None},
        **spec.describe(),
        # the camera the weights serve (the dataset's): a race checks it against its own (RaceSpec.check_weights)
        network_weights.CAMERA_TILT_KEY: float(config.model.camera_tilt_deg),
        "train_wall_s": wall,
        "steps_done": history["step"][-1] if history["step"] else 0,
        "interrupted": history["interrupted"],
        "data": {"dir": str(data_dir), "manifest_sha256": dataset_lib.file_sha256(data_dir / dataset_lib.MANIFEST),
                 "collect_config": manifest["config"], "policy": manifest.get("policy"),
                 "format_version": manifest.get("format_version"), "excited_laps": manifest.get("excited_laps", []),
                 "frames": manifest["frames"], "bytes": manifest.get("bytes"),
                 "laps": [{k: e[k] for k in ("lap", "split", "speed", "seed", "frames", "end", "gates_passed")}
                          for e in manifest["laps"]],
                 **spec.data_record(train_data, test_data)},
        "final_loss": _final_losses(history),
        "results": history.get("results", {}),
        "calls": [
            f"pixelmpc_jax.learn.collect.collect({str(data_dir)!r}, "
            f"CollectConfig(**{json.dumps(manifest['config'])}))",
            _train_call(config, data_dir, out),
        ],
        "command": platform_info.invocation(),
        "versions": manifest.get("versions", {}) | {"jax": jax.__version__, "optax": optax.__version__},
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
