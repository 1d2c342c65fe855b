"""DOF evaluation (Sec. III-D and Fig. 7 of the paper), the shipped weights, and the `pixelmpc evaluate` entry point.

* Flow accuracy: average endpoint error (AEE) in pixels per frame at 204 x 153 on held-out laps, against
  the Farneback flow (the training label; the paper reports 2.45) and against the exact flow (valid
  pixels only), next to two baselines: zero flow, and the mean flow field per orientation bin fitted on
  the TRAIN laps (:mod:`pixelmpc_jax.learn.aee`).
* Control gain: how much the flow at the image centre moves per rad/s of commanded body rate. A linear
  least-squares fit of the central patch's mean flow on ``[wx, wy, wz, thrust, 1]`` over the held-out
  frames, once for the Farneback labels and once for the DOF's prediction at the same frames: the DOF's
  slopes against the data's say whether the network learned what the controls do to the pixel (the only
  thing PixelMPC's pixel cost can act through), separately from its overall AEE.
* The multi-step pixel prediction (Fig. 7), the rotation response and the pixel-cost ranking of sampled
  control sequences: :mod:`pixelmpc_jax.learn.control_response`.
* The evaluation gives the network the input it was trained on (``dof.checkpoint_variant``): the command
  or the rates flown over the frame (AEE, control gain, multi-step prediction and rotation response alike);
  the pixel-cost ranking gives it the sampled controls, as PixelMPC does.
* Figures: a Fig. 2-like panel (image, exact, Farneback and DOF flow in colour) and the multi-step curve.
"""

from __future__ import annotations

import dataclasses
import datetime
import os
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from flax import serialization

from pixelmpc_jax import devices, strict_json, timing
from pixelmpc_jax.dynamics import dof, network_weights, vdof
from pixelmpc_jax.learn import collect as collect_lib
from pixelmpc_jax.learn import control_response, curves
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn.aee import OrientationBinBaseline, fit_orientation_bin_baseline, predict_flow_fields
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import policies
from pixelmpc_jax.world import render as render_lib

PAPER_AEE_PX = 2.45

# Evaluation without a dataset: laps flown with seeds that training never uses (training data starts at
# seed 0 and has fewer than 1000 laps). Lap 1 (10 m/s) is the test lap; laps 0 and 2 (6 and 14 m/s) only
# fit the orientation-bin baseline.
HELDOUT_CONFIG = collect_lib.CollectConfig(laps=3, seed=1000, max_lap_time_s=8.0, test_laps=(1,))
_EVAL_CHUNK_FRAMES = 8


# --------------------------------------------------------------------------------------------------
# Shipped weights.
# --------------------------------------------------------------------------------------------------


def shipped_weights_path() -> Path:
    """The packaged DOF weights file (``pixelmpc_jax/data/dof_weights.msgpack``)."""
    return dof.PACKAGED_WEIGHTS


def load_shipped_dof() -> dof.DOFParams:
    """The DOF parameters shipped with the package (weights + normalisation, no optimizer state)."""
    return dof.load_packaged_dof()


def shipped_dof_record() -> dict:
    """How the shipped weights were made (data, training config, calls, measured AEE): the checkpoint's config."""
    return dof.load_checkpoint(shipped_weights_path())[1]


# --------------------------------------------------------------------------------------------------
# Flow accuracy.
# --------------------------------------------------------------------------------------------------


