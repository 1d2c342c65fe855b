"""The problems the benchmarks time: PixelMPC and nominal MPPI on the AlphaPilot course, and MPPI-Generic's
differential-drive cost-map problem. Each builder returns everything a timed call needs, so the JAX rows,
the torch peer and the tests share one definition of the work.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.mppi import MPPIConfig, MPPIState, make_mppi
from pixelmpc_jax.devices import CompiledController, Execution, compile_controller
from pixelmpc_jax.dynamics import dof as dof_lib
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics import vdof as vdof_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

TARGET_SPEED = 14.0  # m/s, the paper's Table II speed
START_SPEED = 5.0  # m/s along the path tangent at x0, so the rollouts fly (not hover)
START_PIXEL = (0.55, 0.45)  # the detector's target pixel at x0, normalised
START_BOX_SIZE = 0.1  # the detected gate's apparent size at x0 (vdof), normalised


def bench_dof_params() -> dof_lib.DOFParams:
    """The shipped DOF weights (the ones the controller flies with), or seeded random weights of the same
    architecture where the package ships none; timing does not depend on the values."""
    loader = getattr(dof_lib, "load_packaged_dof", None)
    if loader is not None:
        try:
            return loader()
        except (FileNotFoundError, ValueError):
            pass
    return dof_lib.init_dof_params(jax.random.PRNGKey(0))


class ControllerProblem(NamedTuple):
    """One controller and the inputs of its step.

    Attributes:
        ctrl: the controller compiled (on its first call) as its execution says.
        state: its initial MPPIState.
        x0: (n,) the state the step plans from.
        params: the dynamic params pytree of the step.
        config: the ControllerConfig (or MPPIConfig for the nominal/diff-drive problems).
    """

    ctrl: CompiledController
    state: MPPIState
    x0: jax.Array
    params: Any
    config: Any


def step_progress(horizon: int, dt: float = timing.CONTROL_DT, speed: float = TARGET_SPEED) -> jax.Array:
    """(T,) the arc length each horizon step's path window is cut around: flying the path at ``speed``."""
    return speed * dt * jnp.arange(1, horizon + 1, dtype=jnp.float32)


# one compilation instead of dozens of eager ops (seconds on a loaded 2-core machine)
_racing_params = jax.jit(costs.racing_params, static_argnames=("config",))


def pixelmpc_problem(num_samples: int = 512, horizon: int = 80, t_f: float = 1.0, track=None,
                     dof_params=None, seed: int = 0, sample_devices: int = 1,
                     pixel_model: str = "dof") -> ControllerProblem:
    """The full PixelMPC step (a learned pixel model over t_f, racing + pixel cost) at the given sizes.

    ``t_f = 0`` gives the same 12-state controller without the pixel model (the DOF part's baseline);
    ``sample_devices`` is ``Execution.sample_devices`` (x0 and the params are then placed on every device
    once, as a control loop keeps them); ``pixel_model`` "vdof" flies the packaged vdof weights (the pixel state
    then carries the box size too).
    """
    track = track or course_lib.load_course()
    if pixel_model == "vdof":
        dof_params = vdof_lib.load_packaged_vdof() if dof_params is None else dof_params
    else:
        dof_params = bench_dof_params() if dof_params is None else dof_params
    config = pixelmpc_lib.ControllerConfig(mppi=pixelmpc_lib.paper_mppi_config(num_samples, horizon), t_f=t_f,
                                           pixel_model=pixel_model)
    ctrl = compile_controller(pixelmpc_lib.make_pixelmpc(config), Execution(sample_devices=sample_devices))
    racing = _racing_params(track, step_progress(horizon, config.mppi.dt), TARGET_SPEED, config.racing)
    params = pixelmpc_lib.PixelMPCParams(racing=racing, dof=dof_params, target_active=jnp.asarray(True),
                                         target_centre=track.gates.centre[0], target_normal=track.gates.normal[0],
                                         camera=camera_lib.default_camera())
    x = track.start.at[quadrotor.VEL].set(track.path_tangents[0] * START_SPEED)
    pixel = START_PIXEL + ((START_BOX_SIZE,) if pixel_model == "vdof" else ())
    x0 = jnp.concatenate([x, jnp.asarray(pixel, jnp.float32)])
    state = ctrl.init(jax.random.PRNGKey(seed), quadrotor.hover_control(quadrotor.QuadParams()))
    return _placed(ControllerProblem(ctrl, state, x0, params, config))


