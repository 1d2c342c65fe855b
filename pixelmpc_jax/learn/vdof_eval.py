"""`pixelmpc evaluate` of a vdof checkpoint: the DOF evaluation's figures for the velocity-and-depth DOF
(:mod:`pixelmpc_jax.dynamics.vdof`), beside a packaged DOF (default "turned") on the same held-out frames.

Each figure is computed as :mod:`pixelmpc_jax.learn.evaluate` computes it for the DOF, for both models on the
dataset's test laps (the same windows, frames, states and samples):

* ``multistep`` / ``multistep_at``: the gate-centre error k steps ahead (Fig. 7;
  :func:`control_response.multistep_windows`): vdof rolled from the detected pixel state ``[centre, s]`` with
  the logged states and the flown rates, the DOF from the detected centre with its weights' input; and
  ``box_size_rel_err_at``: vdof's box size ``s`` against the detected one, relative, on the same windows.
* ``rotation_response``: the response of the image motion to yaw (u) and pitch (v) at the image centre over
  the exact pinhole rotational flow there (:func:`control_response.rotation_response`). vdof's
  ``uv_dot = s A(uv) v_b + B(uv) w`` is linear in the rates, so its Jacobian is ``B`` at the pixel, whatever
  the velocity and the box size.
* ``pixel_cost_rank_correlation``: the Spearman correlation of PixelMPC's pixel cost of sampled control sequences
  with the model's pixel and with the exact projection (:func:`control_response.pixel_cost_rank_correlation`,
  the DOF evaluation's settings).
* ``target_aee_px``: the one-step error (px/frame at the camera's size) of the target pixel's motion against the
  detector's frame-to-frame motion of the target centre (vdof's training label, ``vdof_data.lap_rows``' rows).

Not reported: the flow-field AEE (vdof predicts the target's pixel state, not a flow field) and the in-view
fraction of the gate's corners (vdof predicts the centre and the box size, not the corners: that needs a corner
model).
"""

from __future__ import annotations

import datetime
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import strict_json
from pixelmpc_jax.dynamics import dof, network_weights, quadrotor, vdof
from pixelmpc_jax.learn import control_response, curves, vdof_data
from pixelmpc_jax.learn import dataset as dataset_lib

COMPARISON_DOF = "turned"
MULTISTEP_AT = (1, 10, 20, 40, 80)
VDOF_INPUT = "flown"  # vdof is trained on, and given, the rates flown over the frame
NOT_REPORTED = {
    "aee_px": "the flow-field AEE: vdof predicts the target's pixel state, not a flow field",
    "in_view_fraction_error": "vdof predicts the gate's centre and box size, not its four corners: the fraction "
                              "of predicted corners in view needs a corner model",
}


# --------------------------------------------------------------------------------------------------
# The figures.
# --------------------------------------------------------------------------------------------------



def _shown_path(path) -> str:
    """A weights file as a report shows it: a file shipped in the package by its place in the package (no path of
    the machine that ran it), any other as given."""
    path, package = Path(path).resolve(), Path(__file__).resolve().parents[1]
    return f"pixelmpc_jax/{path.relative_to(package).as_posix()}" if path.is_relative_to(package) else str(path)

def _vdof_image_velocity(params: vdof.VDOFParams, q: jax.Array, uv: jax.Array, u: jax.Array) -> jax.Array:
    """(2,) vdof's image motion at the pixel ``uv`` for attitude ``q`` at rest with a zero box size: its response
    to the rates ``u[:3]`` (``B(uv)``), which is the same at any velocity and box size, in the DOF's signature
    (``control_response.rotation_response``'s ``velocity_fn``)."""
    x = jnp.zeros(quadrotor.STATE_DIM, uv.dtype).at[quadrotor.QUAT].set(q)
    return vdof.pixel_state_velocity(params, x, jnp.concatenate([uv, jnp.zeros(1, uv.dtype)]), u)[:2]


@jax.jit
def _one_step_motion(vdof_params, dof_params, x, p, u_vdof, u_dof, dt):
    """(R, 3) vdof's and (R, 2) the DOF's predicted one-frame motion of the target's pixel state at R rows."""
    v = jax.vmap(vdof.pixel_state_velocity, in_axes=(None, 0, 0, 0))(vdof_params, x, p, u_vdof)
    d = jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0))(dof_params, x[:, quadrotor.QUAT], p[:, :2], u_dof)
    return dt * v, dt * d


