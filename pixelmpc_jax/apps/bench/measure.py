"""Timing for the runtime harness: compile (first call) outside the timed region, block on every call,
warm up, then at least ``repeats`` timed calls; only calls slower than ``slow_s`` get fewer (recorded).

A row is a flat dict with the fields of ``bench.json`` (see ``apps/bench/suite.py``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np


def _block(out):
    """Wait for JAX arrays (torch CPU and numpy results are already computed when returned)."""
    return jax.block_until_ready(out) if any(isinstance(x, jax.Array) for x in jax.tree_util.tree_leaves(out)) \
        else out


def measure(fn: Callable[[], object], repeats: int = 30, warmup: int = 3, slow_s: float = 1.0,
            slow_repeats: int = 5, budget_s: float | None = None) -> dict:
    """Time ``fn()``: one first call (compilation; timed apart as ``first_call_ms``), ``warmup`` calls, then
    ``repeats`` timed calls, each ending in ``block_until_ready``. A call slower than ``slow_s`` seconds is
    repeated only ``slow_repeats`` times with one warm-up (``reduced_repeats`` says so); with ``budget_s`` the
    repeats are cut to fit about that many seconds (never below ``slow_repeats``).

    Returns the :func:`time_stats` of the timed calls, reduced_repeats and first_call_ms.
    """
    start = time.perf_counter()
    _block(fn())
    first = time.perf_counter() - start
    start = time.perf_counter()
    _block(fn())
    second = time.perf_counter() - start
    requested = repeats
    if second > slow_s:
        repeats, warmup = min(repeats, slow_repeats), 0
    if budget_s is not None:
        repeats = min(repeats, max(slow_repeats, int(budget_s / max(second, 1e-6))))
    reduced = repeats < requested
    for _ in range(max(warmup - 1, 0)):
        _block(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        _block(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return {**time_stats(times), "reduced_repeats": bool(reduced), "first_call_ms": float(first * 1e3)}


def measure_interleaved(fns: dict[str, Callable[[], object]], repeats: int = 30, warmup: int = 3) -> dict[str, dict]:
    """Time several calls of the same work against each other: each first called once (compilation, timed apart
    as ``first_call_ms``) and ``warmup`` times, then ``repeats`` rounds in which each is timed once, in turn, each
    call ending in ``block_until_ready``; on a shared machine a load that comes and goes then weighs on each
    alike. Returns ``{name: time_stats + first_call_ms}``."""
    first = {}
    for name, fn in fns.items():
        start = time.perf_counter()
        _block(fn())
        first[name] = (time.perf_counter() - start) * 1e3
        for _ in range(warmup):
            _block(fn())
    times: dict[str, list] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            _block(fn())
            times[name].append((time.perf_counter() - start) * 1e3)
    return {name: {**time_stats(times[name]), "reduced_repeats": False, "first_call_ms": first[name]}
            for name in fns}


def time_stats(times_ms) -> dict:
    """The ms figures of timed calls: median, mean, two_sigma (2 x std, population), min, max, p95 (linear
    interpolation between the calls) and repeats (how many)."""
    arr = np.asarray(times_ms, dtype=np.float64)
    return {
        "median_ms": float(np.median(arr)),
        "mean_ms": float(arr.mean()),
        "two_sigma_ms": float(2.0 * arr.std()),
        "min_ms": float(arr.min()),
        "max_ms": float(arr.max()),
        "p95_ms": float(np.percentile(arr, 95)),
        "repeats": int(arr.size),
    }


def make_row(group: str, name: str, num_samples: int | None, horizon: int | None, stats: dict | None,
             **extra) -> dict:
    """One row of bench.json; ``stats`` None (not run: OOM, skipped) leaves the timing fields None."""
    timing = {k: None for k in ("median_ms", "mean_ms", "two_sigma_ms", "min_ms", "max_ms", "p95_ms")}
    row = {"group": group, "name": name, "num_samples": num_samples, "horizon": horizon, **timing,
           "repeats": 0, "status": "ok" if stats is not None else "not run"}
    if stats is not None:
        row.update(stats)
    row.update(extra)
    return row


def spread(result: dict, digits: int = 2, repeats: int | None = None, p95: bool = False) -> str:
    """A timing's line for a bench's printout: ``median M ms (mean m +- s ms 2sigma[, p95 P ms], max X ms[, N
    repeats])`` with ``digits`` decimals."""
    f = f".{digits}f"
    tail = (f", p95 {result['p95_ms']:{f}} ms" if p95 else "") + f", max {result['max_ms']:{f}} ms"
    tail += f", {repeats} repeats" if repeats is not None else ""
    return (f"median {result['median_ms']:{f}} ms (mean {result['mean_ms']:{f}} +- {result['two_sigma_ms']:{f}} ms "
            f"2sigma{tail})")


def fmt_ms(row: dict) -> str:
    """'mean +- 2sigma (max)' in ms, or the row's status."""
    if row.get("median_ms") is None:
        return str(row.get("status"))
    return f"{row['mean_ms']:.2f} ± {row['two_sigma_ms']:.2f} (max {row['max_ms']:.2f})"


_CHILD = """
import importlib, json, sys
module, name, args = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
result = getattr(importlib.import_module(module), name)(*args)
print("RESULT " + json.dumps(result))
"""


def run_in_child(module: str, function: str, args: list, timeout_s: float = 1800.0) -> tuple[bool, object]:
    """Call ``module.function(*args)`` (JSON in, JSON out) in a fresh Python process.

    A row that may not fit in memory runs this way: XLA on the CPU answers an allocation it cannot make with
    ``std::bad_alloc``, which aborts the whole process, and the kernel's OOM killer does the same; in a child
    that ends the row, not the harness. Returns ``(True, result)`` or ``(False, why)``.
    """
    root = str(Path(__file__).resolve().parents[3])  # the folder holding pixelmpc_jax (a checkout or site-packages)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    try:
        done = subprocess.run([sys.executable, "-c", _CHILD, module, function, json.dumps(args)], env=env,
                              capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False, f"timed out after {timeout_s:.0f} s"
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode == 0 and lines:
        return True, json.loads(lines[-1][len("RESULT "):])
    tail = [line for line in done.stderr.strip().splitlines() if line.strip()][-1:] or [""]
    cause = f"signal {-done.returncode}" if done.returncode < 0 else f"exit {done.returncode}"
    return False, f"{cause}: {tail[0][:120]}"
