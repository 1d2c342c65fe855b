"""The closed loop: a controller at 40 Hz flying the FlightGoggles-like plant around a course.

Each 1/40 s tick: estimate (ground truth here; the particle filter plugs in at ``Observation``),
controller step, 24 plant substeps at 960 Hz, gate passage and crash checks on the flown segment,
target-gate visibility, logging. An episode is one ``lax.while_loop`` over ticks writing into
preallocated logs, so a finished lap stops computing; a batch of episodes (seeds, speeds, course
perturbations) is a ``vmap`` of it and runs until its last member ends.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.mppi import MPPIConfig
from pixelmpc_jax.control.pixelmpc import paper_mppi_config
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import particle_filter as pf_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import track as track_lib

# Episode end causes beyond the track's crash causes.
CRASH_MISSED_GATE = 4
CRASH_TIMEOUT = 5
END_NAMES = {**track_lib.CRASH_NAMES, CRASH_MISSED_GATE: "missed_gate", CRASH_TIMEOUT: "timeout"}

CONTROL_DT = timing.CONTROL_DT  # s, one control tick (pixelmpc_jax.timing)
SUBSTEPS = timing.SUBSTEPS_PER_TICK  # plant substeps per tick
DETECTORS = ("geometry", "image")
ESTIMATORS = ("truth", "pf")


def _image_detection(track: track_lib.Track, x: jax.Array, camera: camera_lib.Camera, target: jax.Array
                     ) -> detector_lib.Detection:
    """Render the onboard frame and detect the target gate in it with OpenCV (a host callback)."""
    from pixelmpc_jax.world import render as render_lib

    frame = render_lib.render(track, x, camera, supersample=1)

    def host_detect(rgb, gate_id):
        import numpy as np

        det = detector_lib.detect_from_image(np.asarray(rgb), int(gate_id), camera=camera)
        return jax.tree_util.tree_map(np.asarray, det)

    template = detector_lib.Detection(
        found=jax.ShapeDtypeStruct((), jnp.bool_), centre=jax.ShapeDtypeStruct((2,), jnp.float32),
        bbox=jax.ShapeDtypeStruct((4,), jnp.float32), corners=jax.ShapeDtypeStruct((4, 2), jnp.float32),
        corners_visible=jax.ShapeDtypeStruct((4,), jnp.bool_), gate_id=jax.ShapeDtypeStruct((), jnp.int32))
    det = jax.pure_callback(host_detect, template, frame.rgb, target, vmap_method="sequential")
    return jax.tree_util.tree_map(lambda a, t: a.astype(t.dtype), det, template)


@dataclasses.dataclass(frozen=True)
class EpisodeConfig:
    """Static settings of a closed-loop episode.

    Attributes:
        max_time_s: the episode ends as a timeout after this much simulated time.
        detector: "geometry" (projection of the true gate, with the World's noise and dropout; fast and
            batched) or "image" (each tick renders the onboard frame in JAX and runs the OpenCV colour
            detector on the host through ``jax.pure_callback``; slower, one frame per tick).
        logged_prediction_steps: how many steps of the controller's predicted target pixel to log per
            tick (for the onboard video); controllers without a pixel state log zeros.
        estimator: "truth" (the controller sees the true state) or "pf" (the particle filter of Section
            V-D, fed each tick with the previous tick's 24 IMU samples, preintegrated, and the target
            gate's detection; the controller sees its mean).
        pf: the particle filter's settings; pf_initial_spread: its initial spread (position m, attitude
            rad, velocity m/s) around the true start.
        progress_window_m: arc length searched around the last progress when tracking the robot along
            the desired path (the path may pass near itself elsewhere).
        missed_gate_margin_m: the episode ends as ``missed_gate`` when the robot's progress is this far
            past the target gate without having passed it.
    """

    max_time_s: float = 60.0
    progress_window_m: float = 30.0
    missed_gate_margin_m: float = 6.0
    detector: str = "geometry"
    logged_prediction_steps: int = 41
    estimator: str = "truth"
    pf: pf_lib.PFConfig = dataclasses.field(default_factory=pf_lib.PFConfig)
    pf_initial_spread: tuple = (0.3, 0.03, 0.2)

    def __post_init__(self):
        if self.detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if not self.max_time_s > 0:
            raise ValueError(f"max_time_s must be positive, got {self.max_time_s!r}")

    @property
    def max_ticks(self) -> int:
        return int(round(self.max_time_s / CONTROL_DT))


class Observation(NamedTuple):
    """What a controller sees at a tick. x_est: (10,); target_gate: () int32; progress_s: () m;
    target_visibility: () fraction of the target gate's outline in view from the true pose (what the
    metrics count, not what the controller could know); detection: the detector's view of the target gate
    from the true pose."""

    x_est: jax.Array
    target_gate: jax.Array
    progress_s: jax.Array
    target_visibility: jax.Array
    detection: detector_lib.Detection


class Policy(NamedTuple):
    """A controller in the loop: ``init(key) -> state``; ``act(state, obs, world) -> (u, state, predicted)``,
    where ``world`` is the :class:`World` and ``predicted`` the (T+1, n) nominal prediction."""

    init: Callable[[jax.Array], Any]
    act: Callable[[Any, Observation, Any], tuple[jax.Array, Any, jax.Array]]
    name: str


@struct.dataclass
class World:
    """Everything dynamic an episode runs in (a pytree: new values never recompile).

    Attributes:
        track: the course.
        target_speed: () m/s.
        plant_params: the vehicle.
        camera: the onboard camera.
        dof: DOF network weights for PixelMPC (None for controllers without a pixel model).
        detector_noise_px: () std of the geometric detector's pixel noise.
        detector_dropout: () probability that a detection is missed.
    """

    track: track_lib.Track
    target_speed: jax.Array
    plant_params: plant_lib.PlantParams
    camera: camera_lib.Camera
    dof: Any = None
    detector_noise_px: jax.Array = 0.0
    detector_dropout: jax.Array = 0.0


def rate_feedforward(u0: jax.Array, u1: jax.Array, gain: float, u_min, u_max) -> jax.Array:
    """The command sent to the plant: ``u0`` with its body rates led by ``gain * (u1 - u0)``.

    The model assumes the rates follow the command at once; the plant's rate loop lags it with a time
    constant of about 1 / P = 0.11 s. Leading the planned rate change (u1 is the plan's next control)
    lets the plant's rates follow the plan the model optimised. Thrust is passed through. Clipped.
    """
    rates = u0[:3] + gain * (u1[:3] - u0[:3])
    u = jnp.concatenate([rates, u0[3:]])
    return jnp.clip(u, jnp.asarray(u_min), jnp.asarray(u_max))


DEFAULT_FEEDFORWARD_GAIN = 0.0


def _racing_policy(ctrl, mppi_config: MPPIConfig, cost_config: costs.RacingCostConfig, build, name: str,
                   quad_params: quadrotor.QuadParams, feedforward_gain: float) -> Policy:
    """A Policy around an MPPI racing controller. ``build(obs, world, racing_params) -> (x0, params)``
    makes the controller's state and params from an observation; the nominal trajectory's first 10
    columns must be the robot state."""
    horizon = mppi_config.horizon

    def init(key):
        return RacingPolicyState(ctrl.init(key, quadrotor.hover_control(quad_params)),
                                 jnp.full((horizon,), jnp.nan, jnp.float32))

    def act(state: RacingPolicyState, obs: Observation, world: World):
        # First tick: no previous plan, every step's path window starts at the current progress.
        step_progress = jnp.where(jnp.isnan(state.step_progress), obs.progress_s, state.step_progress)
        racing = costs.racing_params(world.track, step_progress, world.target_speed, cost_config)
        x0, params = build(obs, world, racing)
        u, mppi_state, info = ctrl.step_pure(state.mppi, x0, params)
        robot_plan = info.nominal_trajectory[:, :quadrotor.STATE_DIM]
        next_progress = costs.plan_progress(world.track, robot_plan, obs.progress_s, horizon)
        if feedforward_gain:
            u = rate_feedforward(u, mppi_state.plan[0], feedforward_gain, mppi_config.u_min, mppi_config.u_max)
        return u, RacingPolicyState(mppi_state, next_progress), info.nominal_trajectory

    return Policy(init=init, act=act, name=name)


def nominal_mppi_policy(mppi_config: MPPIConfig | None = None,
                        cost_config: costs.RacingCostConfig | None = None,
                        quad_params: quadrotor.QuadParams | None = None,
                        feedforward_gain: float = DEFAULT_FEEDFORWARD_GAIN) -> Policy:
    """The paper's baseline: MPPI on the robot model with the racing cost of Eq. (19) only."""
    mppi_config = mppi_config or paper_mppi_config()
    cost_config = cost_config or costs.RacingCostConfig()
    quad_params = quad_params or quadrotor.QuadParams()
    ctrl = pixelmpc_lib.make_nominal_mppi(mppi_config, cost_config, quad_params)

    def build(obs, world, racing):
        return obs.x_est, racing

    return _racing_policy(ctrl, mppi_config, cost_config, build, "mppi", quad_params, feedforward_gain)


def pixelmpc_policy(config: pixelmpc_lib.PixelMPCConfig | None = None,
                    quad_params: quadrotor.QuadParams | None = None,
                    feedforward_gain: float = DEFAULT_FEEDFORWARD_GAIN) -> Policy:
    """PixelMPC in the loop: the target pixel is the detector's, the pixel cost is active while it
    detects the target; the DOF weights come from ``world.dof``."""
    config = config or pixelmpc_lib.PixelMPCConfig()
    quad_params = quad_params or quadrotor.QuadParams()
    ctrl = pixelmpc_lib.make_pixelmpc(config, quad_params)

    def build(obs, world, racing):
        detection = obs.detection
        uv0 = jnp.where(detection.found, detection.centre, jnp.asarray(pixelmpc_lib.IMAGE_CENTRE, jnp.float32))
        params = pixelmpc_lib.PixelMPCParams(
            racing=racing, dof=world.dof, target_active=detection.found,
            target_centre=world.track.gates.centre[obs.target_gate],
            target_normal=world.track.gates.normal[obs.target_gate], camera=world.camera,
        )
        return jnp.concatenate([obs.x_est, uv0.astype(obs.x_est.dtype)]), params

    return _racing_policy(ctrl, config.mppi, config.racing, build, f"pixelmpc-{config.pixel_model}",
                          quad_params, feedforward_gain)


class RacingPolicyState(NamedTuple):
    """MPPI's state and, per horizon step, the path progress (m) its last plan predicted (T,)."""

    mppi: Any
    step_progress: jax.Array


class EpisodeLog(NamedTuple):
    """One episode (leading batch axes under vmap). M = max ticks; entries past ``num_ticks`` are zero.

    Attributes:
        states: (M+1, 10) true state at each tick, the start included.
        controls: (M, 4) commands sent.
        body_rates: (M+1, 3) true body rates.
        visibility: (M+1,) target-gate visibility at each tick.
        target: (M+1,) target gate index at each tick.
        detected: (M,) the detector reported the target at each tick.
        detection_uv: (M, 2) the detected target pixel (normalised).
        predicted_uv: (M, P, 2) the controller's predicted target pixel for the next P-1 steps.
        estimates: (M, 10) the state the controller acted on (the truth, or the filter's mean).
        position_cov_trace: (M,) trace of the estimator's position covariance (0 for the truth), m^2.
        num_ticks: () ticks flown.
        gates_passed: () gates passed in order.
        end_cause: () int32, 0 finished or still flying, else a key of END_NAMES.
        finished: () bool, all gates passed.
    """

    states: jax.Array
    controls: jax.Array
    body_rates: jax.Array
    visibility: jax.Array
    target: jax.Array
    detected: jax.Array
    detection_uv: jax.Array
    predicted_uv: jax.Array
    estimates: jax.Array
    position_cov_trace: jax.Array
    num_ticks: jax.Array
    gates_passed: jax.Array
    end_cause: jax.Array
    finished: jax.Array


class _Carry(NamedTuple):
    tick: jax.Array
    done: jax.Array
    plant: plant_lib.PlantState
    policy_state: Any
    target: jax.Array
    progress: jax.Array
    progress_est: jax.Array
    filter: Any
    imu_prev: plant_lib.TickIMU
    end_cause: jax.Array
    key: jax.Array
    log: EpisodeLog


def _progress(track: track_lib.Track, position: jax.Array, previous_s: jax.Array, window_m: float) -> jax.Array:
    spacing = track_lib.PATH_SPACING
    length = min(int(window_m / spacing) + 2, track.num_path_points)
    start = jnp.floor((previous_s - 0.25 * window_m) / track.path_spacing).astype(jnp.int32)
    window = track_lib.PathWindow(start=start, length=length)
    return track_lib.path_query(track, position, window).progress_s


def episode_fn(policy: Policy, config: EpisodeConfig = EpisodeConfig()) -> Callable:
    """The pure episode ``run(world, key) -> EpisodeLog`` (jit and vmap it; see :func:`make_runner`)."""
    M = config.max_ticks
    P = config.logged_prediction_steps

    def predicted_pixels(prediction: jax.Array) -> jax.Array:
        if prediction.shape[-1] < quadrotor.STATE_DIM + 2:
            return jnp.zeros((P, 2), jnp.float32)
        uv = prediction[:P, quadrotor.STATE_DIM:quadrotor.STATE_DIM + 2].astype(jnp.float32)
        return jnp.pad(uv, ((0, P - uv.shape[0]), (0, 0)), mode="edge")

    def run(world: World, key: jax.Array) -> EpisodeLog:
        track = world.track
        num_gates = track.num_gates
        key, key_policy, key_filter = jax.random.split(key, 3)
        x0 = track.start
        plant_state = plant_lib.init_plant(x0, world.plant_params)
        visibility0 = camera_lib.gate_visibility(track.gate(0), x0, world.camera)
        log = EpisodeLog(
            states=jnp.zeros((M + 1, quadrotor.STATE_DIM), x0.dtype).at[0].set(x0),
            controls=jnp.zeros((M, quadrotor.CONTROL_DIM), x0.dtype),
            body_rates=jnp.zeros((M + 1, 3), x0.dtype),
            visibility=jnp.zeros((M + 1,), jnp.float32).at[0].set(visibility0),
            target=jnp.zeros((M + 1,), jnp.int32),
            detected=jnp.zeros((M,), jnp.bool_),
            detection_uv=jnp.zeros((M, 2), jnp.float32),
            predicted_uv=jnp.zeros((M, P, 2), jnp.float32),
            estimates=jnp.zeros((M, quadrotor.STATE_DIM), x0.dtype),
            position_cov_trace=jnp.zeros((M,), jnp.float32),
            num_ticks=jnp.asarray(0, jnp.int32),
            gates_passed=jnp.asarray(0, jnp.int32),
            end_cause=jnp.asarray(0, jnp.int32),
            finished=jnp.asarray(False),
        )
        carry = _Carry(
            tick=jnp.asarray(0, jnp.int32), done=jnp.asarray(False), plant=plant_state,
            policy_state=policy.init(key_policy), target=jnp.asarray(0, jnp.int32),
            progress=jnp.asarray(0.0, jnp.float32), progress_est=jnp.asarray(0.0, jnp.float32),
            filter=(pf_lib.pf_init(key_filter, x0, config.pf, config.pf_initial_spread)
                    if config.estimator == "pf" else jnp.zeros(())),
            imu_prev=plant_lib.hover_tick_imu(CONTROL_DT, dtype=x0.dtype),
            end_cause=jnp.asarray(0, jnp.int32), key=key, log=log,
        )

        def body(c: _Carry) -> _Carry:
            key, key_plant, key_detect = jax.random.split(c.key, 3)
            x = c.plant.x
            target_gate = track.gate(c.target)
            if config.detector == "image":
                detection = _image_detection(track, x, world.camera, c.target)
            else:
                detection = detector_lib.detect_from_geometry(
                    target_gate, x, world.camera, key_detect, world.detector_noise_px, world.detector_dropout,
                    c.target)
            if config.estimator == "pf":
                filter_state, estimate, filter_info = pf_lib.pf_step(
                    c.filter, c.imu_prev, detection, track, world.camera, config.pf)
                x_est, cov_trace = estimate.mean.astype(x.dtype), filter_info.position_cov_trace
                progress_est = _progress(track, x_est[quadrotor.POS], c.progress_est, config.progress_window_m)
            else:
                filter_state, x_est, cov_trace, progress_est = c.filter, x, jnp.asarray(0.0), c.progress
            obs = Observation(
                x_est=x_est, target_gate=c.target, progress_s=progress_est,
                target_visibility=camera_lib.gate_visibility(target_gate, x, world.camera), detection=detection,
            )
            u, policy_state, prediction = policy.act(c.policy_state, obs, world)
            plant_state, _, imu_tick = plant_lib.plant_tick(c.plant, u, key_plant, world.plant_params, SUBSTEPS)
            p0, p1 = x[quadrotor.POS], plant_state.x[quadrotor.POS]
            passed = track_lib.gate_passed(target_gate, p0, p1)
            target = c.target + passed.astype(jnp.int32)
            finished = target >= num_gates
            hit, cause = track_lib.collision(track, p0, p1)
            progress = _progress(track, p1, c.progress, config.progress_window_m)
            missed = (~finished) & (progress > track.path_gate_s[jnp.minimum(target, num_gates - 1)]
                                    + config.missed_gate_margin_m)
            tick = c.tick + 1
            timeout = tick >= M
            end_cause = jnp.where(hit, cause, jnp.where(missed, CRASH_MISSED_GATE,
                                                        jnp.where(timeout & ~finished, CRASH_TIMEOUT, 0)))
            done = finished | hit | missed | timeout
            new_visibility = camera_lib.gate_visibility(
                track.gate(jnp.minimum(target, num_gates - 1)), plant_state.x, world.camera)
            log = c.log._replace(
                states=c.log.states.at[tick].set(plant_state.x),
                controls=c.log.controls.at[c.tick].set(u),
                body_rates=c.log.body_rates.at[tick].set(plant_state.rates),
                visibility=c.log.visibility.at[tick].set(jnp.where(finished, 1.0, new_visibility)),
                target=c.log.target.at[tick].set(jnp.minimum(target, num_gates - 1)),
                detected=c.log.detected.at[c.tick].set(detection.found),
                detection_uv=c.log.detection_uv.at[c.tick].set(detection.centre.astype(jnp.float32)),
                predicted_uv=c.log.predicted_uv.at[c.tick].set(predicted_pixels(prediction)),
                estimates=c.log.estimates.at[c.tick].set(x_est),
                position_cov_trace=c.log.position_cov_trace.at[c.tick].set(cov_trace.astype(jnp.float32)),
                num_ticks=tick,
                gates_passed=jnp.minimum(target, num_gates),
                end_cause=end_cause.astype(jnp.int32),
                finished=finished & ~hit,
            )
            return _Carry(tick=tick, done=done, plant=plant_state, policy_state=policy_state, target=target,
                          progress=progress, progress_est=progress_est, filter=filter_state, imu_prev=imu_tick,
                          end_cause=end_cause.astype(jnp.int32), key=key, log=log)

        final = jax.lax.while_loop(lambda c: ~c.done, body, carry)
        return final.log

    return run


class Runner(NamedTuple):
    """Compiled episode runners. ``single(world, key)``; ``batch(worlds, keys)`` with worlds batched on
    their leading axis (use :func:`stack_worlds`)."""

    single: Callable[[World, jax.Array], EpisodeLog]
    batch: Callable[[World, jax.Array], EpisodeLog]


def shard_batch(tree, devices=None):
    """Place a batch (leading axis B on every leaf) across ``devices`` (default: all JAX devices, of every
    process) with a 1-D ``Mesh`` and ``NamedSharding``, padding B to a multiple of the device count by
    repeating the last element. Returns ``(sharded tree, B)``; with one device the tree is returned as it is.

    With several processes (``jax.distributed``), every process holds the whole batch (the laps are built
    from seeds, the same everywhere) and places the rows of its own devices."""
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(devices if devices is not None else jax.devices())
    size = jax.tree_util.tree_leaves(tree)[0].shape[0]
    if len(devices) <= 1:
        return tree, size
    padded = -(-size // len(devices)) * len(devices)
    if padded != size:
        tree = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], padded - size, axis=0)]), tree)
    sharding = NamedSharding(Mesh(np.asarray(devices), ("batch",)), PartitionSpec("batch"))
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding), size

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(place, tree), size


