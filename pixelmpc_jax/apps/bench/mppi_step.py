"""Median step time of the quadrotor MPPI at the paper's sizes (N=512, T=80, K=1).

    pixelmpc bench mppi-step [--samples 512] [--horizon 80] [--repeats 50] [--cost racing|waypoint]

The step is the compiled ``step`` of :func:`~pixelmpc_jax.devices.compile_controller` (inputs validated, one
compiled call), timed after compilation with ``block_until_ready``; the state changes every call as in a control
loop.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.apps.bench.measure import measure, spread
from pixelmpc_jax.control import costs
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi
from pixelmpc_jax.control.pixelmpc import PAPER_NOISE_SIGMA
from pixelmpc_jax.control.rollout import TrajectoryCost
from pixelmpc_jax.devices import compile_controller
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.platform_info import device_description

COSTS = ("racing", "waypoint")  # Eq. (19) on the AlphaPilot course; the demo's waypoint cost


def run_mppi_step(samples: int = 512, horizon: int = 80, repeats: int = 50, cost: str = "racing") -> dict:
    """Time the step at ``samples`` x ``horizon`` with the ``cost`` of :data:`COSTS`, ``repeats`` times; prints the
    device, the figures and a JSON line, and returns them."""
    params = quadrotor.QuadParams()
    lo, hi = params.control_bounds()
    config = MPPIConfig(num_samples=samples, horizon=horizon, dt=timing.CONTROL_DT,
                        noise_sigma=PAPER_NOISE_SIGMA, u_min=tuple(lo.tolist()), u_max=tuple(hi.tolist()))
    if cost == "racing":
        from pixelmpc_jax.world import course as course_lib
        track = course_lib.load_course()
        cost_config = costs.RacingCostConfig()
        x = track.start
        cost_params = costs.racing_params(track, jnp.linspace(0.0, 25.0, horizon), 14.0, cost_config)

        running_cost = TrajectoryCost(lambda X, U, steps, p: costs.racing_costs(X, steps, p, cost_config))
    else:
        weights = costs.WaypointWeights()
        x = quadrotor.hover_state((0.0, 0.0, 2.0))
        cost_params = jnp.asarray([5.0, 0.0, 2.0, 0.0])

        def running_cost(x, u, t, p):
            return costs.waypoint_cost(x, u, p, weights)

    ctrl = compile_controller(make_mppi(config, lambda x, u, p: quadrotor.step(x, u, config.dt, params), running_cost))
    state = ctrl.init(jax.random.PRNGKey(0), quadrotor.hover_control(params))
    holder = {"state": state, "x": x}

    def call():
        u, holder["state"], info = ctrl.step(holder["state"], holder["x"], cost_params)
        holder["x"] = quadrotor.step(holder["x"], u, config.dt, params)
        return u, info.min_cost

    result = measure(call, repeats=repeats)
    device = device_description()
    result.update(num_samples=samples, horizon=horizon, device=device)
    rollouts_per_s = samples * horizon / (result["median_ms"] / 1e3)
    print(f"device: {device['platform']} ({device['device_kind']}; {device['cpu_model']}, "
          f"{device['cpu_count']} cores), jax {device['jax']}")
    print(f"quadrotor MPPI step ({cost} cost), N={samples}, T={horizon}: {spread(result, 2, repeats)}; "
          f"{rollouts_per_s / 1e6:.2f} M model steps/s")
    print(json.dumps({k: v for k, v in result.items() if k != "device"}))
    return result
