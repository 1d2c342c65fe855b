"""How MPPI draws and weighs its samples: time-correlated noise and the importance weights.

* :func:`coloured_noise_filter`: the (T, T) filter that colours white noise along the horizon (1/f^beta).
* :func:`importance_weights`: the softmax weights of the sample costs, NaN-safe.

Where the samples live (split over devices) is :mod:`pixelmpc_jax.devices`'s concern.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np


def coloured_noise_filter(horizon: int, exponent: float) -> np.ndarray:
    """(T, T) matrix L such that ``L @ w``, w white unit noise along the horizon, has the power spectrum 1/f^beta
    (beta = ``exponent``) and unit variance at every step.

    The covariance of a stationary process with that spectrum on a circle of T steps is circulant,
    ``C[s, t] = c(|s - t|)`` with ``c(tau) = sum_f S_f cos(2 pi f tau / T)``, ``S_f = max(f, 1)^-beta`` over the
    integer frequencies (the zero frequency gets the lowest nonzero one's power, as iCEM does); L is its
    symmetric square root, scaled to unit diagonal. beta = 0 gives the identity (white noise).
    """
    if exponent == 0.0:
        return np.eye(horizon, dtype=np.float32)
    freqs = np.fft.fftfreq(horizon) * horizon  # integer frequencies, both signs
    power = np.maximum(np.abs(freqs), 1.0) ** (-float(exponent))
    lags = np.arange(horizon)
    autocov = np.real(np.fft.ifft(power))  # c(tau), tau = 0 .. T-1 (circular)
    cov = autocov[np.abs(lags[:, None] - lags[None, :]) % horizon]
    values, vectors = np.linalg.eigh(cov)
    root = (vectors * np.sqrt(np.maximum(values, 0.0))) @ vectors.T
    root = root / np.sqrt(np.sum(root**2, axis=1, keepdims=True))  # unit variance at every step
    return root.astype(np.float32)


def importance_weights(costs: jax.Array, temperature: float) -> tuple[jax.Array, jax.Array]:
    """MPPI weights from sample costs, NaN-safe.

    w_k = exp(-(S_k - min S) / lambda) / sum_j exp(-(S_j - min S) / lambda), with w_k = 0 for non-finite S_k.

    Args:
        costs: (N,) total cost per sample.
        temperature: lambda.

    Returns:
        weights: (N,), sums to 1 unless every cost is non-finite (then all zeros).
        finite: (N,) bool mask of the finite costs.
    """
    chex.assert_rank(costs, 1)
    finite = jnp.isfinite(costs)
    safe = jnp.where(finite, costs, jnp.inf)
    baseline = jnp.min(safe)
    baseline = jnp.where(jnp.isfinite(baseline), baseline, 0.0)
    logits = jnp.where(finite, -(safe - baseline) / temperature, -jnp.inf)
    any_finite = jnp.any(finite)
    logits = jnp.where(any_finite, logits, 0.0)
    weights = jax.nn.softmax(logits)
    return jnp.where(any_finite, weights, 0.0), finite