def gather_batch(tree):
    """Bring a batch computed over the devices of several processes back whole to every process (with one
    process it is returned as it is)."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)


def make_runner(policy: Policy, config: EpisodeConfig = EpisodeConfig()) -> Runner:
    """Compiled runners; ``batch`` splits its episodes over every device present, across processes too
    (see :func:`shard_batch`), and returns them whole."""
    run = episode_fn(policy, config)
    batch_jit = jax.jit(jax.vmap(run))

    def batch(worlds: World, keys: jax.Array) -> EpisodeLog:
        (worlds, keys), size = shard_batch((worlds, keys))
        logs = gather_batch(batch_jit(worlds, keys))
        return jax.tree_util.tree_map(lambda a: a[:size], logs)

    return Runner(single=jax.jit(run), batch=batch)


def stack_worlds(worlds: list[World]) -> World:
    """Stack worlds (same course layout, possibly perturbed, different speeds) on a new leading axis."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *worlds)


def make_world(track: track_lib.Track | None = None, target_speed: float = 14.0,
               plant_params: plant_lib.PlantParams | None = None,
               camera: camera_lib.Camera | None = None, dof=None, detector_noise_px: float = 0.0,
               detector_dropout: float = 0.0) -> World:
    """A World with defaults: the AlphaPilot course, the reference vehicle, the paper's camera."""
    if not (isinstance(target_speed, (int, float)) and target_speed > 0):
        raise ValueError(f"target_speed must be a positive number of m/s, got {target_speed!r}")
    track = track if track is not None else track_lib.load_course()
    plant_params = plant_params if plant_params is not None else plant_lib.PlantParams()
    camera = camera if camera is not None else camera_lib.default_camera()
    leaves = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32)
                                    if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else jnp.asarray(a),
                                    (plant_params, camera))
    return World(track=track, target_speed=jnp.asarray(target_speed, jnp.float32), plant_params=leaves[0],
                 camera=leaves[1], dof=dof, detector_noise_px=jnp.asarray(detector_noise_px, jnp.float32),
                 detector_dropout=jnp.asarray(detector_dropout, jnp.float32))
