"""The DOF's flow accuracy in the paper's measure, the average endpoint error (AEE) in pixels per frame, and
two baselines: no motion (zero flow), and the mean flow field per orientation bin.

The DOF's dense prediction of a frame is its (l, theta) output at every pixel centre (``dataset.pixel_uv``)
converted back to pixels per frame (``perception.flow.polar_to_flow``). Training reports the test AEE with
these functions and the evaluation uses the same ones, so the numbers compare.
"""

from __future__ import annotations

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn.dataset import as_flow_data, pixel_uv
from pixelmpc_jax.perception.flow import polar_to_flow
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH


def frame_flow(dof_params: dof.DOFParams, q: jax.Array, u: jax.Array, width: int, height: int,
               dt: float) -> jax.Array:
    """The DOF's flow prediction of one frame, pixels per frame: q, u (4,) -> (H, W, 2), ``[..., 0] = du``."""
    jj, ii = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    uv = pixel_uv(ii, jj, width, height)  # (H, W, 2)
    feats = dof.dof_features(jnp.broadcast_to(q, (height, width, 4)), uv, jnp.broadcast_to(u, (height, width, 4)))
    out = dof.dof_forward(dof_params, feats)  # (H, W, 2) = (l, theta)
    return polar_to_flow(out[..., 0], out[..., 1], width, height, dt)


@functools.partial(jax.jit, static_argnames=("width", "height", "dt"))
def predict_flow_fields(dof_params: dof.DOFParams, q: jax.Array, u: jax.Array, width: int, height: int,
                        dt: float) -> jax.Array:
    """The DOF's dense flow prediction, pixels per frame: q, u (C, 4) -> (C, H, W, 2), one frame at a time."""
    chex.assert_shape([q, u], (None, 4))
    return jax.lax.map(lambda args: frame_flow(dof_params, *args, width, height, dt),
                       (q.astype(jnp.float32), u.astype(jnp.float32)))


@functools.partial(jax.jit, static_argnames=("width", "height", "dt"))
def _epe_sum_chunk(dof_params, q, u, flow, frame_mask, width: int, height: int, dt: float):
    """Sum of endpoint errors over a chunk of frames. q, u: (C, 4); flow: (C, H, W, 2); mask: (C,)."""

    def frame_epe(qf, uf, flow_f):
        err = frame_flow(dof_params, qf, uf, width, height, dt) - flow_f.astype(jnp.float32)
        return jnp.sum(jnp.hypot(err[..., 0], err[..., 1]))

    per_frame = jax.vmap(frame_epe)(q, u, flow)  # (C,)
    return jnp.sum(jnp.where(frame_mask, per_frame, 0.0))


