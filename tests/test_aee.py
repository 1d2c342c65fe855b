"""The average endpoint error of the DOF and of the baselines: hand-computed cases, chunk invariance, the
dense prediction against the AEE, and the orientation-bin baseline."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn import aee

W, H, DT = 32, 24, 1.0 / 40.0


@pytest.fixture(scope="module")
def frames():
    """q over a range of attitudes, u random, and a flow field per frame set by u alone (uniform over the
    image plus a little noise): flows the orientation does not explain."""
    rng = np.random.default_rng(0)
    eul = rng.uniform(-0.5, 0.5, (48, 3))
    q = np.asarray(jax.vmap(quadrotor.quat_from_euler)(eul[:, 0], eul[:, 1], eul[:, 2]), np.float32)
    u = np.concatenate([rng.uniform(-2, 2, (48, 3)), rng.uniform(5, 15, (48, 1))], 1).astype(np.float32)
    flow = np.broadcast_to(u[:, None, None, :2], (48, H, W, 2)) + rng.normal(0.0, 0.1, (48, H, W, 2))
    return q, u, flow.astype(np.float16)


def _constant_network(l: float, theta: float) -> dof.DOFParams:
    """Zero weights: the network predicts ``(l, theta) = output_mean`` everywhere."""
    params = dof.init_dof_params(jax.random.key(0), output_mean=[l, theta])
    return params.replace(weights=jax.tree_util.tree_map(jnp.zeros_like, params.weights))


def test_evaluate_aee_matches_numpy_and_is_chunk_invariant(frames):
    params = _constant_network(0.8, 0.7)
    pred_px = np.asarray([0.8 * np.cos(0.7) * W * DT, 0.8 * np.sin(0.7) * H * DT])
    flow = frames[2].astype(np.float64)
    expected = np.mean(np.hypot(pred_px[0] - flow[..., 0], pred_px[1] - flow[..., 1]))
    for chunk_pixels in (1, 5 * W * H, 1 << 20):  # 1 frame, 5 frames with a padded tail, all at once
        got = aee.evaluate_aee(params, *frames, W, H, DT, chunk_pixels=chunk_pixels)
        np.testing.assert_allclose(got, expected, rtol=1e-5)


def test_the_dense_prediction_is_what_the_aee_measures(frames):
    params = dof.init_dof_params(jax.random.key(1), output_mean=[0.5, 0.2])
    q, u, flow = frames
    pred = np.asarray(aee.predict_flow_fields(params, q[:6], u[:6], W, H, DT))
    assert pred.shape == (6, H, W, 2)
    np.testing.assert_allclose(pred[2], aee.frame_flow(params, q[2], u[2], W, H, DT), rtol=1e-5, atol=1e-6)
    err = pred - flow[:6].astype(np.float32)
    np.testing.assert_allclose(aee.evaluate_aee(params, q[:6], u[:6], flow[:6], W, H, DT),
                               np.mean(np.hypot(err[..., 0], err[..., 1])), rtol=1e-5)
    with pytest.raises(AssertionError, match="shape"):
        aee.predict_flow_fields(params, q[0], u[0], W, H, DT)  # one frame needs its frame axis


def test_zero_flow_and_orientation_bin_baselines(frames):
    q, u, flow = frames
    expected = np.mean(np.hypot(flow[..., 0].astype(np.float64), flow[..., 1].astype(np.float64)))
    np.testing.assert_allclose(aee.zero_flow_aee(q, u, flow, chunk_frames=7), expected, rtol=1e-6)
    # A flow field that depends on the orientation bin only is predicted exactly.
    baseline = aee.fit_orientation_bin_baseline(q, u, flow, bins_per_angle=2)
    idx = baseline.bin_index(q)
    assert idx.shape == (48,) and baseline.counts.sum() == len(q) and baseline.mean_flow.shape == (8, H, W, 2)
    np.testing.assert_array_equal(np.bincount(idx, minlength=8), baseline.counts)
    binned_flow = np.asarray(flow[:8][idx % 8], np.float32)
    exact = aee.fit_orientation_bin_baseline(q, u, binned_flow, bins_per_angle=2)
    assert aee.orientation_bin_aee(exact, q, u, binned_flow) < 1e-6
    # On flows driven by u, not q, it is no better than predicting the mean flow.
    assert aee.orientation_bin_aee(baseline, q, u, flow) > 0.5 * expected