def target_one_step_errors(vdof_params, dof_params, laps: list[dataset_lib.Lap], track, camera, dt: float,
                           box_cue: str = "apparent", dof_input: str = "flown") -> dict:
    """The one-step error of the target pixel's motion (px/frame at the camera's size) against the detector's
    motion of the target centre between consecutive frames, on vdof's label rows (every frame whose target gate
    is detected at it and at the next, ``vdof_data.lap_rows``): vdof given the flown rates, the DOF its
    ``dof_input``; with the error of a still pixel and vdof's one-step box-size relative error."""
    scale = np.asarray([camera.width, camera.height], np.float64)
    err_vdof, err_dof, still, box = [], [], [], []
    for lap in laps:
        p, found, _ = (np.asarray(a) for a in vdof_data.lap_detections(
            track, camera, jnp.asarray(lap.states), jnp.asarray(lap.target), box_cue))
        rows = np.nonzero(found[:-1] & found[1:] & (lap.target[:-1] == lap.target[1:]))[0]  # lap_rows' rows
        step_vdof, step_dof = (np.asarray(a, np.float64) for a in _one_step_motion(
            vdof_params, dof_params, jnp.asarray(lap.states[rows]), jnp.asarray(p[rows]),
            jnp.asarray(dataset_lib.lap_input(lap, VDOF_INPUT)[rows]),
            jnp.asarray(dataset_lib.lap_input(lap, dof_input)[rows]), float(dt)))
        motion = p[rows + 1].astype(np.float64) - p[rows]  # (R, 3): the label times dt
        err_vdof.append(np.linalg.norm((step_vdof[:, :2] - motion[:, :2]) * scale, axis=-1))
        err_dof.append(np.linalg.norm((step_dof - motion[:, :2]) * scale, axis=-1))
        still.append(np.linalg.norm(motion[:, :2] * scale, axis=-1))
        box.append(np.abs(step_vdof[:, 2] - motion[:, 2]) / np.maximum(p[rows + 1, 2], 1e-6))
    err_vdof, err_dof, still, box = (np.concatenate(a) for a in (err_vdof, err_dof, still, box))

    def mean(values):
        return float(values.mean()) if values.size else None

    return {"vdof_px": mean(err_vdof), "vdof_median_px": float(np.median(err_vdof)) if err_vdof.size else None,
            "dof_px": mean(err_dof), "dof_median_px": float(np.median(err_dof)) if err_dof.size else None,
            "still_px": mean(still), "vdof_box_rel_err": mean(box), "rows": int(err_vdof.size),
            "dof_input": dof_input, "definition": "|predicted - detected| one-frame motion of the target centre, "
            "px/frame, over frames whose target gate is detected at t and t+1 (vdof's label rows)"}


def _at(summary: dict, steps) -> dict:
    """``multistep_at``: the summary's mean, std and count at each of ``steps`` it reaches."""
    return {str(k): {"mean_px": summary["mean_px"][k - 1], "std_px": summary["std_px"][k - 1],
                     "count": summary["count"][k - 1]} for k in steps if k <= len(summary["steps"])}


def multistep_window_errors(vdof_params, dof_params, laps: list[dataset_lib.Lap], track, camera, horizon: int,
                            dt: float, box_cue: str = "apparent", dof_input: str = "flown") -> dict:
    """The multi-step prediction of vdof and the DOF on the same windows, defined as the DOF evaluation defines
    them (:func:`control_response.multistep_windows`: every start tick whose target gate is detected with its
    centre in the image, counted up to k while it stays so): vdof rolled from the detected ``[centre, s]`` with
    the flown rates, the DOF from the centre with its input ``dof_input``. Per start (rows) and k = 1..horizon:
    ``vdof`` and ``dof`` (the windows' arrays), ``box_rel`` (vdof's box size relative error), ``valid``."""
    model = control_response.pixel_state_model("vdof", box_cue)
    w_vdof = control_response.multistep_windows(model, vdof_params, laps, track, camera, horizon, dt, VDOF_INPUT)
    w_dof = control_response.multistep_windows(control_response.pixel_state_model("dof"), dof_params, laps, track,
                                               camera, horizon, dt, dof_input)
    pred, truth = w_vdof["pred"][..., 2], w_vdof["truth"][..., 2]
    return {"vdof": w_vdof, "dof": w_dof, "valid": w_vdof["valid"],
            "box_rel": np.abs(pred - truth) / np.maximum(truth, 1e-6)}