def evaluate_aee(dof_params: dof.DOFParams, q, u, flow, width: int = PAPER_WIDTH, height: int = PAPER_HEIGHT,
                 dt: float = timing.CONTROL_DT, *, chunk_pixels: int = 1 << 18) -> float:
    """Average endpoint error, pixels per frame, of the DOF prediction over every pixel of every frame.

    The prediction (l, theta) is converted back to pixels per frame; frames go through one compiled
    chunk function (``~chunk_pixels`` rows at a time, the last chunk padded and masked).
    """
    data = as_flow_data((q, u, flow), width, height)
    n = data.q.shape[0]
    chunk = max(1, min(n, chunk_pixels // (width * height)))
    total = 0.0
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        pad = chunk - (stop - start)
        qc, uc, fc = (np.concatenate([a[start:stop], np.zeros((pad, *a.shape[1:]), a.dtype)]) for a in data)
        mask = np.arange(chunk) < (stop - start)
        total += float(_epe_sum_chunk(dof_params, qc, uc, fc, mask, width=width, height=height, dt=float(dt)))
    return total / (n * width * height)


def zero_flow_aee(q, u, flow, chunk_frames: int = 256) -> float:
    """AEE (pixels per frame) of predicting no motion: the mean flow magnitude. q, u unused (every
    evaluator takes the same arrays)."""
    flow = np.asarray(flow)
    total = 0.0
    for start in range(0, flow.shape[0], chunk_frames):
        chunk = flow[start : start + chunk_frames].astype(np.float32)
        total += float(np.hypot(chunk[..., 0], chunk[..., 1]).sum(dtype=np.float64))
    return total / (flow.shape[0] * flow.shape[1] * flow.shape[2])


# --------------------------------------------------------------------------------------------------
# The orientation-bin baseline.
# --------------------------------------------------------------------------------------------------


def _euler(q) -> np.ndarray:
    q = np.asarray(q, np.float32)
    return np.asarray(jax.vmap(quadrotor.euler_angles)(jnp.asarray(quadrotor.normalize_quat(q))))  # (F, 3)


def _bin_index(edges: np.ndarray, angles: np.ndarray) -> np.ndarray:
    bins = edges.shape[1] - 1
    idx = np.stack(
        [np.clip(np.searchsorted(edges[k, 1:-1], angles[:, k], side="right"), 0, bins - 1) for k in range(3)],
        axis=1,
    )
    return (idx[:, 0] * bins + idx[:, 1]) * bins + idx[:, 2]


@dataclasses.dataclass(frozen=True)
class OrientationBinBaseline:
    """Mean flow field per (roll, pitch, yaw) bin.

    Attributes:
        edges: (3, bins + 1) quantile bin edges of roll, pitch, yaw (rad) on the fitting frames.
        mean_flow: (bins^3, H, W, 2) per-bin mean flow, pixels per frame (empty bins: the global mean).
        counts: (bins^3,) fitting frames per bin.
    """

    edges: np.ndarray
    mean_flow: np.ndarray
    counts: np.ndarray

    def bin_index(self, q) -> np.ndarray:
        """(F,) the bin of each orientation q (F, 4), an index into ``mean_flow``."""
        return _bin_index(self.edges, _euler(q))


def fit_orientation_bin_baseline(q, u, flow, bins_per_angle: int = 4) -> OrientationBinBaseline:
    """Bin frames by roll, pitch and yaw quantiles and average the flow field per bin. u unused."""
    flow = np.asarray(flow)
    angles = _euler(q)
    edges = np.quantile(angles, np.linspace(0.0, 1.0, bins_per_angle + 1), axis=0).T  # (3, bins + 1)
    idx = _bin_index(edges, angles)
    n_bins = bins_per_angle**3
    sums = np.zeros((n_bins, *flow.shape[1:]), np.float64)
    for start in range(0, flow.shape[0], 256):  # bounded memory: one chunk of frames at a time
        chunk, chunk_idx = flow[start : start + 256].astype(np.float64), idx[start : start + 256]
        for b in np.unique(chunk_idx):
            sums[b] += chunk[chunk_idx == b].sum(0)
    counts = np.bincount(idx, minlength=n_bins)
    global_mean = sums.sum(0) / flow.shape[0]
    mean_flow = np.where(
        counts[:, None, None, None] > 0, sums / np.maximum(counts, 1)[:, None, None, None], global_mean
    )
    return OrientationBinBaseline(edges=edges, mean_flow=mean_flow.astype(np.float32), counts=counts)


def orientation_bin_aee(baseline: OrientationBinBaseline, q, u, flow, chunk_frames: int = 256) -> float:
    """AEE (pixels per frame) of predicting each frame's orientation-bin mean flow. u unused."""
    flow = np.asarray(flow)
    idx = baseline.bin_index(q)
    total = 0.0
    for start in range(0, flow.shape[0], chunk_frames):
        err = baseline.mean_flow[idx[start : start + chunk_frames]] - flow[start : start + chunk_frames].astype(
            np.float32)
        total += float(np.hypot(err[..., 0], err[..., 1]).sum(dtype=np.float64))
    return total / (flow.shape[0] * flow.shape[1] * flow.shape[2])
