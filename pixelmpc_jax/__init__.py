"""pixelmpc_jax: perception-aware sampling MPC (PixelMPC) with Deep Optical Flow dynamics, in JAX.

The package's front door: what a program calls is imported from here and listed in ``__all__`` (a test holds the
list, so a rename is a deliberate change); every other module is internal and may change. The names, by job:

- the generic controller: :func:`make_mppi` over one sample's ``dynamics`` and ``running_cost``, its
  :class:`MPPIConfig`, its state and info (:class:`MPPIState`, :class:`MPPIInfo`) and the pure init/step pair
  (:class:`Controller`);
- running a step fast: :func:`compile_controller` with an :class:`Execution` (its step jitted with the library's
  compiler options, its inputs checked, its samples over devices);
- PixelMPC: :func:`make_pixelmpc`, its :class:`ControllerConfig` and :class:`PixelMPCParams`; nominal MPPI on the
  racing cost (:func:`make_nominal_mppi`, :func:`paper_mppi_config`), the racing cost's :class:`RacingCostConfig`
  and :func:`racing_params`;
- the vehicle and the pixel models: the :mod:`quadrotor` module, :func:`load_packaged_dof` and
  :func:`load_packaged_vdof` (the weights shipped in the package), the camera (:func:`default_camera`);
- the world: :func:`make_world` (:class:`World`), the courses (:func:`load_course`, :func:`make_course`,
  :func:`course_from_gates`);
- the closed loop: :func:`fly` (one's own controller or course), :func:`make_policy`, :class:`Policy`,
  :func:`make_runner`, :class:`EpisodeConfig`, :class:`EpisodeLog`;
- races: :func:`preset` (:data:`PRESETS`), :func:`nominal_of`, :class:`RaceSpec`, :func:`race` and its
  :class:`RaceResult`.
"""

from pixelmpc_jax.apps.racing.presets import PRESETS, nominal_of, preset
from pixelmpc_jax.apps.racing.race import RaceResult, fly, race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.costs import RacingCostConfig, racing_params
from pixelmpc_jax.control.mppi import Controller, MPPIConfig, MPPIInfo, MPPIState, make_mppi
from pixelmpc_jax.control.pixelmpc import (
    ControllerConfig,
    PixelMPCParams,
    make_nominal_mppi,
    make_pixelmpc,
    paper_mppi_config,
)
from pixelmpc_jax.devices import CompiledController, Execution, compile_controller
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics.dof import load_packaged_dof
from pixelmpc_jax.dynamics.vdof import load_packaged_vdof
from pixelmpc_jax.sim.controllers import make_policy
from pixelmpc_jax.sim.env import World, make_world
from pixelmpc_jax.sim.episode import EpisodeConfig, EpisodeLog, make_runner
from pixelmpc_jax.sim.policies import Policy
from pixelmpc_jax.world.camera import default_camera
from pixelmpc_jax.world.course import course_from_gates, load_course, make_course

__version__ = "0.1.0"

__all__ = [
    # the generic controller
    "MPPIConfig",
    "MPPIState",
    "MPPIInfo",
    "Controller",
    "make_mppi",
    # running a step fast
    "Execution",
    "CompiledController",
    "compile_controller",
    # PixelMPC and nominal MPPI on the racing cost
    "ControllerConfig",
    "PixelMPCParams",
    "make_pixelmpc",
    "make_nominal_mppi",
    "paper_mppi_config",
    "RacingCostConfig",
    "racing_params",
    # the vehicle, the pixel models' packaged weights, the camera
    "quadrotor",
    "load_packaged_dof",
    "load_packaged_vdof",
    "default_camera",
    # the world and its courses
    "World",
    "make_world",
    "load_course",
    "make_course",
    "course_from_gates",
    # the closed loop
    "fly",
    "Policy",
    "make_policy",
    "EpisodeConfig",
    "EpisodeLog",
    "make_runner",
    # races
    "PRESETS",
    "preset",
    "nominal_of",
    "RaceSpec",
    "race",
    "RaceResult",
    "__version__",
]