def multistep_figures(vdof_params, dof_params, laps: list[dataset_lib.Lap], track, camera, horizon: int, dt: float,
                      box_cue: str, dof_input: str) -> dict:
    """The multi-step prediction of vdof and the DOF on the same windows (:func:`multistep_window_errors`)
    as the DOF evaluation reports it (``multistep``, ``multistep_at``) per model, and vdof's box-size relative
    error at the ``multistep_at`` steps (``box_size_rel_err_at``: mean, median, count)."""
    windows = multistep_window_errors(vdof_params, dof_params, laps, track, camera, horizon, dt, box_cue, dof_input)
    out = {}
    for name, model_input in (("vdof", VDOF_INPUT), ("dof", dof_input)):
        w = windows[name]
        summary = {**control_response.multistep_summary(w["err"], w["err_zero"], w["valid"], dt),
                   "input": model_input, "model": name}
        out[name] = {"multistep": summary, "multistep_at": _at(summary, MULTISTEP_AT)}
    valid, box_rel = windows["valid"], windows["box_rel"]
    out["box_size_rel_err_at"] = {
        str(k): {"mean": float(box_rel[valid[:, k - 1], k - 1].mean()) if valid[:, k - 1].any() else None,
                 "median": float(np.median(box_rel[valid[:, k - 1], k - 1])) if valid[:, k - 1].any() else None,
                 "count": int(valid[:, k - 1].sum())} for k in MULTISTEP_AT if k <= horizon}
    return out


# --------------------------------------------------------------------------------------------------
# The evaluation.
# --------------------------------------------------------------------------------------------------


