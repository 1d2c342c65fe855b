"""DOF evaluation (Sec. III-D and Fig. 7 of the paper), the shipped weights, and the train/evaluate entry points.

* Flow accuracy: average endpoint error (AEE) in pixels per frame at 204 x 153 on held-out laps, against
  the Farneback flow (the training label; the paper reports 2.45) and against the exact flow (valid
  pixels only), next to two baselines: zero flow, and the mean flow field per orientation bin fitted on
  the TRAIN laps (``train.fit_orientation_bin_baseline``).
* Multi-step pixel prediction (Fig. 7): the target gate's centre (``detect_from_geometry`` along the
  logged trajectory) is predicted ``k = 1..K`` steps ahead by integrating the DOF pixel dynamics with the
  logged orientation and control, as PixelMPC does, ``uv_{k+1} = uv_k + dt * pixel_velocity(q_k, uv_k,
  u_k)``, and compared with where the gate centre really projects. Each start tick where the gate is
  detected with its centre in the image starts one prediction; step ``k`` counts while the true centre
  has stayed in the image and the gate detected on every tick up to ``k``.
* Control gain: how much the flow at the image centre moves per rad/s of commanded body rate. A linear
  least-squares fit of the central patch's mean flow on ``[wx, wy, wz, thrust, 1]`` over the held-out
  frames, once for the Farneback labels and once for the DOF's prediction at the same frames: the DOF's
  slopes against the data's say whether the network learned what the controls do to the pixel (the only
  thing PixelMPC's pixel cost can act through), separately from its overall AEE.
* Rotation response (``rotation_response``): the DOF's mean Jacobian at the image centre, px/frame per rad/s
  of the rate given to it (``jax.jacfwd`` over the held-out frames' orientation and input), against the
  exact rotational flow of the pinhole camera per rad/s (``fx dt`` of yaw on u, ``-fy dt`` of pitch on v at
  the images' size), and their ratio: 1 is a pixel model that moves the pixel the way the rates do.
* Pixel-cost ranking (``pixel_cost_rank_correlation``): at logged states of the test laps where the target
  is detected, 512 control sequences are sampled as PixelMPC's MPPI samples them (its noise and bounds,
  around the logged commands as the plan), rolled out with the MPC's robot model over ``t_f = 1 s`` (40
  steps), and costed with PixelMPC's pixel cost twice: the pixel from the DOF dynamics and from the exact
  projection of the target. The Spearman correlation of the two costs over the samples says whether the
  DOF ranks the samples as the true pixel would (what MPPI's weights depend on); median and quartiles
  over the states.
* The evaluation gives the network the input it was trained on (``dof.checkpoint_variant``): the command
  or the rates flown over the frame (AEE, control gain, multi-step prediction and rotation response alike);
  the pixel-cost ranking gives it the sampled controls, as PixelMPC does.
* Figures: a Fig. 2-like panel (image, exact, Farneback and DOF flow in colour) and the multi-step curve.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import os
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import strict_json
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.mppi import BatchCost, coloured_noise_filter, rollout_costs
from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn import dataset as dataset_lib
from pixelmpc_jax.learn import train as train_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import render as render_lib

PAPER_AEE_PX = 2.45
SHIPPED_WEIGHTS = "dof_weights.msgpack"
SHIPPED_RECORD = "dof_weights.json"
# Evaluation without a dataset: laps flown with seeds that training never uses (training data starts at
# seed 0 and has fewer than 1000 laps). Lap 1 (10 m/s) is the test lap; laps 0 and 2 (6 and 14 m/s) only
# fit the orientation-bin baseline.
HELDOUT_CONFIG = dataset_lib.CollectConfig(laps=3, seed=1000, max_lap_time_s=8.0, test_laps=(1,))
_EVAL_CHUNK_FRAMES = 8
IMAGE_CENTRE_UV = (0.5, 0.5)
RANK_SAMPLES = 512
RANK_T_F = 1.0
RANK_STRIDE = 5


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


def export_weights(path, dof_params: dof.DOFParams, record: dict) -> None:
    """Weights-only checkpoint (parameters + normalisation, ~140 KB) with ``record`` as its config, and the
    same record as readable JSON beside it (``.json``)."""
    path = Path(path)
    dof.save_checkpoint(path, dof_params, record)
    strict_json.write_json_atomic(path.with_suffix(".json"), record)


# --------------------------------------------------------------------------------------------------
# Flow accuracy.
# --------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("width", "height", "dt"))
def predict_flow_fields(dof_params: dof.DOFParams, q: jax.Array, u: jax.Array, width: int, height: int,
                        dt: float) -> jax.Array:
    """The DOF's dense flow prediction, pixels per frame: q, u (C, 4) -> (C, H, W, 2), ``[..., 0] = du``."""
    jj, ii = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    uv = train_lib.pixel_uv(ii, jj, width, height)  # (H, W, 2)

    def one(qf, uf):
        feats = dof.dof_features(jnp.broadcast_to(qf, (height, width, 4)), uv, jnp.broadcast_to(uf, (height, width, 4)))
        out = dof.dof_forward(dof_params, feats)  # (H, W, 2) = (l, theta)
        return train_lib.polar_to_flow(out[..., 0], out[..., 1], width, height, dt)

    return jax.lax.map(lambda args: one(*args), (q.astype(jnp.float32), u.astype(jnp.float32)))


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
                  baseline: train_lib.OrientationBinBaseline, dt: float = episode_lib.CONTROL_DT,
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
        bins = train_lib._bin_index(baseline.edges, train_lib._euler(lap.q))  # (F,)
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
# Rotation response: how far the DOF moves the pixel per rad/s, against the pinhole camera.
# --------------------------------------------------------------------------------------------------


