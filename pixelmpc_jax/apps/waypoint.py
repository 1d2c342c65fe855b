"""The hover-to-waypoint demo: MPPI on the paper's quadrotor model flying to a point and holding it.

The closed loop is one ``lax.scan`` over control ticks; the model is its own plant here (the
FlightGoggles-like plant of ``sim/plant.py`` is used by the racing loop).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.control import costs
from pixelmpc_jax.control.mppi import MPPIConfig, MPPIInfo, make_mppi
from pixelmpc_jax.dynamics import quadrotor


class WaypointFlight(NamedTuple):
    """A flown trajectory. states: (S+1, 10), controls: (S, 4), min_costs: (S,)."""

    states: jax.Array
    controls: jax.Array
    min_costs: jax.Array


def waypoint_config(num_samples: int = 512, horizon: int = 40, dt: float = timing.CONTROL_DT,
                    params: quadrotor.QuadParams | None = None) -> MPPIConfig:
    """MPPI settings for the demo: the paper's dt and noise on rates, a 1 s horizon, model limits."""
    params = params or quadrotor.QuadParams()
    lo, hi = params.control_bounds()
    return MPPIConfig(
        num_samples=num_samples, horizon=horizon, dt=dt, noise_sigma=(0.3, 0.3, 0.3, 2.0),
        temperature=1.0, u_min=tuple(lo.tolist()), u_max=tuple(hi.tolist()),
    )


def fly_to_waypoint(
    start: jax.Array,
    waypoint: jax.Array,
    num_ticks: int = 160,
    seed: int = 0,
    config: MPPIConfig | None = None,
    params: quadrotor.QuadParams | None = None,
    weights: costs.WaypointWeights | None = None,
) -> WaypointFlight:
    """Fly from ``start`` (10,) to ``waypoint`` [px, py, pz, yaw] (4,) for ``num_ticks`` control ticks."""
    params = params or quadrotor.QuadParams()
    config = config or waypoint_config(params=params)
    weights = weights or costs.WaypointWeights()
    start = jnp.asarray(start, jnp.float32)
    waypoint = jnp.asarray(waypoint, jnp.float32)
    if start.shape != (quadrotor.STATE_DIM,):
        raise ValueError(f"start must be a state of shape (10,), got {start.shape}")
    if waypoint.shape != (4,):
        raise ValueError(f"waypoint must be [px, py, pz, yaw] of shape (4,), got {waypoint.shape}")
    dt = config.dt

    def dynamics(x, u, p):
        return quadrotor.step(x, u, dt, params)

    def running_cost(x, u, t, p):
        return costs.waypoint_cost(x, u, p, weights)

    ctrl = make_mppi(config, dynamics, running_cost)

    @jax.jit
    def run(key, x0, target):
        state = ctrl.init(key, quadrotor.hover_control(params))

        def tick(carry, _):
            x, mppi_state = carry
            u, mppi_state, info = ctrl.step_pure(mppi_state, x, target)
            x_next = quadrotor.step(x, u, dt, params)
            return (x_next, mppi_state), (x_next, u, info.min_cost)

        _, (states, controls, min_costs) = jax.lax.scan(tick, (x0, state), None, length=num_ticks)
        return WaypointFlight(jnp.concatenate([x0[None], states]), controls, min_costs)

    return run(jax.random.PRNGKey(seed), start, waypoint)


__all__ = ["WaypointFlight", "fly_to_waypoint", "waypoint_config", "MPPIInfo"]