def evaluate_vdof(vdof_params: vdof.VDOFParams, record: dict, data_dir, out_dir, *, horizon: int = 80,
                  dof_variant: str = COMPARISON_DOF, figures: bool = True, progress: bool = True,
                  rank_samples: int = control_response.RANK_SAMPLES,
                  rank_stride: int = control_response.RANK_STRIDE) -> dict:
    """Evaluate vdof weights (``record``: their checkpoint's, which says the box cue) on a dataset's test laps,
    beside the packaged DOF ``dof_variant`` on the same frames, and write ``out_dir/dof_eval.json`` (and
    ``vdof_multistep.png``). Returns the dict written; see the module docstring for its figures."""
    t0 = time.perf_counter()
    data_dir, out = Path(data_dir), Path(out_dir)
    manifest = dataset_lib.read_manifest(data_dir)
    out.mkdir(parents=True, exist_ok=True)
    laps, world = dataset_lib.load_test_laps(data_dir, manifest, with_flow=False)
    track, camera, dt = world.track, world.camera, float(manifest["frame_dt_s"])
    box_cue = vdof.box_cue_of(record)
    dof_path = dof.PACKAGED_VARIANTS[dof_variant]
    dof_params, dof_record = dof.load_checkpoint(dof_path)
    dof_input = dof.checkpoint_variant(dof_record)["input"]
    q = np.concatenate([lap.q for lap in laps])

    multistep = multistep_figures(vdof_params, dof_params, laps, track, camera, horizon, dt, box_cue, dof_input)
    one_step = target_one_step_errors(vdof_params, dof_params, laps, track, camera, dt, box_cue, dof_input)
    rotation = {name: control_response.rotation_response(
        params, q, np.concatenate([dataset_lib.lap_input(lap, model_input) for lap in laps]), camera, dt,
        velocity_fn=velocity_fn, name=name)
        for name, params, model_input, velocity_fn in (("vdof", vdof_params, VDOF_INPUT, _vdof_image_velocity),
                                                       ("dof", dof_params, dof_input, None))}
    ranking = {name: control_response.pixel_cost_rank_correlation(
        params, laps, track, camera, num_samples=rank_samples, stride=rank_stride, progress=progress,
        pixel_model=name, box_cue=box_cue) for name, params in (("vdof", vdof_params), ("dof", dof_params))}

    results = {
        "model": "vdof",
        "num_parameters": network_weights.num_trainable_params(vdof_params),
        "hidden_sizes": list(vdof.hidden_sizes_of(vdof_params.weights)),
        "vdof_input": VDOF_INPUT,
        "box_cue": box_cue,
        "target_aee_px": one_step["vdof_px"],
        "target_one_step": one_step,
        **multistep["vdof"],
        "box_size_rel_err_at": multistep["box_size_rel_err_at"],
        "rotation_response": rotation["vdof"],
        "pixel_cost_rank_correlation": ranking["vdof"],
        "comparison_dof": {"variant": dof_variant, "weights": _shown_path(dof_path), "dof_input": dof_input,
                           "num_parameters": network_weights.num_trainable_params(dof_params),
                           "target_aee_px": one_step["dof_px"], **multistep["dof"],
                           "rotation_response": rotation["dof"], "pixel_cost_rank_correlation": ranking["dof"]},
        "not_reported": NOT_REPORTED,
        "image_size_wh": list(manifest["image_size_wh"]),
        # the camera the weights were trained for; the data's, which the figures see through, is data.camera_tilt_deg
        "trained_camera_tilt_deg": network_weights.trained_camera_tilt_deg(record),
        "units": "pixels at the image size; target_aee_px: pixels per frame (1/40 s)",
        "data": dataset_lib.data_record(data_dir, manifest),
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    if figures:
        plot_multistep(out / "vdof_multistep.png", results["multistep"], results["comparison_dof"]["multistep"],
                       title=f"gate-centre prediction, vdof vs the {dof_variant} DOF, same windows")
        results["figures"] = ["vdof_multistep.png"]
    results["wall_s"] = time.perf_counter() - t0
    results = strict_json.json_safe(results)
    strict_json.write_json_atomic(out / "dof_eval.json", results)
    return results


def plot_multistep(path, vdof_multistep: dict, dof_multistep: dict, title: str = "") -> None:
    """Mean +- std gate-centre error of vdof, the DOF's mean and the still pixel's, against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def arr(multistep, key):
        return np.asarray([np.nan if v is None else v for v in multistep[key]], float)

    steps = np.asarray(vdof_multistep["steps"])
    mean, std = arr(vdof_multistep, "mean_px"), arr(vdof_multistep, "std_px")
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, mean, "C0-", label="vdof (Euler, logged x, flown rates)")
    ax.fill_between(steps, mean - std, mean + std, color="C0", alpha=0.25, label="+- 1 std")
    ax.plot(steps, arr(dof_multistep, "mean_px"), "C1-", label=f"DOF ({dof_multistep['input']} input)")
    ax.plot(steps, arr(vdof_multistep, "zero_motion_mean_px"), "C3--", lw=1, label="pixel held still")
    curves.finish_multistep_plot(fig, ax, vdof_multistep['dt_s'], title, path)


def summarise(results: dict) -> str:
    """A few lines: the figures of vdof and of the DOF beside it."""
    def fmt(v):
        return "-" if v is None else f"{v:.2f}"

    dof_ = results["comparison_dof"]
    lines = [f"vdof ({results['num_parameters']} parameters, {results['box_cue']} box) and the {dof_['variant']} DOF "
             f"({dof_['dof_input']} input) on the same held-out frames:",
             f"  target-pixel one-step error (AEE, px/frame, {results['target_one_step']['rows']} rows): vdof "
             f"{fmt(results['target_aee_px'])}, DOF {fmt(dof_['target_aee_px'])}, still "
             f"{fmt(results['target_one_step']['still_px'])}",
             "  multi-step gate-centre error, mean px (windows): " + ", ".join(
                 f"{k}: vdof {fmt(v['mean_px'])} / DOF {fmt(dof_['multistep_at'][k]['mean_px'])} ({v['count']})"
                 for k, v in results["multistep_at"].items()),
             "  vdof box size relative error: " + ", ".join(
                 f"{k}: {fmt(v['mean'])}" for k, v in results["box_size_rel_err_at"].items())]
    for name, key in (("vdof", "vdof"), ("DOF", "dof")):
        rot = (results if key == "vdof" else dof_)["rotation_response"]
        rank = (results if key == "vdof" else dof_)["pixel_cost_rank_correlation"]
        lines.append(f"  {name}: rotation response / exact: yaw -> u {fmt(rot['yaw_to_u']['ratio'])}, pitch -> v "
                     f"{fmt(rot['pitch_to_v']['ratio'])}; pixel-cost rank correlation median {fmt(rank['median'])} "
                     f"(quartiles {fmt(rank['q25'])}, {fmt(rank['q75'])}; {rank['states']} states)")
    return "\n".join(lines)
