"""The limit: the floating-point work of one PixelMPC step, and this device's matrix-multiply rate.

How the work is counted (``step_flops``):

* DOF, analytically: ``2 x sum(fan_in x fan_out)`` multiply-adds of the dense layers (10-128-128-128-2:
  2 x 34,304 = 68,608 flops) plus the bias adds and ReLUs (770), per evaluation; N x n_f evaluations.
  The DOF's matmul flops are what its rate is compared with the measured matmul rate.
* Robot dynamics, racing cost, pixel cost (with the DOF's input/output scaling and PolarToEuler): XLA's
  own count (``compiled.cost_analysis()['flops']``, one flop per elementwise op, transcendentals apart)
  of ONE step over a batch (the dynamics and the pixel part vmapped, the racing cost ``costs.racing_costs``
  of the batch at one horizon step), divided by the batch: per sample-step figures, times N x T (dynamics,
  racing cost) or N x n_f (pixel part).
* MPPI bookkeeping (noise, clipping, weights, update): ``MPPI_FLOPS_PER_SAMPLE_STEP x m`` per sample-step
  (about 8 elementwise ops per control channel), counted by hand.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pixelmpc_jax.apps.bench.measure import make_row, measure
from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.dynamics import dof as dof_lib
from pixelmpc_jax.dynamics import quadrotor

GROUP = "roofline"
MPPI_FLOPS_PER_SAMPLE_STEP = 8  # per control channel: noise scale, add, clip (2), eps, weight x eps, sum, ...


def dof_flops_per_eval(layer_sizes=dof_lib.LAYER_SIZES) -> dict:
    """Flops of one DOF evaluation: ``matmul`` = 2 x sum(fan_in x fan_out); ``elementwise`` = bias adds and
    hidden-layer ReLUs."""
    pairs = list(zip(layer_sizes[:-1], layer_sizes[1:]))
    matmul = 2 * sum(a * b for a, b in pairs)
    elementwise = sum(b for _, b in pairs) + sum(layer_sizes[1:-1])
    return {"matmul": matmul, "elementwise": elementwise}


def step_flops(num_samples: int, horizon: int, pixel_steps: int, per_step: dict, control_dim: int = 4,
               layer_sizes=dof_lib.LAYER_SIZES) -> dict:
    """Flops of one PixelMPC step (K = 1 iteration).

    Args:
        per_step: flops per sample-step of ``dynamics`` (robot), ``racing`` (cost), ``pixel`` (the pixel model
            and cost besides the DOF's dense layers).

    Returns:
        dof_matmul, dof_elementwise, dynamics, racing, pixel, mppi and total, in flops.
    """
    n, t, nf = num_samples, horizon, pixel_steps
    dof = dof_flops_per_eval(layer_sizes)
    out = {
        "dof_matmul": n * nf * dof["matmul"],
        "dof_elementwise": n * nf * dof["elementwise"],
        "dynamics": n * t * per_step["dynamics"],
        "racing": n * t * per_step["racing"],
        "pixel": n * nf * per_step["pixel"],
        "mppi": n * t * control_dim * MPPI_FLOPS_PER_SAMPLE_STEP,
    }
    out["total"] = sum(out.values())
    return out


def _xla_flops(fn, *args) -> float:
    analysis = jax.jit(fn).lower(*args).compile().cost_analysis()
    if isinstance(analysis, list | tuple):
        analysis = analysis[0]
    return float(analysis.get("flops", 0.0))


def per_sample_step_flops(problem, batch: int = 256) -> dict:
    """XLA's flop count per sample-step of the robot step, the racing cost and the pixel part (pixel model
    and cost, without the DOF's dense layers), from one step over ``batch`` samples."""
    config = problem.config
    params = problem.params
    quad_params = quadrotor.QuadParams()
    X = jnp.broadcast_to(problem.x0, (batch, problem.x0.shape[0]))
    U = jnp.broadcast_to(quadrotor.hover_control(quad_params), (batch, 4))
    steps = jnp.zeros((1,), jnp.int32)
    dt = config.mppi.dt

    def dynamics(X, U):
        return jax.vmap(lambda x, u: quadrotor.step(x[:10], u, dt, quad_params))(X, U)

    def racing(X):  # the batch as the samples of one horizon step, (1, batch, 10)
        return costs.racing_costs(X[None, :, :10], steps, params.racing, config.racing)

    def pixel_full(X, U):
        def one(x, u):
            uv = x[10:] + dt * dof_lib.pixel_velocity(params.dof, x[3:7], x[10:], u)
            return pixelmpc_lib.pixel_cost(uv, config) + jnp.sum(uv)
        return jax.vmap(one)(X, U)

    per = {"dynamics": _xla_flops(dynamics, X, U) / batch, "racing": _xla_flops(racing, X) / batch}
    dof = dof_flops_per_eval()
    # XLA counts the dense layers as 2 x MACs like we do; take them out to leave the pixel part's remainder
    per["pixel"] = max(_xla_flops(pixel_full, X, U) / batch - dof["matmul"] - dof["elementwise"], 0.0)
    return per


def matmul_rows(smoke: bool = False, repeats: int = 30) -> list[dict]:
    """float32 matmul rate of this device with JAX: the DOF's hidden-layer shape (N x 128 @ 128 x 128, N = 512
    and N = 512 x 40, the DOF's rows in one step) and a large square one."""
    shapes = [(512, 128, 128), (20480, 128, 128), (2048, 2048, 2048)]
    if smoke:
        shapes = [(64, 128, 128)]
    rows = []
    for m, k, n in shapes:
        a = jax.random.normal(jax.random.PRNGKey(0), (m, k), jnp.float32)
        b = jax.random.normal(jax.random.PRNGKey(1), (k, n), jnp.float32)
        fn = jax.jit(jnp.matmul)
        stats = measure(lambda a=a, b=b, fn=fn: fn(a, b), repeats=repeats)
        flops = 2 * m * k * n
        rows.append(make_row(GROUP, f"matmul f32 {m}x{k} @ {k}x{n}", None, None, stats, flops=flops,
                             gflops_per_s=flops / stats["median_ms"] / 1e6,
                             gflops_per_s_best=flops / stats["min_ms"] / 1e6))
    return rows


def matmul_rate(rows: list[dict]) -> float:
    """The device's matmul rate (flop/s): the highest median rate among the measured shapes."""
    return max(r["gflops_per_s"] for r in rows if r.get("gflops_per_s")) * 1e9