def exact_rotation_response(camera, dt: float = episode_lib.CONTROL_DT, uv=IMAGE_CENTRE_UV) -> np.ndarray:
    """(2, 3) px/frame per rad/s: the exact rotational flow at the normalised pixel ``uv`` per body rate.

    A point far along the camera ray through ``uv`` (pure rotation: no parallax) is projected after the body
    turned by ``w dt`` (``q (x) exp(w dt / 2)``, the model's convention); ``jax.jacfwd`` at ``w = 0`` gives
    the flow per rad/s over one frame, in pixels at the camera's size. At the image centre of the untilted
    camera this is ``fx dt`` of yaw (wz) on u and ``-fy dt`` of pitch (wy) on v: the camera looks along body
    +x, u grows to the right and v downwards, a positive yaw turns the view left (the scene moves right),
    a positive pitch turns the nose down (the scene moves up). It does not depend on the attitude.
    """
    x0 = quadrotor.hover_state((0.0, 0.0, 0.0))
    uv_px = jnp.asarray(uv, jnp.float32) * jnp.asarray([camera.width, camera.height], jnp.float32)
    far = camera_lib.backproject(uv_px, jnp.asarray(1e4, jnp.float32), x0, camera)
    scale = jnp.asarray([camera.width, camera.height], jnp.float32)

    def pixel(rate, axis):  # the pixel after turning at ``rate`` rad/s about the unit body ``axis`` for dt
        half = 0.5 * rate * dt
        turn = jnp.concatenate([jnp.cos(half)[None], jnp.sin(half) * axis])
        q = quadrotor.quat_multiply(x0[quadrotor.QUAT], turn)
        uv_w, _, _ = camera_lib.project(far, x0.at[quadrotor.QUAT].set(q), camera)
        return uv_w * scale

    jac = jnp.stack([jax.jvp(lambda r, e=e: pixel(r, e), (jnp.asarray(0.0),), (jnp.asarray(1.0),))[1]
                     for e in jnp.eye(3)], axis=1)  # (2, 3): d pixel / d rate at rate 0, per axis
    return np.asarray(jac, np.float64)


def _rotation_jacobian(velocity_fn, dof_params, q, u, uv, scale):
    """(F, 2, 4) d(pixel velocity)/d(input) at ``uv`` per frame, in px/frame per unit input."""
    def one(qf, uf):
        return jax.jacfwd(lambda x: velocity_fn(dof_params, qf, uv, x) * scale)(uf)

    return jax.vmap(one)(q, u)


_rotation_jacobian_jit = jax.jit(_rotation_jacobian, static_argnums=0)


