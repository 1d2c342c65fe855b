"""The named controllers as episode policies: "mppi" (nominal MPPI) and "pixelmpc". The race app, the experiment
grids and DOF data collection build their policies here, from one
:class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig`.
"""

from __future__ import annotations

from pixelmpc_jax.devices import Execution
from pixelmpc_jax.sim import policies

CONTROLLERS = ("mppi", "pixelmpc")


def make_policy(controller: str, config=None, execution: Execution | None = None) -> policies.Policy:
    """The named controller as an episode Policy.

    Args:
        controller: "mppi", the paper's nominal MPPI, flying ``config.mppi``, ``config.racing``,
            ``config.model_latency_ticks`` and ``config.disturbance_time_constant_s``; or
            "pixelmpc", flying all of ``config``.
        config: a :class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig` (None: its defaults).
        execution: how the controller's step runs (:class:`~pixelmpc_jax.devices.Execution`: its samples over
            how many devices), not what it computes; None: on one device.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}; choose one of {', '.join(CONTROLLERS)}")
    from pixelmpc_jax.control.pixelmpc import ControllerConfig

    config = ControllerConfig() if config is None else config
    if controller == "mppi":
        return policies.nominal_mppi_policy(config.mppi, config.racing, latency_ticks=config.model_latency_ticks,
                                            disturbance_tau=config.disturbance_time_constant_s, execution=execution)
    return policies.pixelmpc_policy(config, execution=execution)
