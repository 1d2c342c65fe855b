"""The documented compile path against a plain ``jax.jit``: the same PixelMPC step, compiled two ways, timed in
one run, interleaved.

* documented: ``devices.compile_controller(ctrl).step`` (the README's and the reference's path): its inputs checked,
  jitted with :func:`~pixelmpc_jax.devices.compiler_options` (on one CPU device, YNNPACK's kernels);
* plain: ``jax.jit(ctrl.step)`` of the same pure controller, XLA's default CPU options.

Both run on one device (the README's default ``Execution()``), from the same state, x0 and params; each carries its
own state from call to call, as a control loop does. The documented path must be the faster or equal
(``summary.targets``): faster where it takes YNNPACK's kernels, and equal where its ``cpu_matmul="auto"`` keeps
XLA's (``documented_kernels`` "xla": the step's largest product reaches
:data:`~pixelmpc_jax.devices.AUTO_XLA_FROM_MACS`), where it compiles the plain jit's own program
(``tests/test_sample_devices.py`` compares the two compiled programs' text) and the timed ratio is noise about 1.
"""

from __future__ import annotations

import jax

from pixelmpc_jax.apps.bench import problems
from pixelmpc_jax.apps.bench.measure import make_row, measure_interleaved
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib

GROUP = "jit_paths"
SAMPLES = (512, 2048)
HORIZON = 80
DOCUMENTED = "documented: devices.compile_controller(ctrl).step"
PLAIN = "plain: jax.jit(ctrl.step)"


def _carried(step, state, x0, params):
    """A zero-argument call of ``step`` carrying its own MPPI state from call to call."""
    holder = {"state": state}

    def call():
        u0, holder["state"], info = step(holder["state"], x0, params)
        return u0, info.min_cost

    return call


def jit_path_rows(samples=SAMPLES, horizon: int = HORIZON, t_f: float = 1.0, repeats: int = 30) -> list[dict]:
    """Per N: the documented path's row, the plain jit's row, ``plain_over_documented`` (median over median;
    above 1: the documented path is faster) and ``documented_kernels`` ("ynnpack" or "xla": the kernels the
    documented path chose at its first call) on both rows."""
    rows = []
    for n in samples:
        problem = problems.pixelmpc_problem(n, horizon, t_f, sample_devices=1)  # the documented path, one device
        plain = jax.jit(pixelmpc_lib.make_pixelmpc(problem.config).step)
        stats = measure_interleaved({
            DOCUMENTED: _carried(problem.ctrl.step, problem.state, problem.x0, problem.params),
            PLAIN: _carried(plain, problem.state, problem.x0, problem.params),
        }, repeats=repeats)
        ratio = stats[PLAIN]["median_ms"] / stats[DOCUMENTED]["median_ms"]
        kernels = "xla" if problem.ctrl.step_options() is None else "ynnpack"
        for name in (DOCUMENTED, PLAIN):
            rows.append(make_row(GROUP, name, n, horizon, stats[name], t_f=t_f, sample_devices=1,
                                 plain_over_documented=ratio, documented_kernels=kernels))
    return rows