def rotation_response(dof_params, q: np.ndarray, u: np.ndarray, camera, dt: float = episode_lib.CONTROL_DT,
                      velocity_fn=None, uv=IMAGE_CENTRE_UV, chunk: int = 1024) -> dict:
    """The DOF's mean Jacobian at the image centre against the exact rotational flow, px/frame per rad/s.

    Args:
        dof_params: the network (passed to ``velocity_fn``).
        q, u: (F, 4) the frames' orientation and the control input the network is given (its variant's).
        camera: the camera (its size sets the pixels; its intrinsics the exact response).
        velocity_fn: ``(dof_params, q, uv, u) -> uv_dot`` in normalised image units per second (default
            ``dof.pixel_velocity``; a stub with a known response in tests).

    Returns:
        ``yaw_to_u`` and ``pitch_to_v``: ``{"dof", "exact", "ratio"}`` (ratio = dof / exact); ``jacobian_dof``
        and ``jacobian_exact``: (2, 3) rows (du, dv), columns (wx, wy, wz); ``jacobian_dof_std``: the spread of
        the DOF's Jacobian over the frames; ``frames``; ``uv``.
    """
    velocity_fn = dof.pixel_velocity if velocity_fn is None else velocity_fn
    q, u = np.asarray(q, np.float32), np.asarray(u, np.float32)
    scale = jnp.asarray([camera.width * dt, camera.height * dt], jnp.float32)
    uv_arr = jnp.asarray(uv, jnp.float32)
    jacs = []
    for start in range(0, q.shape[0], chunk):
        stop = min(start + chunk, q.shape[0])
        pad = chunk - (stop - start) if q.shape[0] > chunk else 0
        qc = np.concatenate([q[start:stop], np.repeat(q[stop - 1:stop], pad, 0)])
        uc = np.concatenate([u[start:stop], np.repeat(u[stop - 1:stop], pad, 0)])
        jac = _rotation_jacobian_jit(velocity_fn, dof_params, jnp.asarray(qc), jnp.asarray(uc), uv_arr, scale)
        jacs.append(np.asarray(jac, np.float64)[: stop - start, :, :3])
    jac = np.concatenate(jacs)  # (F, 2, 3)
    mean = jac.mean(axis=0)
    exact = exact_rotation_response(camera, dt, uv)

    def entry(axis: int, rate: int) -> dict:
        d, e = float(mean[axis, rate]), float(exact[axis, rate])
        return {"dof": d, "exact": e, "ratio": d / e if abs(e) > 1e-12 else None}

    return {"yaw_to_u": entry(0, 2), "pitch_to_v": entry(1, 1), "jacobian_dof": mean.tolist(),
            "jacobian_dof_std": jac.std(axis=0).tolist(), "jacobian_exact": exact.tolist(),
            "frames": int(q.shape[0]), "uv": list(uv),
            "units": "px/frame per rad/s of the rate given to the DOF, at the image size"}


# --------------------------------------------------------------------------------------------------
# Pixel-cost ranking of sampled control sequences: DOF against the exact projection.
# --------------------------------------------------------------------------------------------------


