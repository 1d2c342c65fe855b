"""Peers on identical work.

* pytorch-mppi (PyPI ``pytorch-mppi``) given the PixelMPC problem ported to torch (``torch_port.py``: the
  same quadrotor, DOF weights, racing and pixel costs, N, T, lambda, sigma, bounds; the DOF runs over t_f
  only, through ``step_dependent_dynamics=True``), beside our PixelMPC step in the same run; ``ratio`` is
  ours / theirs (median). PyTorch's CPU threads are probed at 1 and at the default count (3 calls each) and
  the faster is timed fully; the ratio is against it (on a shared machine OpenMP's spinning threads can make
  the default count many times slower). The probe of the slower setting is kept as a row.
* MPPI-Generic's benchmark problem (differential drive in a cost map, ``problems.diff_drive_problem``) in
  our generic MPPI, beside its published figures (other hardware: a reference, not a same-run ratio).
"""

from __future__ import annotations

from pixelmpc_jax.apps.bench import problems
from pixelmpc_jax.apps.bench.controller import pixelmpc_row
from pixelmpc_jax.apps.bench.measure import make_row, measure
from pixelmpc_jax.dynamics import quadrotor

PEER_SAMPLES = (128, 512, 2048)

# MPPI-Generic (arXiv 2409.07563), ms per optimisation iteration, by number of samples.
MPPI_GENERIC_PUBLISHED = {
    "MPPI-Generic, RTX 4090": {128: 0.123, 1024: 0.131, 4096: 0.170, 16384: 0.389},
    "AutoRally MPPI, RTX 4090": {128: 0.198, 1024: 0.202, 4096: 0.224, 16384: 0.338},
    "TorchRL MPPIPlanner, RTX 4090": {128: 24.5, 1024: 28.1, 4096: 28.2, 16384: 28.6},
    "ROS2 Nav2 MPPI, i9-13900K CPU": {128: 0.39, 1024: 3.36, 4096: 13.9, 16384: 62.3},
    "MPPI-Generic, GTX 1050 Ti": {128: 0.20, 1024: 0.43, 4096: 1.47, 16384: 5.64},
}
DIFF_DRIVE_SAMPLES = (128, 1024, 4096, 16384)
TORCH_MISSING = "not run: torch and pytorch-mppi are not installed (the bench extra: pip install 'pixelmpc-jax[bench]')"


def torch_available() -> bool:
    try:
        import pytorch_mppi  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def pytorch_mppi_rows(samples=PEER_SAMPLES, horizon: int = 80, repeats: int = 30, ours: dict | None = None,
                      budget_s: float = 20.0) -> list[dict]:
    """Ours and pytorch-mppi at each N (T = 80, t_f = 1 s), one row per (implementation, N), peer rows with
    ``ratio`` = ours / theirs. ``ours`` optionally maps N to an already measured row of ours."""
    if not torch_available():
        return [make_row("peer", "pytorch-mppi", n, horizon, None, status=TORCH_MISSING) for n in samples]
    import torch

    from pixelmpc_jax.apps.bench import torch_port

    quad_params = quadrotor.QuadParams()
    default_threads = torch.get_num_threads()
    rows = []
    for n in samples:
        problem = problems.pixelmpc_problem(n, horizon, 1.0)
        our_row = (ours or {}).get(n) or pixelmpc_row(n, horizon, 1.0, repeats)
        our_row = {**our_row, "group": "peer", "name": "ours: PixelMPC step (JAX)"}
        rows.append(our_row)
        # Probe each thread count with 3 calls, then time the faster fully (the slower keeps its probe figures).
        probes = {}
        for threads in sorted({1, default_threads}):
            torch.set_num_threads(threads)
            try:
                ctrl, x0 = torch_port.make_pytorch_mppi(problem, quad_params)
                probes[threads] = (ctrl, x0, measure(lambda ctrl=ctrl, x0=x0: ctrl.command(x0), repeats=2, warmup=0))
            finally:
                torch.set_num_threads(default_threads)
        best_threads = min(probes, key=lambda k: probes[k][2]["median_ms"])
        peer_rows = []
        for threads, (ctrl, x0, probe) in probes.items():
            name = f"pytorch-mppi (torch {torch.__version__}, {threads} thread(s))"
            if threads != best_threads:
                peer_rows.append(make_row("peer", name, n, horizon, probe, torch_threads=threads,
                                          note="probe only (2 timed calls): the slower thread count"))
                continue
            torch.set_num_threads(threads)
            try:
                stats = measure(lambda ctrl=ctrl, x0=x0: ctrl.command(x0), repeats=repeats, budget_s=budget_s)
            finally:
                torch.set_num_threads(default_threads)
            peer_rows.append(make_row("peer", name, n, horizon, stats, torch_threads=threads))
        best = min(r["median_ms"] for r in peer_rows)
        for r in peer_rows:
            r["ratio"] = our_row["median_ms"] / r["median_ms"]
            r["best_peer"] = r["median_ms"] == best
        our_row["ratio"] = our_row["median_ms"] / best
        rows += peer_rows
    return rows


def mppi_generic_rows(samples=DIFF_DRIVE_SAMPLES, repeats: int = 30) -> list[dict]:
    """MPPI-Generic's differential-drive problem in our generic MPPI (T = 100, K = 1), with its figures."""
    rows = []
    for n in samples:
        problem = problems.diff_drive_problem(n)
        stats = measure(problems.control_loop_call(problem), repeats=repeats)
        published = {name: figures.get(n) for name, figures in MPPI_GENERIC_PUBLISHED.items()}
        rows.append(make_row("mppi_generic", "diff drive, cost map (ours, generic MPPI)", n, problem.config.horizon,
                             stats, published_ms=published))
    return rows
