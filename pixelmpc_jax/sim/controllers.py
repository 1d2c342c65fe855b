"""The named controllers as episode policies: "mppi" (nominal MPPI) and "pixelmpc", with further settings by
field name (``options``). The race app, the experiment grids and DOF data collection build their policies here.
"""

from __future__ import annotations

import dataclasses

from pixelmpc_jax.sim import episode as episode_lib

CONTROLLERS = ("mppi", "pixelmpc")
OPTION_PREFIXES = ("mppi.", "racing.")


def split_options(options: dict | None) -> tuple[dict, dict, dict]:
    """Split controller options into (PixelMPCConfig fields, MPPIConfig fields, RacingCostConfig fields).

    A key ``"mppi.NAME"`` sets ``MPPIConfig.NAME``, ``"racing.NAME"`` sets ``RacingCostConfig.NAME``, any
    other key a field of :class:`~pixelmpc_jax.control.pixelmpc.PixelMPCConfig`. Unknown names raise a
    ValueError naming them and the accepted fields.
    """
    from pixelmpc_jax.control.costs import RacingCostConfig
    from pixelmpc_jax.control.mppi import MPPIConfig
    from pixelmpc_jax.control.pixelmpc import PixelMPCConfig

    groups: tuple[dict, dict, dict] = ({}, {}, {})
    kinds = ((PixelMPCConfig, ""), (MPPIConfig, "mppi."), (RacingCostConfig, "racing."))
    for key, value in (options or {}).items():
        index = 1 if key.startswith("mppi.") else 2 if key.startswith("racing.") else 0
        cls, prefix = kinds[index]
        name = key[len(prefix):]
        fields = {f.name for f in dataclasses.fields(cls)} - {"mppi", "racing"}
        if name not in fields:
            raise ValueError(f"unknown controller option {key!r}: {cls.__name__} has the fields "
                             f"{', '.join(sorted(prefix + f for f in fields))}")
        groups[index][name] = value
    return groups


def make_policy(controller: str, temperature: float | None = None, num_samples: int = 512,
                pixel_model: str = "dof", t_f: float = 1.0, c_pixel: float = 9e6, options: dict | None = None):
    """The named controller as an episode Policy ("mppi": nominal MPPI; "pixelmpc": PixelMPC).

    ``options`` sets further configuration fields by name (see :func:`split_options`); the MPPI and racing
    options apply to nominal MPPI too, the PixelMPC ones only to PixelMPC.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}; choose one of {', '.join(CONTROLLERS)}")
    pixel_options, mppi_options, racing_options = split_options(options)
    if controller == "mppi" and pixel_options:
        raise ValueError(f"options {sorted(pixel_options)} configure PixelMPC, not nominal MPPI")
    kwargs = {"num_samples": num_samples}
    if temperature is not None:
        kwargs["temperature"] = temperature
    mppi_config = dataclasses.replace(episode_lib.paper_mppi_config(**kwargs), **mppi_options)
    from pixelmpc_jax.control.costs import RacingCostConfig

    racing_config = RacingCostConfig(**racing_options)
    if controller == "mppi":
        return episode_lib.nominal_mppi_policy(mppi_config, racing_config)
    from pixelmpc_jax.control.pixelmpc import PixelMPCConfig

    config = PixelMPCConfig(mppi=mppi_config, racing=racing_config, t_f=t_f, c_pixel=c_pixel,
                            pixel_model=pixel_model, **pixel_options)
    return episode_lib.pixelmpc_policy(config)