def rankdata(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``x`` (1-D), ties given their mean rank (as Spearman's correlation needs)."""
    x = np.asarray(x)
    order = np.argsort(x, kind="mergesort")
    sorted_x = x[order]
    ranks = np.empty(x.shape[0], np.float64)
    ranks[order] = np.arange(1, x.shape[0] + 1, dtype=np.float64)
    # average the ranks over each run of equal values
    boundaries = np.concatenate([[True], sorted_x[1:] != sorted_x[:-1], [True]])
    starts = np.nonzero(boundaries)[0]
    for a, b in zip(starts[:-1], starts[1:]):
        if b - a > 1:
            ranks[order[a:b]] = 0.5 * (a + 1 + b)
    return ranks


def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
    """Spearman's rank correlation of two 1-D arrays (numpy ranks); ``None`` if either is constant."""
    ra, rb = rankdata(a), rankdata(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denominator = np.sqrt(np.sum(ra * ra) * np.sum(rb * rb))
    return float(np.sum(ra * rb) / denominator) if denominator > 0 else None


@functools.lru_cache(maxsize=4)
def _pixel_cost_pair_fn(config: pixelmpc_lib.PixelMPCConfig, velocity_fn=None):
    """The jitted ``(dof_params, x0, uv0, controls (N, n_f, 4), target_centre, target_normal, camera) ->
    (cost_dof (N,), cost_projection (N,))``: the pixel cost of Eq. (18) over the first ``n_f`` steps with the
    pixel from the DOF dynamics and from the exact projection, both as :func:`pixelmpc.make_pixelmpc` models
    and costs them (robot model ``quadrotor.step``, the pixel cost only while the target is ahead)."""
    velocity_fn = dof.pixel_velocity if velocity_fn is None else velocity_fn
    dt = config.mppi.dt
    quad_params = quadrotor.QuadParams()
    n = quadrotor.STATE_DIM

    def dof_dynamics(X, u, p):
        x, uv = X[:n], X[n:]
        uv_dot = velocity_fn(p["dof"], x[quadrotor.QUAT], uv, u)
        return jnp.concatenate([quadrotor.step(x, u, dt, quad_params), uv + dt * uv_dot])

    def projection_dynamics(X, u, p):
        x_next = quadrotor.step(X[:n], u, dt, quad_params)
        uv, _, in_front = camera_lib.project(p["centre"], x_next, p["camera"])
        uv = jnp.where(in_front, uv, pixelmpc_lib.behind_camera_pixel(uv.dtype))
        return jnp.concatenate([x_next, uv])

    def pixel_term(X, p):
        ahead = jnp.dot(X[quadrotor.POS] - p["centre"], p["normal"]) < 0.0
        return ahead.astype(X.dtype) * pixelmpc_lib.pixel_cost(X[n:], config)

    cost = BatchCost(lambda X, U, t, p: jax.vmap(pixel_term, in_axes=(0, None))(X, p))

    @jax.jit
    def pair(dof_params, x0, uv0, controls, centre, normal, camera):
        p = {"dof": dof_params, "centre": centre, "normal": normal, "camera": camera}
        X0 = jnp.concatenate([x0, uv0.astype(x0.dtype)])
        return (rollout_costs(dof_dynamics, cost, None, X0, controls, p),
                rollout_costs(projection_dynamics, cost, None, X0, controls, p))

    return pair


def sample_control_sequences(key: jax.Array, plan: jax.Array, mppi_config) -> jax.Array:
    """(N, T, m) control sequences around ``plan`` (T, m) as :func:`mppi.make_mppi` samples them: noise of
    std ``noise_sigma`` (coloured if ``noise_exponent``), sample 0 the plan itself (``nominal_sample``),
    clipped to the bounds."""
    N, (T, m) = mppi_config.num_samples, plan.shape
    white = jax.random.normal(key, (N, T, m), dtype=plan.dtype)
    if mppi_config.noise_exponent:
        white = jnp.einsum("ts,nsm->ntm", jnp.asarray(coloured_noise_filter(T, mppi_config.noise_exponent)), white)
    noise = white * jnp.asarray(mppi_config.noise_sigma, plan.dtype)
    if mppi_config.nominal_sample:
        noise = noise.at[0].set(0.0)
    controls = plan[None] + noise
    if mppi_config.u_min is not None:
        controls = jnp.maximum(controls, jnp.asarray(mppi_config.u_min, plan.dtype))
    if mppi_config.u_max is not None:
        controls = jnp.minimum(controls, jnp.asarray(mppi_config.u_max, plan.dtype))
    return controls


def pixel_cost_rank_correlation(dof_params, laps: list[dataset_lib.Lap], track, camera,
                                num_samples: int = RANK_SAMPLES, t_f: float = RANK_T_F, stride: int = RANK_STRIDE,
                                seed: int = 0, velocity_fn=None, config: pixelmpc_lib.PixelMPCConfig | None = None,
                                progress: bool = False) -> dict:
    """Spearman correlation between the DOF's and the exact projection's pixel cost of sampled sequences.

    At every ``stride``-th logged state of ``laps`` where the target gate is detected (geometric detector,
    no noise) with its centre in the image, ``num_samples`` control sequences of ``t_f / dt`` steps are
    sampled as PixelMPC's MPPI samples them (:func:`sample_control_sequences`, PixelMPC's MPPI config) around
    the logged commands from that tick on (the plan MPPI was flying), rolled out with the MPC's robot model
    from the logged state, and costed with PixelMPC's pixel cost (``PixelMPCConfig``, the l1 cost by default)
    with the DOF's pixel and with the target's exact projection. The DOF is given the sampled controls, as
    PixelMPC gives them.

    Returns:
        ``median``, ``q25``, ``q75``, ``mean`` of the per-state correlations; ``states`` counted;
        ``skipped_constant`` (states where either cost did not vary over the samples); ``samples``, ``steps``.
    """
    base = config or pixelmpc_lib.PixelMPCConfig()
    config = dataclasses.replace(base, t_f=float(t_f), mppi=dataclasses.replace(base.mppi, num_samples=num_samples))
    steps = config.pixel_steps
    pair = _pixel_cost_pair_fn(config, velocity_fn)
    key = jax.random.key(seed)
    correlations, skipped = [], 0
    starts = []
    for lap in laps:
        F = lap.u.shape[0]
        for s in range(0, F, int(stride)):
            det = detector_lib.detect_from_geometry(track.gate(int(lap.target[s])), jnp.asarray(lap.states[s]),
                                                    camera)
            if bool(det.found) and bool(camera_lib.in_image(det.centre)):
                starts.append((lap, s, det.centre))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(starts), desc="pixel-cost ranking", unit="state", leave=False)
    for lap, s, uv0 in starts:
        idx = np.minimum(np.arange(s, s + steps), lap.u.shape[0] - 1)
        plan = jnp.asarray(lap.u[idx], jnp.float32)
        key, key_sample = jax.random.split(key)
        controls = sample_control_sequences(key_sample, plan, config.mppi)
        gate = int(lap.target[s])
        cost_dof, cost_exact = pair(dof_params, jnp.asarray(lap.states[s], jnp.float32), uv0, controls,
                                    track.gates.centre[gate], track.gates.normal[gate], camera)
        rho = spearman(np.asarray(cost_dof), np.asarray(cost_exact))
        if rho is None:
            skipped += 1
        else:
            correlations.append(rho)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    values = np.asarray(correlations, np.float64)

    def stat(fn):
        return float(fn(values)) if values.size else None

    return {"median": stat(np.median), "q25": stat(lambda v: np.percentile(v, 25)),
            "q75": stat(lambda v: np.percentile(v, 75)), "mean": stat(np.mean), "states": int(values.size),
            "skipped_constant": skipped, "samples": int(num_samples), "steps": int(steps), "t_f_s": float(t_f),
            "stride": int(stride), "pixel_cost": config.pixel_cost}


# --------------------------------------------------------------------------------------------------
# Multi-step pixel prediction (Fig. 7).
# --------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("horizon", "dt"))
def _multistep_lap(dof_params, track, camera, states, controls, target, horizon: int, dt: float):
    """Per start tick s (F,): predicted and true gate-centre pixel for k = 0..K. Returns
    err (F, K+1) px, err_zero (F, K+1) px (the pixel held still), valid (F, K+1) bool."""
    F = controls.shape[0]
    scale = jnp.asarray([camera.width, camera.height], jnp.float32)
    ks = jnp.arange(horizon + 1)

    def one_start(s):
        gate = track.gate(target[s])
        idx = jnp.minimum(s + ks, F)  # state index of step k
        det = jax.vmap(lambda x: detector_lib.detect_from_geometry(gate, x, camera))(states[idx])
        seen = det.found & camera_lib.in_image(det.centre) & (s + ks <= F)
        tracked = jnp.cumprod(seen.astype(jnp.int32)).astype(bool)  # seen on every tick up to k

        def step(uv, k):
            j = jnp.minimum(s + k, F - 1)
            uv_next = uv + dt * dof.pixel_velocity(dof_params, states[j, 3:7], uv, controls[j])
            return uv_next, uv_next

        uv0 = det.centre[0]
        _, rollout = jax.lax.scan(step, uv0, ks[:-1])
        pred = jnp.concatenate([uv0[None], rollout])  # (K+1, 2)
        err = jnp.linalg.norm((pred - det.centre) * scale, axis=-1)
        err_zero = jnp.linalg.norm((uv0 - det.centre) * scale, axis=-1)
        return err, err_zero, tracked

    return jax.vmap(one_start)(jnp.arange(F))


def multistep_error(dof_params: dof.DOFParams, laps: list[dataset_lib.Lap], track, camera,
                    horizon: int = 80, dt: float = episode_lib.CONTROL_DT, input: str = "command") -> dict:
    """Mean and std of the pixel error of the gate centre predicted ``k = 1..horizon`` steps ahead (Fig. 7),
    the DOF given the logged control input ``input`` ("command", or "flown": the rates flown over each frame).

    Returns lists of length ``horizon`` (``None`` where no prediction reaches that step): ``mean_px``,
    ``std_px``, ``count``, and ``zero_motion_mean_px`` (the error of assuming the pixel does not move).
    """
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    errs, zeros, valids = [], [], []
    for lap in laps:
        err, err_zero, valid = _multistep_lap(dof_params, track, camera, jnp.asarray(lap.states),
                                              jnp.asarray(dataset_lib.lap_input(lap, input)),
                                              jnp.asarray(lap.target), int(horizon), float(dt))
        errs.append(np.asarray(err)[:, 1:])
        zeros.append(np.asarray(err_zero)[:, 1:])
        valids.append(np.asarray(valid)[:, 1:])
    err, err_zero, valid = (np.concatenate(a) for a in (errs, zeros, valids))

    def column_stat(values, fn):
        return [float(fn(values[valid[:, k], k])) if valid[:, k].any() else None for k in range(horizon)]

    return {
        "steps": list(range(1, horizon + 1)),
        "dt_s": float(dt),
        "mean_px": column_stat(err, np.mean),
        "std_px": column_stat(err, np.std),
        "count": [int(c) for c in valid.sum(0)],
        "zero_motion_mean_px": column_stat(err_zero, np.mean),
        "starts": int(valid[:, 0].sum()),
        "input": input,
    }


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


def plot_multistep(path, multistep: dict, title: str = "") -> None:
    """Fig. 7 (right): mean +- std pixel error of the multi-step prediction vs the horizon step."""
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
    ax.set(xlabel=f"prediction step (dt = {multistep['dt_s']:g} s)", ylabel="gate-centre error [px]",
           title=title or "multi-step pixel prediction error")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# --------------------------------------------------------------------------------------------------
# The evaluation.
# --------------------------------------------------------------------------------------------------


def default_cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pixelmpc_jax"


def heldout_dataset(cache_dir=None, config: dataset_lib.CollectConfig = HELDOUT_CONFIG, progress: bool = True,
                    policy: episode_lib.Policy | None = None) -> Path:
    """Collect (or reuse) the seeded held-out set in the cache; returns its directory."""
    tag = f"dof_heldout_seed{config.seed}_laps{config.laps}_t{config.max_lap_time_s:g}_ss{config.supersample}"
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir() / tag
    dataset_lib.collect(root, config, progress=progress, policy=policy)
    return root


def evaluate(dof_params: dof.DOFParams | None = None, data_dir=None, out_dir="runs/dof_eval", *, horizon: int = 80,
             bins_per_angle: int = 4, cache_dir=None, heldout_config: dataset_lib.CollectConfig = HELDOUT_CONFIG,
             figures: bool = True, progress: bool = True, input: str | None = None,
             rank_samples: int = RANK_SAMPLES, rank_stride: int = RANK_STRIDE) -> dict:
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
    if input not in train_lib.INPUTS:
        raise ValueError(f"input must be one of {train_lib.INPUTS}, got {input!r}")
    dof_params = load_shipped_dof() if dof_params is None else dof_params
    if data_dir is None:
        data_dir = heldout_dataset(cache_dir, heldout_config, progress=progress)
    data_dir = Path(data_dir)
    manifest = dataset_lib.read_manifest(data_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    train_data = dataset_lib.load_dataset(data_dir, "train")
    baseline = train_lib.fit_orientation_bin_baseline(train_data.q, train_data.u, train_data.flow, bins_per_angle)
    del train_data
    laps = dataset_lib.load_laps(data_dir, "test")
    world = episode_lib.make_world()
    W, H = manifest["image_size_wh"]
    if (world.camera.width, world.camera.height) != (W, H):
        raise ValueError(f"{data_dir}: images are {W}x{H}, the camera renders {world.camera.width}x"
                         f"{world.camera.height}")
    dt = float(manifest["frame_dt_s"])
    accuracy = flow_accuracy(dof_params, laps, baseline, dt, progress=progress, input=input)
    multistep = multistep_error(dof_params, laps, world.track, world.camera, horizon, dt, input=input)
    rotation = rotation_response(dof_params, np.concatenate([lap.q for lap in laps]),
                                 np.concatenate([dataset_lib.lap_input(lap, input) for lap in laps]), world.camera, dt)
    ranking = pixel_cost_rank_correlation(dof_params, laps, world.track, world.camera, num_samples=rank_samples,
                                          stride=rank_stride, progress=progress)

    results = {
        "num_parameters": dof.num_trainable_params(dof_params),
        "dof_input": input,
        **accuracy,
        "rotation_response": rotation,
        "pixel_cost_rank_correlation": ranking,
        "paper_aee_px": PAPER_AEE_PX,
        "image_size_wh": [W, H],
        "units": "pixels per frame (1/40 s) at the image size; multistep: pixels",
        "multistep": multistep,
        "multistep_at": {str(k): {"mean_px": multistep["mean_px"][k - 1], "std_px": multistep["std_px"][k - 1],
                                  "count": multistep["count"][k - 1]} for k in (1, 10, 20, 40, 80) if k <= horizon},
        "data": {
            "dir": str(data_dir),
            "test_laps": [{k: e[k] for k in ("lap", "speed", "seed", "frames", "end")} for e in
                          manifest["laps"] if e["split"] == "test"],
            "train_laps_for_baseline": [e["lap"] for e in manifest["laps"] if e["split"] == "train"],
            "collect_config": manifest["config"],
        },
        "baseline_bins_per_angle": bins_per_angle,
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    if figures:
        lap = laps[0]
        t = _figure_frame(lap)
        frame = render_lib.render(world.track, jnp.asarray(lap.states[t]), world.camera,
                                  supersample=int(manifest["config"]["supersample"]))
        lap_u = dataset_lib.lap_input(lap, input)
        predicted = np.asarray(predict_flow_fields(dof_params, lap.q[t:t + 1], lap_u[t:t + 1], W, H, dt))[0]
        exact = None if lap.exact_flow is None else lap.exact_flow[t].astype(np.float32)
        valid = None if lap.exact_valid is None else lap.exact_valid[t]
        speed = float(np.linalg.norm(lap.states[t, 7:10]))
        plot_flow_fields(out / "dof_flow_fields.png", np.asarray(frame.rgb), exact, valid,
                         lap.flow[t].astype(np.float32), predicted,
                         title=f"test lap {lap.info.get('lap')} frame {t}, {speed:.1f} m/s")
        plot_multistep(out / "dof_multistep.png", multistep,
                       title=f"multi-step gate-centre prediction, {multistep['starts']} starts")
        results["figures"] = ["dof_flow_fields.png", "dof_multistep.png"]
        results["figure_frame"] = {"lap": lap.info.get("lap"), "frame": t}
    results["wall_s"] = time.perf_counter() - t0
    results = strict_json.json_safe(results)
    strict_json.write_json_atomic(out / "dof_eval.json", results)
    return results


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
# The `pixelmpc train` and `pixelmpc evaluate` entry points.
# --------------------------------------------------------------------------------------------------


def run_train(data_dir, out_dir="runs/dof_train", steps: int = 20_000, batch_size: int = 4096,
              learning_rate: float = 1e-3, seed: int = 0, resume: bool = False, progress: bool = True,
              ship: bool = False, loss: str = "polar", input: str = "command") -> dict:
    """Train the DOF on ``data_dir``'s train laps (train.py, Algorithm 1), report the test-lap AEE, and
    write ``out_dir/checkpoint.msgpack`` (resumable: Adam state), ``out_dir/dof_weights.msgpack``
    (weights only, with the provenance record) and ``out_dir/history.json``. ``ship=True`` also copies
    the weights into the package (``pixelmpc_jax/data``). Prints a short summary; returns the record.

    ``loss``: "polar" (the paper's) or "endpoint"; ``input``: the network's control input, "command" (the
    paper's) or "flown" (the rates flown over the frame; ``train.INPUTS``). The variant is recorded in the
    weights' record (``variant``, read back by ``dof.checkpoint_variant``)."""
    if input not in train_lib.INPUTS:
        raise ValueError(f"input must be one of {train_lib.INPUTS}, got {input!r}")
    data_dir, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest = dataset_lib.read_manifest(data_dir)
    W, H = manifest["image_size_wh"]
    train_data = dataset_lib.load_dataset(data_dir, "train", input=input)
    has_test = bool(manifest["split"]["test"]) and manifest["frames"]["test"] > 0
    test_data = dataset_lib.load_dataset(data_dir, "test", input=input) if has_test else None
    checkpoint = out / "checkpoint.msgpack"
    config = train_lib.TrainConfig(steps=steps, batch_size=batch_size, learning_rate=learning_rate, seed=seed,
                                   width=W, height=H, dt=float(manifest["frame_dt_s"]),
                                   checkpoint_path=str(checkpoint), progress=progress, loss=loss, input=input)
    t0 = time.perf_counter()
    dof_params, history = train_lib.train(config, train_data, test_data,
                                          resume_from=checkpoint if (resume and checkpoint.exists()) else None)
    wall = time.perf_counter() - t0
    strict_json.write_json_atomic(out / "history.json", history)
    record = {
        "what": "DOF weights (parameters + input/output normalisation), pixelmpc_jax.learn",
        "train_config": {**dataclasses.asdict(config), "checkpoint_path": None},
        "variant": {"input": input, "loss": loss, "layer_sizes": list(dof.LAYER_SIZES),
                    "input_means": "the body rates commanded at the frame's tick (the paper's)" if input == "command"
                    else "the body rates flown over the frame interval (dataset w_flown), commanded thrust"},
        "train_wall_s": wall,
        "steps_done": history["step"][-1] if history["step"] else 0,
        "interrupted": history["interrupted"],
        "data": {
            "dir": str(data_dir),
            "collect_config": manifest["config"],
            "policy": manifest.get("policy"),
            "format_version": manifest.get("format_version"),
            "excited_laps": manifest.get("excited_laps", []),
            "frames": manifest["frames"],
            "bytes": manifest.get("bytes"),
            "laps": [{k: e[k] for k in ("lap", "split", "speed", "seed", "frames", "end", "gates_passed")}
                     for e in manifest["laps"]],
        },
        "results": {"test_aee_px": history.get("test_aee_px"),
                    "test_zero_flow_aee_px": history.get("test_zero_flow_aee_px")},
        "calls": [
            f"pixelmpc_jax.learn.dataset.collect({str(data_dir)!r}, "
            f"CollectConfig(**{json.dumps(manifest['config'])}))",
            f"pixelmpc_jax.learn.evaluate.run_train({str(data_dir)!r}, {str(out)!r}, steps={steps}, "
            f"batch_size={batch_size}, learning_rate={learning_rate}, seed={seed}, loss={loss!r}, input={input!r})",
        ],
        "versions": manifest.get("versions", {}) | {"jax": jax.__version__},
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    export_weights(out / SHIPPED_WEIGHTS, dof_params, record)
    if ship:
        target = shipped_weights_path()
        shutil.copyfile(out / SHIPPED_WEIGHTS, target)
        shutil.copyfile(out / SHIPPED_RECORD, target.with_suffix(".json"))
    aee = history.get("test_aee_px")
    zero = history.get("test_zero_flow_aee_px")
    print(f"trained {record['steps_done']} steps ({input} input, {loss} loss) in {wall / 60:.1f} min on "
          f"{manifest['frames']['train']} frames; "
          f"test AEE {'-' if aee is None else f'{aee:.2f}'} px/frame (zero flow "
          f"{'-' if zero is None else f'{zero:.2f}'}); weights: {out / SHIPPED_WEIGHTS}")
    return record


def run_evaluate(weights=None, data_dir=None, out_dir="runs/dof_eval", horizon: int = 80,
                 progress: bool = True) -> dict:
    """Evaluate a weights file (default: the shipped one) and print a short summary; see :func:`evaluate`.
    The network is given the input its record names (``dof.checkpoint_variant``: command or flown)."""
    dof_params, record = dof.load_checkpoint(shipped_weights_path() if weights is None else weights)
    variant = dof.checkpoint_variant(record)
    results = evaluate(dof_params, data_dir, out_dir, horizon=horizon, progress=progress, input=variant["input"])
    print(summarise(results))
    print(f"wrote {Path(out_dir) / 'dof_eval.json'}")
    return results
