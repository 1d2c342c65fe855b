"""Honest timing helpers: compile outside the timed region, block on every call, report spread."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import jax
import numpy as np

from pixelmpc_jax.platform_info import device_description, device_line  # noqa: F401 (re-exported)


def time_call(fn: Callable[[], object], repeats: int = 30, warmup: int = 3) -> dict:
    """Time ``fn()`` (which must return JAX arrays) ``repeats`` times after ``warmup`` calls.

    Returns a dict of ms figures: median, mean, two_sigma (2 x std), min, max, and the repeats.
    """
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append((time.perf_counter() - start) * 1e3)
    arr = np.asarray(times)
    return {
        "median_ms": float(statistics.median(times)),
        "mean_ms": float(arr.mean()),
        "two_sigma_ms": float(2 * arr.std()),
        "min_ms": float(arr.min()),
        "max_ms": float(arr.max()),
        "repeats": repeats,
    }
