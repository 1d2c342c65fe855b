"""Median step time of the quadrotor MPPI at the paper's sizes (N=512, T=80, K=1).

    python benchmarks/mppi_step.py [--samples 512] [--horizon 80] [--repeats 50]

The step is the public jitted ``ctrl.step`` (inputs validated, one compiled call), timed after
compilation with ``block_until_ready``; the state changes every call as in a control loop.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp

from pixelmpc_jax.control import costs
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi
from pixelmpc_jax.dynamics import quadrotor

try:
    from benchmarks.timing import device_description, time_call
except ImportError:  # run as a script from the benchmarks folder
    from timing import device_description, time_call


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=512)
    parser.add_argument("--horizon", type=int, default=80)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args(argv)

    params = quadrotor.QuadParams()
    lo, hi = params.control_bounds()
    config = MPPIConfig(num_samples=args.samples, horizon=args.horizon, dt=0.025,
                        noise_sigma=(0.2, 0.2, 0.3, 2.2), u_min=tuple(lo.tolist()), u_max=tuple(hi.tolist()))
    weights = costs.WaypointWeights()
    ctrl = make_mppi(
        config,
        lambda x, u, p: quadrotor.step(x, u, config.dt, params),
        lambda x, u, t, p: costs.waypoint_cost(x, u, p, weights),
    )
    state = ctrl.init(jax.random.PRNGKey(0), quadrotor.hover_control(params))
    x = quadrotor.hover_state((0.0, 0.0, 2.0))
    waypoint = jnp.asarray([5.0, 0.0, 2.0, 0.0])
    holder = {"state": state, "x": x}

    def call():
        u, holder["state"], info = ctrl.step(holder["state"], holder["x"], waypoint)
        holder["x"] = quadrotor.step(holder["x"], u, config.dt, params)
        return u, info.min_cost

    result = time_call(call, repeats=args.repeats)
    device = device_description()
    result.update(num_samples=args.samples, horizon=args.horizon, device=device)
    rollouts_per_s = args.samples * args.horizon / (result["median_ms"] / 1e3)
    print(f"device: {device['platform']} ({device['device_kind']}; {device['cpu_model']}, "
          f"{device['cpu_count']} cores), jax {device['jax']}")
    print(f"quadrotor MPPI step, N={args.samples}, T={args.horizon}: median {result['median_ms']:.2f} ms "
          f"(mean {result['mean_ms']:.2f} +- {result['two_sigma_ms']:.2f} ms 2sigma, max {result['max_ms']:.2f} ms, "
          f"{args.repeats} repeats); {rollouts_per_s / 1e6:.2f} M model steps/s")
    print(json.dumps({k: v for k, v in result.items() if k != "device"}))
    return result


if __name__ == "__main__":
    main()
