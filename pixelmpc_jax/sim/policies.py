"""Policies for the closed loop: the paper's nominal MPPI baseline and PixelMPC, as pure init/act pairs.

A :class:`Policy` is ``init(key, world) -> state``, called once per episode (per-episode constants belong in
the state), and ``act(state, obs, world) -> (u, state, predicted)``, called every tick with the environment's
:class:`~pixelmpc_jax.sim.env.Observation`; ``world`` is what the drone knows of the world
(:class:`~pixelmpc_jax.sim.env.PolicyWorld`: the map, never the course flown). The driver is
:mod:`pixelmpc_jax.sim.episode`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.mppi import MPPIConfig
from pixelmpc_jax.control.pixelmpc import paper_mppi_config
from pixelmpc_jax.devices import Execution, compile_controller
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics import vdof as vdof_lib
from pixelmpc_jax.sim.env import Observation, PolicyWorld


class Policy(NamedTuple):
    """A controller in the loop.

    ``init(key, world) -> state`` once per episode; ``act(state, obs, world) -> (u, state, predicted)`` every
    tick, with ``u`` (4,) the command, ``obs`` the :class:`~pixelmpc_jax.sim.env.Observation`, ``world`` the
    :class:`~pixelmpc_jax.sim.env.PolicyWorld` (the map, the target speed, the camera, the pixel model: no truth;
    the driver hands nothing else) and ``predicted`` the (T+1, n) nominal prediction (its columns past the 10 robot
    states, if any, are the target pixel).
    ``compiler_options``: the XLA options of its controller's step (:func:`~pixelmpc_jax.devices.compile_controller`),
    for the episode's ``jax.jit``.
    """

    init: Callable[[jax.Array, PolicyWorld], Any]
    act: Callable[[Any, Observation, PolicyWorld], tuple[jax.Array, Any, jax.Array]]
    name: str
    compiler_options: Any = None


class RacingPolicyState(NamedTuple):
    """A racing policy's state.

    Attributes:
        mppi: the MPPI controller's state.
        step_progress: (T,) per horizon step, the path progress (m) the last plan predicted (NaN before the
            first plan).
        racing_constants: the racing cost's per-track constants (the path's samples, tangents and speed cap),
            computed once per episode by ``init``.
        pending: (L, 4) the last L commands sent, oldest first, with a model latency of L ticks (None without).
        disturbance: (3,) m/s^2, the estimated external acceleration (None without a disturbance model).
        expected: (10,) the model's prediction of the next tick's estimate (NaN before the first; None without).
        kept: the target's pixel state kept alive while undetected (:class:`KeptPixel`; None without).
    """

    mppi: Any
    step_progress: jax.Array
    racing_constants: costs.RacingConstants
    pending: jax.Array | None = None
    disturbance: jax.Array | None = None
    expected: jax.Array | None = None
    kept: Any = None


class KeptPixel(NamedTuple):
    """The target's pixel state as the controller's pixel model predicts it for this tick, from the last tick's:
    what charges the pixel cost while the detector does not report the target (``target_prior="kept"`` or
    ``"seeded"``).

    Attributes:
        pixel: (P,) the pixel state predicted under the command sent (the nominal prediction's second state).
        valid: () bool, the pixel descends from a detection of ``gate``.
        gate: () int, the target it belongs to (a new target starts unseen).
    """

    pixel: jax.Array
    valid: jax.Array
    gate: jax.Array


DISTURBANCE_MAX = 10.0  # m/s^2 per axis: the estimated external acceleration is clipped to this


def predict_through(x: jax.Array, pending: jax.Array, quad_params: quadrotor.QuadParams, dt: float,
                    disturbance: jax.Array | None = None) -> jax.Array:
    """The state (10,) after the commands ``pending`` (L, 4), oldest first, by the controller's model
    (:func:`~pixelmpc_jax.control.pixelmpc.disturbed_step`): where the vehicle will be when the next command acts."""

    def one(x, u):
        return pixelmpc_lib.disturbed_step(x, u, dt, quad_params, disturbance), None

    return jax.lax.scan(one, x, pending)[0]


def disturbance_update(disturbance: jax.Array, expected: jax.Array, x_est: jax.Array, tau: float) -> jax.Array:
    """The external acceleration (3,) one tick later: ``a + (v_est - v_expected) / tau``, clipped to
    :data:`DISTURBANCE_MAX`. The residual of the model's one-tick prediction (which holds ``a``) is integrated, so a
    constant push is learnt with time constant ``tau`` (offset-free MPC). No prediction yet (NaN): no change."""
    residual = x_est[quadrotor.VEL] - expected[quadrotor.VEL]
    residual = jnp.where(jnp.isfinite(residual), residual, 0.0)
    return jnp.clip(disturbance + residual / tau, -DISTURBANCE_MAX, DISTURBANCE_MAX).astype(disturbance.dtype)


def racing_policy(ctrl, mppi_config: MPPIConfig, cost_config: costs.RacingCostConfig, build, name: str,
                  quad_params: quadrotor.QuadParams, latency_ticks: int = 0,
                  disturbance_tau: float | None = None, kept_pixel_dim: int = 0,
                  execution: Execution | None = None) -> Policy:
    """A Policy around a pure MPPI racing controller (from :mod:`pixelmpc_jax.control.pixelmpc`), its step placed as
    ``execution`` says (:func:`~pixelmpc_jax.devices.compile_controller`: its samples over the devices; None: one
    device).

    ``build(obs, world, racing_params, disturbance, kept) -> (x0, params)`` makes the controller's state and params
    from an observation (``disturbance``: (3,) or None; ``kept``: a :class:`KeptPixel` or None); the nominal
    trajectory's first 10 columns must be the robot state. With ``kept_pixel_dim`` P the policy keeps the target's
    pixel state alive: the next P columns of the nominal prediction's second state, valid while it descends from a
    detection of the same target. Each tick cuts the racing cost's path windows (Eq. 19) around the
    progress the previous plan predicted for each step, from the per-track constants ``init`` computed for the
    episode's world. With ``latency_ticks`` L the controller plans from the estimate rolled forward through its last
    L commands (:func:`predict_through`), which a plant with that actuation latency has not applied yet. With
    ``disturbance_tau`` the model's external acceleration is estimated each tick (:func:`disturbance_update`).
    """
    horizon, dt = mppi_config.horizon, mppi_config.dt
    run = compile_controller(ctrl, execution or Execution())

    def init(key: jax.Array, world: PolicyWorld) -> RacingPolicyState:
        hover = quadrotor.hover_control(quad_params)
        pending = jnp.broadcast_to(hover, (latency_ticks, hover.shape[0])) if latency_ticks else None
        observer = (jnp.zeros(3, jnp.float32), jnp.full((quadrotor.STATE_DIM,), jnp.nan, jnp.float32)) \
            if disturbance_tau else (None, None)
        kept = KeptPixel(jnp.zeros((kept_pixel_dim,), jnp.float32), jnp.asarray(False), jnp.asarray(-1, jnp.int32)) \
            if kept_pixel_dim else None
        return RacingPolicyState(run.placed.init(key, hover), jnp.full((horizon,), jnp.nan, jnp.float32),
                                 costs.racing_constants(world.track, cost_config), pending, *observer, kept)

    def act(state: RacingPolicyState, obs: Observation, world: PolicyWorld):
        # First tick: no previous plan, every step's path window starts at the current progress.
        step_progress = jnp.where(jnp.isnan(state.step_progress), obs.progress_s, state.step_progress)
        # the map's constants, computed once; where the estimator places the gates (obs.track) the path moves
        constants = state.racing_constants if obs.track is None else costs.racing_constants(world.track, cost_config)
        racing = costs.racing_params(world.track, step_progress, world.target_speed, cost_config, constants)
        x_now, disturbance = obs.x_est, None
        if disturbance_tau:
            disturbance = disturbance_update(state.disturbance, state.expected, x_now, disturbance_tau)
        if latency_ticks:
            obs = obs._replace(x_est=predict_through(x_now, state.pending, quad_params, dt, disturbance))
        x0, params = build(obs, world, racing, disturbance, state.kept)
        u, mppi_state, info = run.placed.step(state.mppi, x0, params)
        kept = state.kept
        if kept_pixel_dim:
            pixel = info.nominal_trajectory[1, quadrotor.STATE_DIM:quadrotor.STATE_DIM + kept_pixel_dim]
            tracked = obs.detection.found | (kept.valid & (kept.gate == obs.target_gate))
            kept = KeptPixel(pixel.astype(kept.pixel.dtype), tracked, jnp.asarray(obs.target_gate, jnp.int32))
        robot_plan = info.nominal_trajectory[:, :quadrotor.STATE_DIM]
        next_progress = costs.plan_progress(world.track, robot_plan, obs.progress_s, horizon)
        pending, expected = state.pending, state.expected
        if disturbance_tau:  # what the plant applies this tick: the oldest pending command, else this one
            applied = pending[0] if latency_ticks else u
            expected = pixelmpc_lib.disturbed_step(x_now, applied.astype(x_now.dtype), dt, quad_params, disturbance)
        if latency_ticks:
            pending = jnp.concatenate([pending[1:], u[None].astype(pending.dtype)])
        return (u, RacingPolicyState(mppi_state, next_progress, state.racing_constants, pending, disturbance,
                                     expected, kept), info.nominal_trajectory)

    return Policy(init=init, act=act, name=name, compiler_options=run.compiler_options)


def nominal_mppi_policy(mppi_config: MPPIConfig | None = None,
                        cost_config: costs.RacingCostConfig | None = None,
                        quad_params: quadrotor.QuadParams | None = None, latency_ticks: int = 0,
                        disturbance_tau: float | None = None, execution: Execution | None = None) -> Policy:
    """The paper's baseline: MPPI on the robot model with the racing cost of Eq. (19) only (``latency_ticks``:
    the actuation latency its model predicts across; ``disturbance_tau``: the time constant of its estimate of an
    external acceleration; ``execution``: how its step runs; see :func:`racing_policy`)."""
    mppi_config = mppi_config or paper_mppi_config()
    cost_config = cost_config or costs.RacingCostConfig()
    quad_params = quad_params or quadrotor.QuadParams()
    ctrl = pixelmpc_lib.make_nominal_mppi(mppi_config, cost_config, quad_params, disturbance=bool(disturbance_tau))

    def build(obs, world, racing, disturbance, kept):
        return obs.x_est, racing if disturbance is None else (racing, disturbance)

    return racing_policy(ctrl, mppi_config, cost_config, build, "mppi", quad_params, latency_ticks, disturbance_tau,
                         execution=execution)


def pixelmpc_policy(config: pixelmpc_lib.ControllerConfig | None = None,
                    quad_params: quadrotor.QuadParams | None = None, execution: Execution | None = None) -> Policy:
    """PixelMPC in the loop: the target pixel is the detector's (with the "vdof" pixel model also the apparent
    size of its corners, a corner the detector does not report in view projected from the map and the estimate),
    the pixel cost is active while it detects the target, or always with the map-aided prior
    (``config.target_prior``: an undetected target's pixel from the map and the estimate), or since it was first
    seen with the kept-alive one (the pixel the controller's pixel model predicted for this tick, from the last), or
    always with the seeded one (kept alive once seen, from the map and the estimate before it is first seen); with
    ``config.look_ahead`` the next gate's pixel state follows, from the map and the estimate; the learned pixel
    model's weights come from ``world.dof``; ``execution``: how its step runs."""
    config = config or pixelmpc_lib.ControllerConfig()
    quad_params = quad_params or quadrotor.QuadParams()
    ctrl = pixelmpc_lib.make_pixelmpc(config, quad_params)

    def build(obs, world, racing, disturbance, kept):
        detection = obs.detection
        prior = config.target_prior
        if prior in ("map", "seeded") or config.pixel_model == "vdof" or config.partial_target == "map":
            # the target's pixel from the map and the estimate
            mapped, mapped_corners = pixelmpc_lib.map_pixel_state(world.track.gate(obs.target_gate), obs.x_est,
                                                                  world.camera)
            # the whole pixel state from the map: [u, v], or [u, v, s] with vdof
            mapped_state = mapped if config.pixel_model != "vdof" else vdof_lib.initial_pixel_state(mapped,
                                                                                                   mapped_corners)
        if prior == "map":  # an undetected target's pixel from the map and the estimate
            uv0 = jnp.where(detection.found, detection.centre, mapped)
            active = jnp.asarray(True)
        else:  # the paper's: not costed while the target is not detected, whatever the pixel holds
            uv0 = jnp.where(detection.found, detection.centre, jnp.asarray(pixelmpc_lib.IMAGE_CENTRE, jnp.float32))
            active = detection.found
        if config.pixel_model == "vdof":  # the size from the corners in view (none when undetected), the rest mapped
            corners = jnp.where(detection.corners_visible[:, None], detection.corners, mapped_corners)
            uv0 = vdof_lib.initial_pixel_state(uv0, corners)
        if config.partial_target == "map":  # a gate cut by the image border: its pixel state from the map
            partial = detection.found & ~jnp.all(detection.corners_visible)
            uv0 = jnp.where(partial, mapped_state.astype(uv0.dtype), uv0)
        if prior in ("kept", "seeded"):  # an undetected target's pixel as the pixel model moved it since it was seen
            alive = ~detection.found & kept.valid & (kept.gate == obs.target_gate)
            uv0 = jnp.where(alive, kept.pixel.astype(uv0.dtype), uv0)
            active = detection.found | alive
        if prior == "seeded":  # a target not detected since it became the target: its pixel from the map
            uv0 = jnp.where(active, uv0, mapped_state.astype(uv0.dtype))
            active = jnp.asarray(True)
        gates = world.track.gates
        params = pixelmpc_lib.PixelMPCParams(
            racing=racing, dof=world.dof, target_active=active, target_centre=gates.centre[obs.target_gate],
            target_normal=gates.normal[obs.target_gate], camera=world.camera, disturbance=disturbance,
        )
        pixels = [uv0]
        if config.look_ahead > 0:  # the next gate, map-aided (the detector reports the target only)
            following = obs.target_gate + 1
            next_gate = jnp.minimum(following, world.track.num_gates - 1)
            uv_next, corners_next = pixelmpc_lib.map_pixel_state(world.track.gate(next_gate), obs.x_est,
                                                                 world.camera)
            if config.next_pixel_dim == 3:  # predicted by vdof
                uv_next = vdof_lib.initial_pixel_state(uv_next, corners_next)
            pixels.append(uv_next)
            params = params.replace(next_active=following < world.track.num_gates,
                                    next_centre=gates.centre[next_gate], next_normal=gates.normal[next_gate])
        return jnp.concatenate([obs.x_est, *(pixel.astype(obs.x_est.dtype) for pixel in pixels)]), params

    kept_pixel_dim = config.pixel_dim if config.target_prior in ("kept", "seeded") else 0
    return racing_policy(ctrl, config.mppi, config.racing, build, f"pixelmpc-{config.pixel_model}",
                         quad_params, config.model_latency_ticks, config.disturbance_time_constant_s, kept_pixel_dim,
                         execution=execution)
