"""The hover-to-waypoint demo: MPPI on the paper's quadrotor model flying to a point and holding it.

The closed loop is one ``lax.scan`` over control ticks; the model is its own plant here (the
FlightGoggles-like plant of ``sim/plant.py`` is used by the racing loop).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.control import costs
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi
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
            u, mppi_state, info = ctrl.step(mppi_state, x, target)
            x_next = quadrotor.step(x, u, dt, params)
            return (x_next, mppi_state), (x_next, u, info.min_cost)

        _, (states, controls, min_costs) = jax.lax.scan(tick, (x0, state), None, length=num_ticks)
        return WaypointFlight(jnp.concatenate([x0[None], states]), controls, min_costs)

    return run(jax.random.PRNGKey(seed), start, waypoint)



def run_demo(distance: float = 5.0, seconds: float = 4.0, samples: int = 512, seed: int = 0, out=None) -> dict:
    """``pixelmpc demo``: fly from hover at 2 m to a waypoint ``distance`` ahead for ``seconds``, print a summary
    and, with ``out``, write ``demo.json`` and ``demo.png``; returns the summary."""
    import numpy as np

    start = quadrotor.hover_state((0.0, 0.0, 2.0))
    waypoint = jnp.asarray([distance, 0.0, 2.0, 0.0])
    config = waypoint_config(num_samples=samples)
    print(f"MPPI hover-to-waypoint: {distance:.1f} m, N={config.num_samples}, T={config.horizon}, "
          f"{seconds:.1f} s at {1 / config.dt:.0f} Hz ...")
    flight = fly_to_waypoint(start, waypoint, num_ticks=max(1, int(round(seconds / config.dt))), seed=seed,
                             config=config)
    states = np.asarray(flight.states)
    error = np.linalg.norm(states[:, :3] - np.asarray(waypoint[:3]), axis=1)
    times = np.arange(len(states)) * config.dt
    reached = np.nonzero(error < 0.2)[0]
    summary = {
        "final_position": states[-1, :3].round(3).tolist(),
        "final_error_m": float(error[-1]),
        "time_to_within_0.2m_s": float(times[reached[0]]) if reached.size else None,
        "max_error_last_second_m": float(error[times >= times[-1] - 1.0].max()),
    }
    for key, value in summary.items():
        print(f"  {key}: {value}")
    if out is not None:
        _write_demo(Path(out), summary, times, states, error)
    return summary


def _write_demo(out: Path, summary: dict, times, states, error) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pixelmpc_jax.strict_json import write_json_atomic

    write_json_atomic(out / "demo.json", summary)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    for i, name in enumerate("xyz"):
        ax[0].plot(times, states[:, i], label=name)
    ax[0].set(xlabel="time [s]", ylabel="position [m]", title="position")
    ax[0].legend()
    ax[1].plot(times, error)
    ax[1].set(xlabel="time [s]", ylabel="distance to waypoint [m]", yscale="log", title="error")
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=120)
    plt.close(fig)
    print(f"  wrote {out / 'demo.json'} and {out / 'demo.png'}")