def _epe(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a.astype(np.float32) - b.astype(np.float32)
    return np.hypot(d[..., 0], d[..., 1])


class _Mean:
    """Running mean in float64."""

    def __init__(self):
        self.total, self.count = 0.0, 0

    def add(self, values: np.ndarray) -> None:
        self.total += float(np.sum(values, dtype=np.float64))
        self.count += int(np.size(values))

    @property
    def value(self) -> float | None:
        return self.total / self.count if self.count else None


def flow_accuracy(dof_params: dof.DOFParams, laps: list[dataset_lib.Lap],
                  baseline: OrientationBinBaseline, dt: float = timing.CONTROL_DT,
                  chunk_frames: int = _EVAL_CHUNK_FRAMES, progress: bool = False, input: str = "command") -> dict:
    """AEE (pixels per frame) of the DOF and the baselines on ``laps``, against Farneback (every pixel)
    and against the exact flow (valid pixels, laps that store it). The network gets the control input
    ``input`` ("command" or "flown", :func:`dataset.control_input`); the control gain is fitted on it."""
    names = ("dof", "zero", "mean")
    patch_fb, patch_dof, controls = [], [], []
    vs_fb = {n: _Mean() for n in names}
    vs_exact = {n: _Mean() for n in (*names, "farneback")}
    total = sum(lap.q.shape[0] for lap in laps)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc="AEE", unit="frame", leave=False)
    for lap in laps:
        H, W = lap.flow.shape[1:3]
        patch = (slice(None), slice(3 * H // 8, 5 * H // 8), slice(3 * W // 8, 5 * W // 8))  # the central quarter
        bins = baseline.bin_index(lap.q)  # (F,)
        lap_u = dataset_lib.lap_input(lap, input)
        for start in range(0, lap.q.shape[0], chunk_frames):
            stop = min(start + chunk_frames, lap.q.shape[0])
            count = stop - start
            q, u = lap.q[start:stop], lap_u[start:stop]
            if count < chunk_frames:  # pad: one compiled shape
                q = np.concatenate([q, np.repeat(q[-1:], chunk_frames - count, 0)])
                u = np.concatenate([u, np.repeat(u[-1:], chunk_frames - count, 0)])
            pred = np.asarray(predict_flow_fields(dof_params, q, u, W, H, float(dt)))[:count]
            fb = lap.flow[start:stop].astype(np.float32)
            patch_fb.append(fb[patch].mean(axis=(1, 2)))
            patch_dof.append(pred[patch].mean(axis=(1, 2)))
            controls.append(lap_u[start:stop])
            mean_pred = baseline.mean_flow[bins[start:stop]]
            zero = np.zeros_like(fb)
            for name, p in (("dof", pred), ("zero", zero), ("mean", mean_pred)):
                vs_fb[name].add(_epe(p, fb))
            if lap.exact_flow is not None:
                exact = lap.exact_flow[start:stop].astype(np.float32)
                valid = lap.exact_valid[start:stop]
                for name, p in (("dof", pred), ("zero", zero), ("mean", mean_pred), ("farneback", fb)):
                    vs_exact[name].add(_epe(p, exact)[valid])
            if bar is not None:
                bar.update(count)
    if bar is not None:
        bar.close()
    return {
        "aee_px": vs_fb["dof"].value,
        "aee_exact_px": vs_exact["dof"].value,
        "baseline_zero_aee_px": vs_fb["zero"].value,
        "baseline_mean_aee_px": vs_fb["mean"].value,
        "baseline_zero_aee_exact_px": vs_exact["zero"].value,
        "baseline_mean_aee_exact_px": vs_exact["mean"].value,
        "farneback_vs_exact_aee_px": vs_exact["farneback"].value,
        "frames": total,
        "exact_valid_pixels": vs_exact["dof"].count,
        "control_gain": {**control_gain(np.concatenate(controls), np.concatenate(patch_fb),
                                        np.concatenate(patch_dof)), "input": input} if controls else None,
    }


def control_gain(u: np.ndarray, flow_data: np.ndarray, flow_dof: np.ndarray) -> dict:
    """Least-squares slopes (px per frame per rad/s) of the central flow on the body rates given to the DOF.

    Args:
        u: (F, 4) the DOF's control input ``[wx, wy, wz, thrust]`` (commanded, or the rates flown over the
            frame); flow_data, flow_dof: (F, 2) the central patch's mean flow (px/frame), Farneback and DOF.

    Returns:
        ``data`` and ``dof``: (2, 3) slopes, rows (du, dv), columns (wx, wy, wz); ``r2_data``: (2,) the share
        of the labels' variance the linear fit explains; ``yaw_to_u`` and ``pitch_to_v``: the dominant
        couplings as ``{"data", "dof", "ratio"}`` (ratio = DOF / data).
    """
    X = np.concatenate([u.astype(np.float64), np.ones((u.shape[0], 1))], axis=1)
    fit = lambda y: np.linalg.lstsq(X, y.astype(np.float64), rcond=None)[0]  # noqa: E731  (5, 2)
    data, net = fit(flow_data), fit(flow_dof)
    residual = flow_data - X @ data
    r2 = 1.0 - residual.var(axis=0) / np.maximum(flow_data.var(axis=0), 1e-12)

    def coupling(axis: int, rate: int) -> dict:
        d, n = float(data[rate, axis]), float(net[rate, axis])
        return {"data": d, "dof": n, "ratio": n / d if abs(d) > 1e-9 else None}

    return {"data": data[:3].T.tolist(), "dof": net[:3].T.tolist(), "r2_data": r2.tolist(),
            "yaw_to_u": coupling(0, 2), "pitch_to_v": coupling(1, 1)}


# --------------------------------------------------------------------------------------------------
# Figures.
# --------------------------------------------------------------------------------------------------


def _figure_frame(lap: dataset_lib.Lap) -> int:
    """A representative frame: mean Farneback magnitude nearest the lap's 75th percentile."""
    mags = np.array([np.hypot(*lap.flow[t].astype(np.float32).reshape(-1, 2).T).mean()
                     for t in range(lap.q.shape[0])])
    return int(np.argmin(np.abs(mags - np.percentile(mags, 75))))


def plot_flow_fields(path, rgb, exact, valid, farneback, predicted, title: str = "") -> None:
    """Fig. 2-like: the image, the exact, Farneback and DOF flow in colour (one scale), and the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    exact = np.where(valid[..., None], exact, 0.0) if valid is not None else exact
    reference = exact if exact is not None else farneback
    vmax = float(np.percentile(np.hypot(reference[..., 0], reference[..., 1]), 99)) or 1.0
    panels = [("image", rgb)]
    if exact is not None:
        panels.append(("exact flow", flow_lib.flow_to_rgb(exact, vmax)))
    panels += [("Farneback flow (label)", flow_lib.flow_to_rgb(farneback, vmax)),
               ("DOF prediction", flow_lib.flow_to_rgb(predicted, vmax))]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(3.2 * len(panels) + 1.6, 2.8),
                             gridspec_kw={"width_ratios": [1] * len(panels) + [0.5]})
    for ax, (name, image) in zip(axes, panels):
        ax.imshow(image)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    axes[-1].imshow(flow_lib.colour_wheel())
    axes[-1].set_title(f"legend\n(rim {vmax:.1f} px)", fontsize=8)
    axes[-1].axis("off")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


PART_LABELS = {"dof_rate_response": "the DOF's response to the rates alone",
               "exact_rotation": "exact rotational flow alone",
               "exact_rotation_dof_rest": "exact rotation + the DOF's flow at zero rate"}


def plot_multistep(path, multistep: dict, title: str = "", parts: dict | None = None) -> None:
    """Fig. 7 (right): mean +- std pixel error of the multi-step prediction vs the horizon step; ``parts``:
    ``{part: mean_px list}`` of the pixel models of :data:`control_response.PIXEL_MODEL_PARTS`, drawn beside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.asarray(multistep["steps"])

    def arr(key):
        return np.asarray([np.nan if v is None else v for v in multistep[key]], float)

    mean, std, zero = arr("mean_px"), arr("std_px"), arr("zero_motion_mean_px")
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, mean, "C0-", label="DOF (Euler, logged q, u)")
    ax.fill_between(steps, mean - std, mean + std, color="C0", alpha=0.25, label="+- 1 std")
    ax.plot(steps, zero, "C3--", lw=1, label="pixel held still")
    for colour, (part, values) in zip(("C1", "C2", "C4"), (parts or {}).items()):
        ax.plot(steps[:len(values)], [np.nan if v is None else v for v in values], f"{colour}-", lw=1,
                label=PART_LABELS.get(part, part))
    curves.finish_multistep_plot(fig, ax, multistep['dt_s'], title, path)


# --------------------------------------------------------------------------------------------------
# The evaluation.
# --------------------------------------------------------------------------------------------------


def default_cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pixelmpc_jax"


def heldout_dataset(cache_dir=None, config: collect_lib.CollectConfig = HELDOUT_CONFIG, progress: bool = True,
                    policy: policies.Policy | None = None) -> Path:
    """Collect (or reuse) the seeded held-out set in the cache; returns its directory (one per camera tilt)."""
    tag = f"dof_heldout_seed{config.seed}_laps{config.laps}_t{config.max_lap_time_s:g}_ss{config.supersample}"
    tag += f"_tilt{config.camera_tilt_deg:g}" if config.camera_tilt_deg else ""  # (the untilted set's name as before)
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir() / tag
    collect_lib.collect(root, config, progress=progress, policy=policy)
    return root


def evaluate(dof_params: dof.DOFParams | None = None, data_dir=None, out_dir="runs/dof_eval", *, horizon: int = 80,
             bins_per_angle: int = 4, cache_dir=None, heldout_config: collect_lib.CollectConfig = HELDOUT_CONFIG,
             figures: bool = True, progress: bool = True, input: str | None = None,
             rank_samples: int = control_response.RANK_SAMPLES,
             rank_stride: int = control_response.RANK_STRIDE) -> dict:
    """Evaluate DOF parameters on a dataset's test laps and write ``out_dir/dof_eval.json`` and the figures.

    Args:
        dof_params: the parameters (default: the shipped weights).
        data_dir: a collected dataset (its test laps are evaluated, its train laps fit the orientation-bin
            baseline). ``None``: a small seeded held-out set (``heldout_config``, seeds >= 1000, never used
            for training) is collected into ``cache_dir`` (default ``~/.cache/pixelmpc_jax/...``) or reused.
        out_dir: where ``dof_eval.json``, ``dof_flow_fields.png`` and ``dof_multistep.png`` go.
        horizon: steps of the multi-step prediction (the paper: 80).
        bins_per_angle: orientation bins per Euler angle of the mean-flow baseline.
        input: the network's control input, "command" or "flown" (``None``: the shipped weights' variant
            when ``dof_params`` is None, else "command"; :func:`run_evaluate` reads it from the weights file).
        rank_samples, rank_stride: sampled sequences per state and the tick stride of the states of the
            pixel-cost ranking.

    Returns:
        The dict written to ``dof_eval.json``: ``num_parameters``, ``aee_px`` (vs Farneback),
        ``aee_exact_px``, ``baseline_zero_aee_px``, ``baseline_mean_aee_px``, the baselines against the
        exact flow, ``farneback_vs_exact_aee_px``, ``multistep`` (per-step mean/std/count),
        ``rotation_response``, ``pixel_cost_rank_correlation``, ``dof_input`` and where the data came from.
    """
    t0 = time.perf_counter()
    if input is None:
        input = dof.checkpoint_variant(shipped_dof_record())["input"] if dof_params is None else "command"
    if input not in dataset_lib.INPUTS:
        raise ValueError(f"input must be one of {dataset_lib.INPUTS}, got {input!r}")
    dof_params = load_shipped_dof() if dof_params is None else dof_params
    if data_dir is None:
        data_dir = heldout_dataset(cache_dir, heldout_config, progress=progress)
    data_dir = Path(data_dir)
    manifest = dataset_lib.read_manifest(data_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    train_data = dataset_lib.load_dataset(data_dir, "train")
    baseline = fit_orientation_bin_baseline(train_data.q, train_data.u, train_data.flow, bins_per_angle)
    del train_data
    laps, world = dataset_lib.load_test_laps(data_dir, manifest)
    dt = float(manifest["frame_dt_s"])
    accuracy = flow_accuracy(dof_params, laps, baseline, dt, progress=progress, input=input)
    multistep = _multistep_results(dof_params, laps, world, horizon, dt, input)
    rotation = control_response.rotation_response(
        dof_params, np.concatenate([lap.q for lap in laps]),
        np.concatenate([dataset_lib.lap_input(lap, input) for lap in laps]), world.camera, dt)
    ranking = control_response.pixel_cost_rank_correlation(dof_params, laps, world.track, world.camera,
                                                           num_samples=rank_samples, stride=rank_stride,
                                                           progress=progress)

    results = {
        "num_parameters": network_weights.num_trainable_params(dof_params),
        "dof_input": input,
        **accuracy,
        "rotation_response": rotation,
        "pixel_cost_rank_correlation": ranking,
        "paper_aee_px": PAPER_AEE_PX,
        "image_size_wh": list(manifest["image_size_wh"]),
        "units": "pixels per frame (1/40 s) at the image size; multistep: pixels",
        **multistep,
        "data": dataset_lib.data_record(data_dir, manifest),
        "baseline_bins_per_angle": bins_per_angle,
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    if figures:
        results.update(_write_figures(out, dof_params, laps[0], world, manifest, input, multistep["multistep"],
                                      multistep["multistep_parts"]["mean_px"]))
    results["wall_s"] = time.perf_counter() - t0
    results = strict_json.json_safe(results)
    strict_json.write_json_atomic(out / "dof_eval.json", results)
    return results


def _multistep_results(dof_params: dof.DOFParams, laps: list[dataset_lib.Lap], world: env_lib.World,
                       horizon: int, dt: float, input: str) -> dict:
    """The multi-step pixel prediction (Fig. 7): ``multistep`` (per step), ``multistep_at`` (at steps 1, 10, 20, 40, 80)
    and ``multistep_parts`` (the same prediction with parts of the pixel model swapped)."""
    multistep = control_response.multistep_error(dof_params, laps, world.track, world.camera, horizon, dt, input=input)
    parts = {part: control_response.multistep_error(dof_params, laps, world.track, world.camera, horizon, dt,
                                                    input=input, part=part)["mean_px"]
             for part in control_response.PIXEL_MODEL_PARTS if part != "dof"}
    return {
        "multistep": multistep,
        "multistep_at": {str(k): {"mean_px": multistep["mean_px"][k - 1], "std_px": multistep["std_px"][k - 1],
                                  "count": multistep["count"][k - 1]} for k in (1, 10, 20, 40, 80) if k <= horizon},
        # the same prediction with parts of the pixel model swapped: which part holds the DOF back
        "multistep_parts": {"mean_px": parts,
                            "at": {part: {str(k): v[k - 1] for k in (10, 20, 40, 80) if k <= horizon}
                                   for part, v in parts.items()}},
    }


def _write_figures(out: Path, dof_params: dof.DOFParams, lap: dataset_lib.Lap, world: env_lib.World,
                   manifest: dict, input: str, multistep: dict, parts: dict) -> dict:
    """Fig. 2-like flow fields of a representative frame of ``lap`` and the multi-step curve into ``out``;
    returns their record (``figures``, ``figure_frame``)."""
    W, H = manifest["image_size_wh"]
    dt = float(manifest["frame_dt_s"])
    t = _figure_frame(lap)
    frame = devices.compiled(render_lib.render, ("supersample",))(
        world.track, jnp.asarray(lap.states[t]), world.camera, supersample=int(manifest["config"]["supersample"]))
    lap_u = dataset_lib.lap_input(lap, input)
    predicted = np.asarray(predict_flow_fields(dof_params, lap.q[t:t + 1], lap_u[t:t + 1], W, H, dt))[0]
    exact = None if lap.exact_flow is None else lap.exact_flow[t].astype(np.float32)
    valid = None if lap.exact_valid is None else lap.exact_valid[t]
    speed = float(np.linalg.norm(lap.states[t, 7:10]))
    plot_flow_fields(out / "dof_flow_fields.png", np.asarray(frame.rgb), exact, valid,
                     lap.flow[t].astype(np.float32), predicted,
                     title=f"test lap {lap.info.get('lap')} frame {t}, {speed:.1f} m/s")
    plot_multistep(out / "dof_multistep.png", multistep,
                   title=f"multi-step gate-centre prediction, {multistep['starts']} starts", parts=parts)
    return {"figures": ["dof_flow_fields.png", "dof_multistep.png"],
            "figure_frame": {"lap": lap.info.get("lap"), "frame": t}}


def summarise(results: dict) -> str:
    def fmt(v):
        return "-" if v is None else f"{v:.2f}"

    ms = results.get("multistep_at", {})
    steps = "  ".join(f"{k}: {fmt(v['mean_px'])}+-{fmt(v['std_px'])} px (n={v['count']})" for k, v in ms.items())
    rot, rank = results.get("rotation_response"), results.get("pixel_cost_rank_correlation")
    extra = []
    if rot:
        yaw, pitch = rot["yaw_to_u"], rot["pitch_to_v"]
        extra.append("  rotation response at the image centre, px/frame per rad/s (DOF / exact = ratio): yaw -> u "
                     f"{fmt(yaw['dof'])} / {fmt(yaw['exact'])} = {fmt(yaw['ratio'])}, pitch -> v "
                     f"{fmt(pitch['dof'])} / {fmt(pitch['exact'])} = {fmt(pitch['ratio'])}")
    parts = (results.get("multistep_parts") or {}).get("at", {})
    if parts:
        extra.append("  40-step error with parts of the pixel model swapped: " + ", ".join(
            f"{PART_LABELS.get(part, part)} {fmt(at.get('40'))} px" for part, at in parts.items()))
    if rank:
        extra.append(f"  pixel-cost rank correlation with the exact projection ({rank['samples']} samples, "
                     f"{rank['steps']} steps, {rank['states']} states): median {fmt(rank['median'])} "
                     f"(quartiles {fmt(rank['q25'])}, {fmt(rank['q75'])})")
    return "\n".join([
        f"DOF ({results['num_parameters']} parameters, {results.get('dof_input', 'command')} input) on "
        f"{results['frames']} held-out frames:",
        f"  AEE vs Farneback {fmt(results['aee_px'])} px/frame (paper {PAPER_AEE_PX}); vs exact flow "
        f"{fmt(results['aee_exact_px'])} (Farneback itself vs exact {fmt(results['farneback_vs_exact_aee_px'])})",
        f"  baselines vs Farneback: zero flow {fmt(results['baseline_zero_aee_px'])}, orientation-bin mean "
        f"{fmt(results['baseline_mean_aee_px'])}",
        f"  multi-step gate-centre error: {steps}",
    ] + ([] if not results.get("control_gain") else [
        "  control gain at the image centre, px/frame per rad/s (DOF / data): yaw -> u "
        f"{fmt(results['control_gain']['yaw_to_u']['dof'])} / {fmt(results['control_gain']['yaw_to_u']['data'])}, "
        f"pitch -> v {fmt(results['control_gain']['pitch_to_v']['dof'])} / "
        f"{fmt(results['control_gain']['pitch_to_v']['data'])}"]) + extra)


# --------------------------------------------------------------------------------------------------
# The `pixelmpc evaluate` entry point.
# --------------------------------------------------------------------------------------------------


def read_weights(path) -> tuple[str, dof.DOFParams | vdof.VDOFParams, dict]:
    """``(kind, params, record)`` of a DOF (kind "dof", ``dof.load_checkpoint``) or vdof (kind "vdof",
    ``vdof.load_vdof``) weights file, dispatched once on the file's format; ``ValueError`` (one line, the DOF
    reader's) for a file that is neither."""
    path = Path(path)
    if _checkpoint_format(path) == vdof.CHECKPOINT_FORMAT:
        return ("vdof", *vdof.load_vdof(path))
    return ("dof", *dof.load_checkpoint(path))


def _checkpoint_format(path: Path) -> str | None:
    """The ``format`` a msgpack checkpoint names, or None for a file that is not one."""
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except Exception:  # msgpack raises several unrelated types on bad bytes; the reader names what is wrong
        return None
    return payload.get("format") if isinstance(payload, dict) else None


def run_evaluate(weights=None, data_dir=None, out_dir="runs/dof_eval", horizon: int = 80,
                 progress: bool = True) -> dict:
    """Evaluate a weights file (default: the shipped DOF) and print a short summary. A DOF file: see
    :func:`evaluate`; the network is given the input its record names (``dof.checkpoint_variant``: command or
    flown). A vdof file: :func:`vdof_eval.evaluate_vdof` (the same figures, beside the packaged "turned" DOF on
    the same frames). Either writes ``out_dir/dof_eval.json``. Without ``data_dir`` the held-out set is seen through
    the camera the weights' record states (``network_weights.trained_camera_tilt_deg``); a dataset is seen through
    its own camera, whatever the weights were trained for."""
    kind, params, record = read_weights(shipped_weights_path() if weights is None else weights)
    heldout = dataclasses.replace(HELDOUT_CONFIG, camera_tilt_deg=network_weights.trained_camera_tilt_deg(record))
    if kind == "vdof":
        from pixelmpc_jax.learn import vdof_eval  # it builds on this module's data loading

        if data_dir is None:
            data_dir = heldout_dataset(config=heldout, progress=progress)
        results = vdof_eval.evaluate_vdof(params, record, data_dir, out_dir, horizon=horizon, progress=progress)
        print(vdof_eval.summarise(results))
    else:
        variant = dof.checkpoint_variant(record)
        results = evaluate(params, data_dir, out_dir, horizon=horizon, progress=progress, input=variant["input"],
                           heldout_config=heldout)
        print(summarise(results))
    print(f"wrote {Path(out_dir) / 'dof_eval.json'}")
    return results