def _placed(problem: ControllerProblem) -> ControllerProblem:
    """The problem with x0 and the params on every device of a controller that splits its samples."""
    if problem.ctrl.shardings is None:
        return problem
    x0, params = jax.device_put((problem.x0, problem.params), problem.ctrl.shardings.replicated)
    return problem._replace(x0=x0, params=params)


def nominal_problem(num_samples: int = 512, horizon: int = 80, track=None, seed: int = 0,
                    sample_devices: int = 1) -> ControllerProblem:
    """Nominal MPPI (the paper's baseline): the 10-state quadrotor with the racing cost, no pixel model;
    ``sample_devices`` as in :func:`pixelmpc_problem`."""
    track = track or course_lib.load_course()
    mppi_config = pixelmpc_lib.paper_mppi_config(num_samples, horizon)
    cost_config = costs.RacingCostConfig()
    quad_params = quadrotor.QuadParams()
    dt = mppi_config.dt
    ctrl = compile_controller(pixelmpc_lib.make_nominal_mppi(mppi_config, cost_config, quad_params),
                              Execution(sample_devices=sample_devices))
    params = _racing_params(track, step_progress(horizon, dt), TARGET_SPEED, cost_config)
    x0 = track.start.at[quadrotor.VEL].set(track.path_tangents[0] * START_SPEED)
    state = ctrl.init(jax.random.PRNGKey(seed), quadrotor.hover_control(quad_params))
    return _placed(ControllerProblem(ctrl, state, x0, params, mppi_config))


def control_loop_call(problem: ControllerProblem):
    """A zero-argument call of the compiled step that carries the MPPI state from call to call, as a
    control loop does (the plan and key change every call; x0 and params stay)."""
    holder = {"state": problem.state}

    def call():
        u0, holder["state"], info = problem.ctrl.step(holder["state"], problem.x0, problem.params)
        return u0, info.min_cost

    return call


# --------------------------------------------------------------------------------------------------
# MPPI-Generic's benchmark problem: a differential-drive robot in a 2-D cost map.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DiffDriveConfig:
    """MPPI-Generic's published benchmark settings (arXiv 2409.07563): dt 0.02 s, horizon 100, lambda 1,
    sigma 0.2 on both controls. The map and the weights are ours (the paper gives the problem, not its
    numbers): a 10 m x 10 m map at 5 cm, four round obstacles, goal at (9, 9)."""

    dt: float = 0.02
    horizon: int = 100
    temperature: float = 1.0
    sigma: float = 0.2
    map_cells: int = 200
    resolution: float = 0.05  # m per cell
    goal: tuple[float, float] = (9.0, 9.0)
    goal_weight: float = 1.0
    obstacle_weight: float = 100.0
    lookup: str = "bilinear"  # or "nearest"


def diff_drive_step(x: jax.Array, u: jax.Array, dt: float) -> jax.Array:
    """Unicycle kinematics, one Euler step: x = [px, py, heading], u = [v, omega]. -> (3,)."""
    heading = x[2]
    return x + dt * jnp.stack([u[0] * jnp.cos(heading), u[0] * jnp.sin(heading), u[1]])


