"""How MPPI draws, weighs and places its samples: time-correlated noise, the importance weights, the samples
split over devices and the kernels the step compiles to.

* :func:`coloured_noise_filter`: the (T, T) filter that colours white noise along the horizon (1/f^beta).
* :func:`importance_weights`: the softmax weights of the sample costs, NaN-safe.
* :func:`sample_shardings`: the samples of one step split over several devices (``MPPIConfig.sample_devices``).
  Each device rolls out and costs its share of the N samples; only the weights' normalisers and the
  weighted update cross devices. The noise is drawn whole from the same key (the partitionable threefry
  lets each device draw just its rows), so the samples, and the plan up to float rounding, are those of one
  device. On a CPU, the host's cores become devices with :func:`pixelmpc_jax.host.split_host_cpu` (before JAX
  starts): XLA runs
  one device's program on one core but for its largest kernels, and splitting the samples splits all of the
  step's work (the rollout, the DOF's 40 sequential 512 x 128 x 128 products, the costs, the noise).
* :func:`compiler_options`: on one CPU device, the products go to YNNPACK (``MPPIConfig.cpu_matmul``).
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

SAMPLE_AXIS = "samples"
CPU_MATMULS = ("auto", "xla", "ynnpack")  # MPPIConfig.cpu_matmul
YNNPACK_MATMULS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT"}


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


class SampleShardings(NamedTuple):
    """Where one MPPI step's arrays live when its samples are split over devices.

    Attributes:
        samples: the leading (sample) axis split over the devices, the rest whole.
        replicated: a whole copy on every device (the plan, x0, the params, the key).
    """

    samples: jax.sharding.NamedSharding
    replicated: jax.sharding.NamedSharding


def sample_shardings(num_devices: int, num_samples: int) -> SampleShardings:
    """The shardings of a step whose ``num_samples`` samples are split over the first ``num_devices`` local
    devices (of the default backend). A ValueError if fewer are present or the samples do not split evenly."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.local_devices()
    if num_devices > len(devices):
        raise ValueError(f"sample_devices={num_devices} but only {len(devices)} {devices[0].platform} device(s) are "
                         f"present (on a CPU, split the host's cores into devices before JAX starts: "
                         f"pixelmpc_jax.host.split_host_cpu, or the `pixelmpc` command does it)")
    if num_samples % num_devices:
        raise ValueError(f"num_samples={num_samples} does not split evenly over sample_devices={num_devices}")
    mesh = Mesh(np.asarray(devices[:num_devices]), (SAMPLE_AXIS,))
    return SampleShardings(NamedSharding(mesh, PartitionSpec(SAMPLE_AXIS)), NamedSharding(mesh, PartitionSpec()))


def usable_sample_devices(num_samples: int) -> int:
    """The most local devices, at most all of them, over which ``num_samples`` samples split evenly (1 with one
    device): what to give ``MPPIConfig.sample_devices`` to use every device for one controller."""
    count = len(jax.local_devices())
    return next(k for k in range(count, 0, -1) if num_samples % k == 0)


def compiler_options(cpu_matmul: str, sample_devices: int) -> dict | None:
    """The XLA options a step is compiled with (``jax.jit(..., compiler_options=...)``), for
    ``MPPIConfig.cpu_matmul``: "ynnpack" hands the products and the bias and ReLU after them to YNNPACK, which
    splits even a 512 x 128 x 128 product over a CPU's cores (XLA's own kernel runs it on one); "xla" keeps
    XLA's; "auto" (the default) takes YNNPACK for a step on one CPU device and XLA's where the samples are
    split over devices already (each core then has its own share). Other platforms ignore the option."""
    if cpu_matmul not in CPU_MATMULS:
        raise ValueError(f"cpu_matmul must be one of {CPU_MATMULS}, got {cpu_matmul!r}")
    if cpu_matmul == "xla" or (cpu_matmul == "auto" and (sample_devices > 1 or jax.default_backend() != "cpu")):
        return None
    return dict(YNNPACK_MATMULS)