def costmap_lookup(costmap: jax.Array, xy: jax.Array, origin: jax.Array, resolution: float,
                   method: str = "bilinear") -> jax.Array:
    """The cost of a 2-D map at world point xy (2,). -> ().

    ``costmap[row, col]`` is the value at the centre of cell (col, row), i.e. at
    ``origin + (col + 0.5, row + 0.5) * resolution``. ``"nearest"`` returns the value of the cell that holds
    xy; ``"bilinear"`` interpolates between the four surrounding cell centres. Points outside the map read
    the nearest edge value (clamped), like a texture lookup with clamp addressing.
    """
    rows, cols = costmap.shape
    g = (xy - origin) / resolution  # continuous cell coordinates, (col, row)
    if method == "nearest":
        col = jnp.clip(jnp.floor(g[0]), 0, cols - 1).astype(jnp.int32)
        row = jnp.clip(jnp.floor(g[1]), 0, rows - 1).astype(jnp.int32)
        return costmap[row, col]
    if method != "bilinear":
        raise ValueError(f"method must be 'bilinear' or 'nearest', got {method!r}")
    c = jnp.clip(g[0] - 0.5, 0.0, cols - 1.0)
    r = jnp.clip(g[1] - 0.5, 0.0, rows - 1.0)
    c0 = jnp.minimum(jnp.floor(c), cols - 2).astype(jnp.int32) if cols > 1 else jnp.zeros((), jnp.int32)
    r0 = jnp.minimum(jnp.floor(r), rows - 2).astype(jnp.int32) if rows > 1 else jnp.zeros((), jnp.int32)
    c1, r1 = jnp.minimum(c0 + 1, cols - 1), jnp.minimum(r0 + 1, rows - 1)
    fc, fr = c - c0, r - r0
    top = costmap[r0, c0] * (1 - fc) + costmap[r0, c1] * fc
    bottom = costmap[r1, c0] * (1 - fc) + costmap[r1, c1] * fc
    return top * (1 - fr) + bottom * fr


def make_costmap(config: DiffDriveConfig = DiffDriveConfig()) -> np.ndarray:
    """(cells, cells) float32 obstacle cost in [0, 1]: four round obstacles with smooth 0.3 m edges."""
    n, res = config.map_cells, config.resolution
    centres = res * (np.arange(n) + 0.5)
    px, py = np.meshgrid(centres, centres)  # px varies along columns, py along rows
    cost = np.zeros((n, n), np.float32)
    for cx, cy, radius in ((3.0, 3.0, 1.0), (6.5, 4.0, 0.8), (4.0, 7.0, 0.9), (7.5, 7.5, 0.6)):
        d = np.hypot(px - cx, py - cy) - radius
        cost = np.maximum(cost, np.clip(1.0 - d / 0.3, 0.0, 1.0))
    return cost.astype(np.float32)


def diff_drive_problem(num_samples: int, config: DiffDriveConfig = DiffDriveConfig(),
                       seed: int = 0) -> ControllerProblem:
    """MPPI-Generic's benchmark in our generic MPPI: N samples, T = 100, K = 1 iteration per step."""
    mppi_config = MPPIConfig(num_samples=num_samples, horizon=config.horizon, dt=config.dt,
                             noise_sigma=(config.sigma, config.sigma), temperature=config.temperature)
    goal = jnp.asarray(config.goal, jnp.float32)

    def dynamics(x, u, p):
        return diff_drive_step(x, u, config.dt)

    def running_cost(x, u, t, p):
        obstacle = costmap_lookup(p["costmap"], x[:2], p["origin"], config.resolution, config.lookup)
        return config.goal_weight * jnp.sum((x[:2] - goal) ** 2) + config.obstacle_weight * obstacle

    ctrl = compile_controller(make_mppi(mppi_config, dynamics, running_cost))
    params = {"costmap": jnp.asarray(make_costmap(config)), "origin": jnp.zeros(2, jnp.float32)}
    x0 = jnp.asarray([1.0, 1.0, 0.785], jnp.float32)
    state = ctrl.init(jax.random.PRNGKey(seed), jnp.asarray([0.5, 0.0], jnp.float32))
    return ControllerProblem(ctrl, state, x0, params, mppi_config)
