"""The racing environment: the FlightGoggles-like plant on a course, seen through a detector and an estimator.

Three pure functions over a :class:`SimState` pytree, built for a frozen :class:`EnvConfig` by
:func:`make_env` (brax-like; the driver is :mod:`pixelmpc_jax.sim.episode`):

- ``reset(world, key) -> SimState``: the vehicle at rest at the course's start.
- ``observe(world, state, key) -> (SimState, Observation)``: the detection of the gate the controller steers for,
  from the true pose (the projection cut to the image, the ideal projection, or the rendered frame through OpenCV),
  the estimate (the truth, the particle filter of Section V-D, or the error-state Kalman filter of
  :mod:`pixelmpc_jax.perception.eskf`, updated with the last tick's IMU and this detection) and, on a filter, the
  controller's gate switch from that estimate: what a policy acts on. With the gates painted alike
  (``EnvConfig.gate_paint``) the frame shows gate-like shapes, not a gate's name: the estimator names the target's
  among them (:mod:`pixelmpc_jax.perception.association`) before its update.
- ``step(world, state, u, key) -> SimState``: one 1/40 s control tick, 24 plant substeps at 960 Hz, then
  gate passage and collisions on the flown segment, progress along the desired path, and the episode's end.

Two courses: the map (``World.track``), which the controller and the filter read, and the course the world flies
(``World.course`` where it differs from the map, moved further by the map-error fault): the world judges passage,
misses and crashes on it, from the true state. On the true state the controller's target is the world's; on a
filter (``EnvConfig.gate_switch="estimate"``) it advances when the estimate crosses the map's gate, and a lap whose
two targets part for longer than ``EnvConfig.target_mismatch_s`` (or that misses a gate while they differ) ends as
``target_mismatch``.

A policy is handed no truth: of the World it gets :class:`PolicyWorld` (the map, the target speed, the camera, the
pixel model; not the course flown, the vehicle as it flies or the detector's noise), and each tick the
:class:`Observation` (the estimate, its target and progress, the detection), which holds nothing true beyond the true
state the "truth" estimator gives as its estimate.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import association as association_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import eskf as eskf_lib
from pixelmpc_jax.perception import estimator as estimator_lib
from pixelmpc_jax.perception import filter_guards as guards_lib
from pixelmpc_jax.perception import particle_filter as pf_lib
from pixelmpc_jax.settings import MAX_TIME_RANGE, check, setting
from pixelmpc_jax.sim import faults as faults_lib
from pixelmpc_jax.sim import imu as imu_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.sim import start_error as start_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import track as track_lib
from pixelmpc_jax.world.render import GATE_PAINTS

# Episode end causes beyond the track's crash causes.
CRASH_MISSED_GATE = 4
CRASH_TIMEOUT = 5
CRASH_TARGET_MISMATCH = 6  # the controller steered for another gate than the world's next (passed or skipped)
END_NAMES = {**track_lib.CRASH_NAMES, CRASH_MISSED_GATE: "missed_gate", CRASH_TIMEOUT: "timeout",
             CRASH_TARGET_MISMATCH: "target_mismatch"}

CONTROL_DT = timing.CONTROL_DT  # s, one control tick (pixelmpc_jax.timing)
SUBSTEPS = timing.SUBSTEPS_PER_TICK  # plant substeps per tick
DETECTORS = ("clipped", "ideal", "image")
ESTIMATORS = ("truth", "pf", "eskf")
GATE_SWITCHES = ("estimate", "truth")
GATE_MAPS = ("map", "estimated")
_PAD_STREAM = 2901  # folded into the reset key: the IMU's noise on the pad (ESKFConfig.align_s)
_NEXT_GATE_STREAM = 2902  # folded into the observation's key: the next gate's detector noise and dropout


@struct.dataclass
class World:
    """Everything dynamic an episode runs in (a pytree: new values never recompile).

    Attributes:
        track: the map: the course as the controller and the filter know it.
        target_speed: () m/s.
        plant_params: the vehicle.
        camera: the onboard camera.
        dof: DOF network weights for PixelMPC (None for controllers without a pixel model).
        detector_noise_px: () std of the geometric detector's pixel noise.
        detector_dropout: () probability that a detection is missed.
        course: the course as it stands where it differs from the map (the perturbed gates of a race on a surveyed
            map; the same gates in number and order); None: the map is the course.
        gate_std: (G, 4) what the drone was told of its map: the stds of each gate's offset from where the map puts it
            ``[dx, dy, dz (m), dyaw (rad)]`` (``course.gate_prior_std``), the prior of the gates it estimates
            (``EnvConfig.gates`` "estimated"); None: the map is taken as it is.
    """

    track: track_lib.Track
    target_speed: jax.Array
    plant_params: plant_lib.PlantParams
    camera: camera_lib.Camera
    dof: Any = None
    detector_noise_px: jax.Array = 0.0
    detector_dropout: jax.Array = 0.0
    course: track_lib.Track | None = None
    gate_std: jax.Array | None = None


def make_world(track: track_lib.Track | None = None, target_speed: float = 14.0,
               plant_params: plant_lib.PlantParams | None = None,
               camera: camera_lib.Camera | None = None, dof=None, detector_noise_px: float = 0.0,
               detector_dropout: float = 0.0, course: track_lib.Track | None = None, gate_std=None) -> World:
    """A World with defaults: the AlphaPilot course as the map and the course flown (``course``: the course flown
    where it differs from the map ``track``), the reference vehicle, the paper's camera; ``gate_std`` (G, 4): what
    the drone was told of its map's accuracy (:class:`World`)."""
    if not (isinstance(target_speed, (int, float)) and target_speed > 0):
        raise ValueError(f"target_speed must be a positive number of m/s, got {target_speed!r}")
    track = track if track is not None else course_lib.load_course()
    if course is not None and course.num_gates != track.num_gates:
        raise ValueError(f"the course flown has {course.num_gates} gates, the map {track.num_gates}: a map names the "
                         "same gates in the same order")
    if gate_std is not None:
        gate_std = jnp.asarray(gate_std, jnp.float32)
        if gate_std.shape != (track.num_gates, 4) or not bool(jnp.all(jnp.isfinite(gate_std) & (gate_std >= 0))):
            raise ValueError(f"gate_std must be ({track.num_gates}, 4) finite stds >= 0 [dx, dy, dz, dyaw] per gate, "
                             f"got shape {gate_std.shape}")
    plant_params = plant_params if plant_params is not None else plant_lib.PlantParams()
    camera = camera if camera is not None else camera_lib.default_camera()
    leaves = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32)
                                    if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else jnp.asarray(a),
                                    (plant_params, camera))
    return World(track=track, target_speed=jnp.asarray(target_speed, jnp.float32), plant_params=leaves[0],
                 camera=leaves[1], dof=dof, detector_noise_px=jnp.asarray(detector_noise_px, jnp.float32),
                 detector_dropout=jnp.asarray(detector_dropout, jnp.float32), course=course, gate_std=gate_std)


def stack_worlds(worlds: list[World]) -> World:
    """Stack worlds (same course layout, possibly perturbed, different speeds) on a new leading axis."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *worlds)


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static settings of the environment (hashable: a new config compiles once).

    Attributes:
        max_time_s: the episode ends as a timeout after this much simulated time.
        progress_window_m: arc length searched around the last progress when tracking the robot along
            the desired path (the path may pass near itself elsewhere).
        missed_gate_margin_m: the episode ends as ``missed_gate`` when the robot's progress is this far
            past the target gate without having passed it.
        detector: "clipped" (the projection of the true gate cut at the image border, as a camera's detector
            reports it: :func:`~pixelmpc_jax.perception.detector.detect_in_view`; with the World's noise and dropout;
            fast and batched), "ideal" (the projection, corners and centre reported in the image or not:
            :func:`~pixelmpc_jax.perception.detector.detect_from_geometry`) or "image" (each tick renders the onboard
            frame in JAX and runs the OpenCV colour detector on the host through ``jax.pure_callback``; slower, one
            frame per tick).
        estimator: "truth" (the controller sees the true state) or "pf" (the particle filter of Section
            V-D, fed each tick with the previous tick's 24 IMU samples, preintegrated, and the target
            gate's detection; the controller sees its mean) or "eskf" (the error-state Kalman filter, fed
            the same; a detection arriving late is applied at the tick it was captured, and a detection whose
            every usable corner the filter's Mahalanobis gate rejects reaches the controller as none).
        pf: the particle filter's settings; pf_initial_spread: the initial spread of either filter (position m,
            attitude rad, velocity m/s) around the true start (the particle filter draws its cloud with it, the
            Kalman filter takes it as its prior's standard deviations).
        eskf: the error-state Kalman filter's settings; its ``max_delay_ticks`` must cover the faults'
            detection delay.
        guards: the particle filter's guards against a lying detector and its own divergence
            (:mod:`pixelmpc_jax.perception.filter_guards`; off by default).
        faults: what the world does beyond the nominal model (:mod:`pixelmpc_jax.sim.faults`; none by default).
        gate_switch: with a filter, when the controller's target moves to the next gate: "estimate" (the estimated
            position crosses the map's gate plane within its opening, :func:`estimated_switch`: what the drone can
            know) or "truth" (when the world's does: the true position crosses the true gate). The true state has
            the world's switch.
        target_mismatch_s: with the estimated switch, a lap whose controller steers for another gate than the
            world's next one (a gate already passed, or one skipped) for longer than this ends as
            ``target_mismatch``; so does a lap that misses a gate while the two differ.
        gate_paint: with the image detector, how the rendered gates are painted (``render.GATE_PAINTS``): "hues",
            each gate its own hue, so the detector finds the target gate by its colour; "alike", one paint for all, so
            the detector reports the gate-like components in view
            (:func:`~pixelmpc_jax.perception.detector.detect_candidates_from_image`) and the estimator names the
            target's among them from its estimate and the map
            (:func:`~pixelmpc_jax.perception.association.make_associating`; a rejected or ambiguous association makes
            no update and is counted in ``Observation.association``).
        association: the association's settings with ``gate_paint="alike"`` (K candidates, the pixel gate, the
            ambiguity ratio: :class:`~pixelmpc_jax.perception.association.AssociationConfig`).
        imu: on a filter, the IMU it reads is a racing flight controller's, named in
            :data:`~pixelmpc_jax.sim.imu.IMU_SPECS` (:mod:`pixelmpc_jax.sim.imu`): biases drawn per lap within its
            datasheet's tolerance and white noise of its datasheet's density on the simulator's IMU, and the filter
            (the Kalman filter's noise densities and bias prior) configured from that datasheet; None: the
            simulator's IMU, the filter told its noise.
        start_error: on a filter, it starts each lap from the true start plus an error drawn per lap
            (:mod:`pixelmpc_jax.sim.start_error`: a drone placed by hand on a start pad), its initial spread widened
            to cover it; False: about the exact true start.
    """

    max_time_s: float = setting(timing.LAP_TIME_LIMIT_S, range=MAX_TIME_RANGE, help="timeout per lap")
    progress_window_m: float = 30.0
    missed_gate_margin_m: float = 6.0
    detector: str = setting(
        "clipped", choices=DETECTORS, help="target detection: clipped, the projection of the true gate cut at the "
        "image border as a camera's detector reports it (the corners in view, a centre from the visible outline); "
        "ideal, the projection reported whole, in the image or not; or image, OpenCV on rendered frames")
    estimator: str = setting(
        "truth", choices=ESTIMATORS, help="state the controller acts on: truth, pf (the paper's particle filter) or "
        "eskf (an error-state Kalman filter with IMU bias states)")
    pf: pf_lib.PFConfig = dataclasses.field(default_factory=pf_lib.PFConfig)
    pf_initial_spread: tuple = (0.3, 0.03, 0.2)
    eskf: eskf_lib.ESKFConfig = dataclasses.field(default_factory=eskf_lib.ESKFConfig)
    guards: guards_lib.GuardConfig = dataclasses.field(default_factory=guards_lib.GuardConfig)
    faults: faults_lib.Faults = dataclasses.field(default_factory=faults_lib.Faults)
    gate_switch: str = setting(
        "estimate", choices=GATE_SWITCHES, help="on a filter (pf or eskf), when the controller's target moves to the "
        "next gate: estimate, when the estimate crosses the map's gate (a lap whose target then parts from the "
        "world's ends as target_mismatch); truth, when the true position passes the true gate (as races on a filter "
        "flew before)")
    target_mismatch_s: float = 0.5
    gate_paint: str = setting(
        "hues", choices=GATE_PAINTS, help="with the image detector, how the gates are painted: hues, each gate its own "
        "hue, so the detector knows which gate it sees; alike, one paint for all, the detector reports the gate-like "
        "shapes in view and the estimator names the gate from its estimate and the map (rejected or ambiguous "
        "associations make no update and are counted)")
    association: association_lib.AssociationConfig = dataclasses.field(
        default_factory=association_lib.AssociationConfig)
    imu: str | None = setting(
        None, choices=tuple(imu_lib.IMU_SPECS), none="the simulator's IMU, the filter told its noise",
        help="on a filter (pf or eskf), the IMU it reads is this racing flight controller IMU: biases drawn per lap "
             "within its datasheet's tolerance and noise at its datasheet's density, the Kalman filter configured "
             "from its datasheet")
    start_error: bool = setting(
        False, help="on a filter (pf or eskf), it starts each lap off the true start by an error drawn per lap (a "
                    "drone placed by hand on a pad: 0.1 m, 5 deg of yaw, 2 deg of roll and pitch), its initial "
                    "spread covering it")
    gates: str = setting(
        "map", choices=GATE_MAPS, help="map: the filter and the controller take the map's gates where the map puts "
        "them; estimated: the Kalman filter estimates each gate's offset from the map (prior: what the drone was told "
        "of its map, World.gate_std) and the controller's path, target and gate switch follow the estimated gates")

    def __post_init__(self):
        check(self)  # the timeout, the detector, the estimator and the gate switch, each in its range or choices
        if not self.target_mismatch_s > 0:
            raise ValueError(f"target_mismatch_s must be positive, got {self.target_mismatch_s!r}")
        delay = self.faults.detection_delay_ticks
        if self.estimator == "eskf" and delay > self.eskf.max_delay_ticks:
            raise ValueError(f"the detection delay of {delay} ticks exceeds the Kalman filter's window "
                             f"(eskf.max_delay_ticks={self.eskf.max_delay_ticks})")
        if self.estimator != "pf" and self.guards.active:
            raise ValueError("guards are the particle filter's: they need estimator='pf'")
        if self.gate_paint == "alike" and self.detector != "image":
            raise ValueError("gate_paint='alike' paints the rendered gates: it needs detector='image'")
        if self.gate_paint == "alike" and (self.faults.has_detector_noise or delay):
            raise ValueError("the detector's faults corrupt one gate's detection: with gate_paint='alike' (candidates "
                             "named by the estimator) they are not modelled yet")
        if self.gates == "estimated" and self.estimator != "eskf":
            raise ValueError("gates='estimated' are the Kalman filter's states: they need estimator='eskf'")
        if self.estimator == "truth" and (self.imu is not None or self.start_error):
            raise ValueError("imu and start_error act on a filter's inputs and start: they need estimator='pf' or "
                             "'eskf'")

    @property
    def max_ticks(self) -> int:
        return int(round(self.max_time_s / CONTROL_DT))

    @property
    def switches_on_estimate(self) -> bool:
        """The controller's target advances on the estimate (a filter with the estimated switch)."""
        return self.estimator != "truth" and self.gate_switch == "estimate"


class Observation(NamedTuple):
    """What a policy sees at a tick: what the drone's own sensors and estimator give it, nothing of the truth
    (beside the true state the "truth" estimator hands over as its estimate). The metric's visibility of the target
    (:func:`target_visibility`, from the true pose) is the episode log's, not here, so a policy cannot steer by it.

    Attributes:
        x_est: (10,) the estimated state (the true state with the "truth" estimator).
        target_gate: () int32 index of the gate the controller steers for (the world's next gate, or with the
            estimated switch the gate after the last the estimate crossed; at most the last gate). On a filter with
            ``gate_switch="truth"`` it moves when the true position passes the true gate: that setting hands the
            policy the world's target on purpose.
        progress_s: () m, the estimate's progress along the desired path.
        detection: the detector's report of ``target_gate`` (a measurement, taken from the true pose as a camera
            takes it).
        position_cov_trace: () m^2, trace of the estimator's position covariance (0 for the truth).
        association: () int32, with gates painted alike what became of the tick's candidates (an index of
            :data:`~pixelmpc_jax.perception.association.OUTCOMES`: none in view, accepted, rejected, ambiguous);
            :data:`~pixelmpc_jax.perception.association.NOT_ASSOCIATING` (-1) where each gate has its own hue.
        track: with the gates estimated (``EnvConfig.gates``), the map as the estimator places its gates now, the
            desired path rebuilt through them (``track.with_gates``): the policy flies it in place of the map; None:
            the map as it is.
    """

    x_est: jax.Array
    target_gate: jax.Array
    progress_s: jax.Array
    detection: detector_lib.Detection
    position_cov_trace: jax.Array = 0.0
    association: jax.Array = association_lib.NOT_ASSOCIATING
    track: track_lib.Track | None = None


class PolicyWorld(NamedTuple):
    """What a policy knows of the :class:`World`: the map, the speed asked for, its camera and its pixel model.

    The rest of the World is the truth a drone cannot read: the course as it stands where it differs from the map
    (``World.course``), the vehicle as it flies (``World.plant_params``; a policy plans on its own model), the
    detector's noise and dropout. The type lacks them, so a policy that reads one fails when it is traced.

    Attributes:
        track: the map (``World.track``): the gates, path and start as the drone was told them.
        target_speed: () m/s.
        camera: the onboard camera (its calibration).
        dof: the pixel model's weights (None for controllers without one).
    """

    track: track_lib.Track
    target_speed: jax.Array
    camera: camera_lib.Camera
    dof: Any = None


def policy_world(world: World) -> PolicyWorld:
    """The part of ``world`` a policy may read (:class:`PolicyWorld`), on every loop: the same arrays, regrouped."""
    return PolicyWorld(track=world.track, target_speed=world.target_speed, camera=world.camera, dof=world.dof)


class SimState(NamedTuple):
    """The environment's state for one episode (leading batch axes under vmap).

    Attributes:
        tick: () int32 ticks flown.
        plant: the vehicle (true rigid-body state, body rates, motors).
        target: () int32 index of the gate to pass next; the number of gates once every gate is passed (the world's:
            the true position through the course flown).
        target_est: () int32 the gate the controller steers for: ``target``, or with the estimated switch the gate
            after the last the estimate crossed on the map.
        position_est: (3,) the position the estimate held at the last switch check (the start before the first).
        mismatch_ticks: () int32 ticks in a row that ``target_est`` has differed from ``target``.
        progress_s: () m, the true position's progress along the desired path.
        progress_est_s: () m, the estimate's progress (follows ``progress_s`` with the "truth" estimator).
        filter: the estimator's state (:func:`make_estimator`'s ``init``; a () placeholder for the truth).
        imu: the last tick's IMU samples, preintegrated (the filter's next input).
        end_cause: () int32, 0 while flying or once finished, else a key of ``END_NAMES``.
        done: () bool, the episode has ended (finished, crashed, missed a gate or timed out).
        faults: what the faults carry from tick to tick (:class:`~pixelmpc_jax.sim.faults.FaultState`; no leaves
            without faults).
        imu_errors: the lap's IMU biases drawn from ``EnvConfig.imu``'s datasheet
            (:class:`~pixelmpc_jax.sim.imu.ImuErrors`); None with the simulator's IMU.
    """

    tick: jax.Array
    plant: plant_lib.PlantState
    target: jax.Array
    target_est: jax.Array
    position_est: jax.Array
    mismatch_ticks: jax.Array
    progress_s: jax.Array
    progress_est_s: jax.Array
    filter: pf_lib.PFState | eskf_lib.ESKFState | jax.Array
    imu: plant_lib.TickIMU
    end_cause: jax.Array
    done: jax.Array
    faults: faults_lib.FaultState = faults_lib.FaultState()
    imu_errors: imu_lib.ImuErrors | None = None


class Env(NamedTuple):
    """The environment's pure functions for one :class:`EnvConfig` (see the module docstring)."""

    reset: Callable[[World, jax.Array], SimState]
    observe: Callable[[World, SimState, jax.Array], tuple[SimState, Observation]]
    step: Callable[[World, SimState, jax.Array, jax.Array], SimState]
    config: EnvConfig


def _course(world: World) -> track_lib.Track:
    """The course as it stands before the faults: ``world.course``, or the map where None."""
    return world.track if world.course is None else world.course


def flown_track(world: World, fault_state: faults_lib.FaultState) -> track_lib.Track:
    """The course the world flies: :func:`_course` with the gates where the map-error fault moved them."""
    return faults_lib.true_track(_course(world), fault_state)


def _steered_gate(config: EnvConfig, state: SimState, num_gates: int) -> jax.Array:
    """() int32 the gate the controller steers for (the detector looks for): the world's target, or with the
    estimated switch the controller's own (at most the last gate)."""
    if config.switches_on_estimate:
        return jnp.minimum(state.target_est, num_gates - 1)
    return state.target


def _switch_on_estimate(known: track_lib.Track, state: SimState, x_est: jax.Array,
                        detection: detector_lib.Detection):
    """The controller's gate switch from the estimate ``x_est`` (10,): its target moves on when the estimate
    crossed the target gate of the map as the drone knows it (``known``: the map, or its gates where the estimator
    places them) since the last check (:func:`estimated_switch`). The tick's detection was of the gate just left
    behind: the controller gets none for its new target this tick. -> (state, detection)."""
    num_gates = known.num_gates
    position = x_est[quadrotor.POS].astype(state.position_est.dtype)
    gate = known.gate(jnp.minimum(state.target_est, num_gates - 1))
    switched = (state.target_est < num_gates) & estimated_switch(gate, state.position_est, position)
    detection = detection.replace(found=detection.found & ~switched,
                                  corners_visible=detection.corners_visible & ~switched)
    return state._replace(target_est=state.target_est + switched.astype(jnp.int32), position_est=position), detection


def estimated_switch(gate: track_lib.Gate, position_before: jax.Array, position: jax.Array) -> jax.Array:
    """() bool, the controller's target moves past ``gate`` (the map's): the estimated position went from
    ``position_before`` (3,) to ``position`` (3,) through the gate's plane, forwards, inside its opening
    (:func:`~pixelmpc_jax.world.track.gate_passed` on the estimate)."""
    return track_lib.gate_passed(gate, position_before, position)


def target_visibility(world: World, state: SimState) -> jax.Array:
    """() fraction of the target gate's outline in view from the true pose; 1 once every gate is passed."""
    track = flown_track(world, state.faults)
    num_gates = track.num_gates
    visibility = camera_lib.gate_visibility(track.gate(jnp.minimum(state.target, num_gates - 1)),
                                            state.plant.x, world.camera)
    return jnp.where(state.target >= num_gates, 1.0, visibility)


def lap_finished(world: World, state: SimState) -> jax.Array:
    """() bool, every gate passed without a crash."""
    return (state.target >= world.track.num_gates) & (state.end_cause == 0)


def _image_report(track: track_lib.Track, x: jax.Array, camera: camera_lib.Camera, target: jax.Array, detect,
                  template, palette=None):
    """Render the onboard frame (its gates in ``palette``; None: each its own hue) and run the OpenCV detector
    ``detect(rgb, gate_id)`` on it in a host callback, its report shaped as ``template``."""
    from pixelmpc_jax.world import render as render_lib

    frame = render_lib.render(track, x, camera, supersample=1, palette=palette)

    def host_detect(rgb, gate_id):
        gate_id = np.asarray(gate_id)
        return jax.tree_util.tree_map(np.asarray, detect(np.asarray(rgb), int(gate_id) if gate_id.ndim == 0
                                                         else gate_id))

    found = jax.pure_callback(host_detect, template, frame.rgb, target, vmap_method="sequential")
    return jax.tree_util.tree_map(lambda a, t: a.astype(t.dtype), found, template)


_DETECTION_TEMPLATE = detector_lib.Detection(
    found=jax.ShapeDtypeStruct((), jnp.bool_), centre=jax.ShapeDtypeStruct((2,), jnp.float32),
    bbox=jax.ShapeDtypeStruct((4,), jnp.float32), corners=jax.ShapeDtypeStruct((4, 2), jnp.float32),
    corners_visible=jax.ShapeDtypeStruct((4,), jnp.bool_), gate_id=jax.ShapeDtypeStruct((), jnp.int32))


def _image_detection(track: track_lib.Track, x: jax.Array, camera: camera_lib.Camera, target: jax.Array
                     ) -> detector_lib.Detection:
    """The target gate found by its paint in the onboard frame (each gate its own hue); with ``target`` (K,) gate
    indices, each of those gates in the one frame, stacked."""
    if jnp.ndim(target) == 0:
        return _image_report(track, x, camera, target,
                             lambda rgb, gate_id: detector_lib.detect_from_image(rgb, gate_id, camera=camera),
                             _DETECTION_TEMPLATE)

    def detect_each(rgb, gate_ids):
        found = [detector_lib.detect_from_image(rgb, int(gate_id), camera=camera) for gate_id in gate_ids]
        return jax.tree_util.tree_map(lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]), *found)

    template = jax.tree_util.tree_map(lambda t: jax.ShapeDtypeStruct((*jnp.shape(target), *t.shape), t.dtype),
                                      _DETECTION_TEMPLATE)
    return _image_report(track, x, camera, target, detect_each, template)


def _image_candidates(track: track_lib.Track, x: jax.Array, camera: camera_lib.Camera, target: jax.Array,
                      max_candidates: int) -> detector_lib.Candidates:
    """The gate-like components of the onboard frame with every gate painted alike: up to ``max_candidates``, for
    the estimator to name the ``target``'s."""
    from pixelmpc_jax.world import render as render_lib

    def detect(rgb, gate_id):
        return detector_lib.detect_candidates_from_image(rgb, gate_id, max_candidates, camera=camera)

    return _image_report(track, x, camera, target, detect, detector_lib.candidates_template(max_candidates),
                         palette=render_lib.gate_palette(track.num_gates, "alike"))


def _progress(track: track_lib.Track, position: jax.Array, previous_s: jax.Array, window_m: float) -> jax.Array:
    """() m, the progress of ``position`` (3,) along the desired path, searched around ``previous_s``."""
    spacing = track_lib.PATH_SPACING
    length = min(int(window_m / spacing) + 2, track.num_path_points)
    start = jnp.floor((previous_s - 0.25 * window_m) / track.path_spacing).astype(jnp.int32)
    window = track_lib.PathWindow(start=start, length=length)
    return track_lib.path_query(track, position, window).progress_s


def _with_next_gate(config: EnvConfig, world: World, track: track_lib.Track, x: jax.Array, steered: jax.Array,
                    detection: detector_lib.Detection, key: jax.Array, second=None) -> detector_lib.Detection:
    """The target's ``detection`` and the next gate's, stacked (2 leading): the estimated gates are seen before they
    become the target. The next gate's detector is the target's (``second``: the image detector's report of it in
    the same frame); past the last gate it reports nothing."""
    following = steered + 1
    index = jnp.minimum(following, track.num_gates - 1)
    if second is None:
        detect = detector_lib.detect_in_view if config.detector == "clipped" else detector_lib.detect_from_geometry
        second = detect(track.gate(index), x, world.camera, jax.random.fold_in(key, _NEXT_GATE_STREAM),
                        world.detector_noise_px, world.detector_dropout, index)
    exists = following < track.num_gates
    second = second.replace(found=second.found & exists, corners_visible=second.corners_visible & exists)
    return detector_lib.stack_detections(detection, second)


def _faulty_detection(config: EnvConfig, world: World, track: track_lib.Track, state: SimState,
                      detection: detector_lib.Detection, key: jax.Array):
    """The detector's report with the configured detector faults (noise, misses, false detections: another gate's
    image, from ``track``, the true course) and its delay. -> (detection, the faults' state)."""
    faults, fault_state = config.faults, state.faults
    if faults.has_detector_noise:
        other = track.gate((_steered_gate(config, state, track.num_gates) + 1) % track.num_gates)
        wrong_gate = detector_lib.detect_from_geometry(other, state.plant.x, world.camera)
        detection = faults_lib.corrupt_detection(detection, wrong_gate, faults, key, world.camera)
    if faults.detection_delay_ticks:
        detection, queue = faults_lib.fifo(fault_state.detections, detection)
        fault_state = fault_state._replace(detections=queue)
    return detection, fault_state


def make_estimator(config: EnvConfig) -> estimator_lib.Estimator:
    """The estimator ``config.estimator`` names, built once: the truth, the particle filter with its guards
    (:func:`~pixelmpc_jax.perception.filter_guards.make_guarded_particle_filter`; without a guard on, the plain
    filter), or the error-state Kalman filter, each about its start with ``config.pf_initial_spread`` (widened to
    cover the start's error with ``config.start_error``: :func:`~pixelmpc_jax.sim.start_error.covering`). With
    ``config.imu`` the Kalman filter is told that IMU's datasheet (:func:`~pixelmpc_jax.sim.imu.filter_config`); the
    particle filter keeps its own noise model. With ``config.gates`` "estimated" the Kalman filter takes two
    detections a tick, the target gate's and the next one's (``make_eskf``'s ``detections_per_tick``)."""
    spread = start_lib.covering(config.pf_initial_spread) if config.start_error else config.pf_initial_spread
    if config.estimator == "eskf":
        eskf = config.eskf if config.imu is None else imu_lib.filter_config(imu_lib.IMU_SPECS[config.imu], config.eskf)
        # with the gates estimated the next gate is seen too, before it becomes the target
        return eskf_lib.make_eskf(eskf, spread, detections_per_tick=2 if config.gates == "estimated" else 1)
    if config.estimator == "pf":
        return guards_lib.make_guarded_particle_filter(config.pf, config.guards, spread)
    return estimator_lib.make_truth()


def make_env(config: EnvConfig = EnvConfig()) -> Env:
    """The environment's ``reset``, ``observe`` and ``step`` for ``config`` (pure; jit and vmap them). The
    configured faults (``config.faults``) act in the world only: the estimator and the controller are given the
    map (``world.track``) and the nominal vehicle. The estimator is built here, once (:func:`make_estimator`)."""
    faults = config.faults
    estimator = make_estimator(config)
    if config.gate_paint == "alike":  # the detector reports candidates; the estimator names the target's among them
        estimator = association_lib.make_associating(estimator, config.association)
    imu_spec = None if config.imu is None else imu_lib.IMU_SPECS[config.imu]

    def sensed(imu: plant_lib.TickIMU, imu_errors: imu_lib.ImuErrors | None, key: jax.Array) -> plant_lib.TickIMU:
        """``imu`` as the filter's sensor reads it: with ``config.imu``, with that IMU's biases ``imu_errors`` and its
        noise (:func:`~pixelmpc_jax.sim.imu.read`); else as it is."""
        return imu if imu_spec is None else imu_lib.read(imu, imu_errors, imu_spec, key)

    def init_filter(key: jax.Array, x0: jax.Array, plant_params: plant_lib.PlantParams,
                    imu_errors: imu_lib.ImuErrors | None, gate_std: jax.Array | None):
        """The estimator's first state about ``x0`` (with ``config.start_error``, about ``x0`` plus the start's error
        drawn from ``key``: :func:`~pixelmpc_jax.sim.start_error.draw_start`), with the gates as states about the map
        within ``gate_std`` where it estimates them, aligned on the IMU's readings at rest at ``x0`` before the lap
        where it aligns (the Kalman filter with ``config.eskf.align_s`` > 0: the vehicle's own IMU, its faults and
        ``config.imu``'s errors included)."""
        start = start_lib.draw_start(x0, key) if config.start_error else x0
        if config.gates == "estimated":
            if gate_std is None:
                raise ValueError("gates='estimated' needs what the drone was told of its map: World.gate_std (G, 4)")
            state = estimator.init(key, start, gate_std)
        else:
            state = estimator.init(key, start)
        if estimator.align is not None:
            pad_key = jax.random.fold_in(key, _PAD_STREAM)
            pad = faults_lib.corrupt_imu(sensed(plant_lib.resting_imu(x0, config.eskf.align_s, pad_key, plant_params),
                                                imu_errors, pad_key), faults, pad_key)
            state = estimator.align(state, pad.accel, pad.gyro)
        return state

    def estimate(world: World, state: SimState, detection: detector_lib.Detection):
        """The estimator's step with the last tick's IMU and ``detection``: ``(filter state, x_est, position
        covariance trace, progress of the estimate, the detection as the loop uses it, the association's outcome, the
        map as the drone now knows it: with its gates where the estimator places them, or as it is)``.
        A detection the filter rejects (the particle filter's detection gate in ``config.guards``, the Kalman filter's
        own gate), or with gates painted alike candidates it could not name, reaches the controller as none."""
        x = state.plant.x
        params = estimator_lib.EstimatorParams(gates=world.track.gates, camera=world.camera,
                                               delay_ticks=faults.detection_delay_ticks, x_true=x)
        estimated, filter_state, info = estimator.step(state.filter, state.imu, detection, params)
        x_est = estimated.mean.astype(x.dtype)
        known = world.track if estimated.gates is None else track_lib.with_gates(world.track, estimated.gates)
        return (filter_state, x_est, estimated.position_cov_trace, progress_of(known, state, x_est),
                estimated.detection, association_of(info), known)

    def association_of(info) -> jax.Array:
        """() int32, what became of the tick's candidates (``Observation.association``)."""
        if config.gate_paint == "alike":
            return info.outcome
        return jnp.asarray(association_lib.NOT_ASSOCIATING, jnp.int32)

    if config.estimator == "truth":
        def progress_of(known: track_lib.Track, state: SimState, x_est: jax.Array) -> jax.Array:
            """() m, the true progress (tracked on the course flown): the truth's estimate is the true state."""
            return state.progress_s
    else:
        def progress_of(known: track_lib.Track, state: SimState, x_est: jax.Array) -> jax.Array:
            """() m, the estimate's progress along the desired path of the map as the drone knows it, searched
            around the last."""
            return _progress(known, x_est[quadrotor.POS], state.progress_est_s, config.progress_window_m)

    def reset(world: World, key: jax.Array) -> SimState:
        """The vehicle at rest at the course's start, level, with the motors at hover speed; ``key`` draws
        the particle filter's initial cloud (and, folded, the faults' first draws, the IMU's biases and the filter's
        start error)."""
        x0 = world.track.start
        hover = jnp.asarray([0.0, 0.0, 0.0, 1.0], x0.dtype) * world.plant_params.hover_thrust
        imu_errors = None if imu_spec is None else imu_lib.draw_errors(imu_spec, key)
        return SimState(
            tick=jnp.asarray(0, jnp.int32),
            plant=plant_lib.init_plant(x0, faults_lib.plant_params(world.plant_params, faults)),
            target=jnp.asarray(0, jnp.int32), target_est=jnp.asarray(0, jnp.int32), position_est=x0[quadrotor.POS],
            mismatch_ticks=jnp.asarray(0, jnp.int32), progress_s=jnp.asarray(0.0, jnp.float32),
            progress_est_s=jnp.asarray(0.0, jnp.float32),
            filter=init_filter(key, x0, faults_lib.plant_params(world.plant_params, faults), imu_errors,
                               world.gate_std),
            imu=sensed(plant_lib.hover_tick_imu(CONTROL_DT, dtype=x0.dtype), imu_errors, key),
            end_cause=jnp.asarray(0, jnp.int32), done=jnp.asarray(False),
            faults=faults_lib.init_fault_state(faults, key, _course(world).gates, hover), imu_errors=imu_errors,
        )

    def observe(world: World, state: SimState, key: jax.Array) -> tuple[SimState, Observation]:
        """Detect the gate the controller steers for from the true pose (``key``: the geometric detector's noise
        and dropout, and the detector's faults), update the estimator with the last tick's IMU and the detection,
        and with the estimated switch move the controller's target on from the estimate."""
        track, x = flown_track(world, state.faults), state.plant.x
        steered = _steered_gate(config, state, track.num_gates)
        if config.detector == "image" and config.gate_paint == "alike":
            detection = _image_candidates(track, x, world.camera, steered, config.association.max_candidates)
        elif config.detector == "image" and config.gates == "estimated":  # the target and the next gate, one frame
            following = jnp.minimum(steered + 1, track.num_gates - 1)
            both = _image_detection(track, x, world.camera, jnp.stack([steered, following]))
            detection, second = (jax.tree_util.tree_map(lambda a, k=k: a[k], both) for k in range(2))
        elif config.detector == "image":
            detection = _image_detection(track, x, world.camera, steered)
        else:
            detect = detector_lib.detect_in_view if config.detector == "clipped" else detector_lib.detect_from_geometry
            detection = detect(track.gate(steered), x, world.camera, key, world.detector_noise_px,
                               world.detector_dropout, steered)
        detection, fault_state = _faulty_detection(config, world, track, state, detection, key)
        if config.gates == "estimated" and not (config.detector == "image" and config.gate_paint == "alike"):
            detection = _with_next_gate(config, world, track, x, steered, detection, key,
                                        second if config.detector == "image" else None)
        filter_state, x_est, cov_trace, progress_est, detection, association, known = estimate(world, state,
                                                                                                detection)
        state = state._replace(filter=filter_state, progress_est_s=progress_est, faults=fault_state)
        if config.switches_on_estimate:
            state, detection = _switch_on_estimate(known, state, x_est, detection)
        observation = Observation(
            x_est=x_est, target_gate=_steered_gate(config, state, track.num_gates), progress_s=progress_est,
            detection=detection, position_cov_trace=cov_trace.astype(jnp.float32), association=association,
            track=known if config.gates == "estimated" else None,
        )
        return state, observation

    def fly(world: World, state: SimState, u: jax.Array, key: jax.Array):
        """The plant over one tick under the configured latency, model error and wind, and the IMU the filter
        reads (with its faults, and ``config.imu``'s errors). -> (plant state, TickIMU, the faults' state)."""
        fault_state = state.faults
        if faults.latency_ticks:
            u, queue = faults_lib.fifo(fault_state.commands, u)
            fault_state = fault_state._replace(commands=queue)
        plant_state, _, imu = plant_lib.plant_tick(state.plant, u, key, faults_lib.plant_params(world.plant_params,
                                                                                                 faults),
                                                   SUBSTEPS, wind=faults_lib.wind_velocity(faults, fault_state))
        if faults.gust > 0:
            fault_state = fault_state._replace(gust=faults_lib.gust_step(fault_state.gust, key, faults))
        return plant_state, faults_lib.corrupt_imu(sensed(imu, state.imu_errors, key), faults, key), fault_state

    def step(world: World, state: SimState, u: jax.Array, key: jax.Array) -> SimState:
        """Fly command ``u`` (4,) for one tick (``key``: the plant's noise), then check the flown segment for
        gate passage and collisions, track the progress, and end the episode on a finish, a crash, the
        controller's target parted from the world's (:func:`_mismatch`), a gate missed by more than
        ``missed_gate_margin_m``, or the time limit."""
        track = flown_track(world, state.faults)
        num_gates = track.num_gates
        plant_state, imu, fault_state = fly(world, state, u, key)
        p0, p1 = state.plant.x[quadrotor.POS], plant_state.x[quadrotor.POS]
        passed = track_lib.gate_passed(track.gate(state.target), p0, p1)
        target = state.target + passed.astype(jnp.int32)
        finished = target >= num_gates
        hit, cause = track_lib.collision(track, p0, p1)
        progress = _progress(track, p1, state.progress_s, config.progress_window_m)
        missed = (~finished) & (progress > track.path_gate_s[jnp.minimum(target, num_gates - 1)]
                                + config.missed_gate_margin_m)
        tick = state.tick + 1
        timeout = tick >= config.max_ticks
        end_cause = jnp.where(missed, CRASH_MISSED_GATE, jnp.where(timeout & ~finished, CRASH_TIMEOUT, 0))
        done = finished | hit | missed | timeout
        if config.switches_on_estimate:
            mismatch, mismatch_ticks = _mismatch(state, target, finished, missed)
            end_cause, done = jnp.where(mismatch, CRASH_TARGET_MISMATCH, end_cause), done | mismatch
            state = state._replace(mismatch_ticks=mismatch_ticks)
        else:  # the controller's target is the world's
            state = state._replace(target_est=target)
        end_cause = jnp.where(hit, cause, end_cause)
        return state._replace(tick=tick, plant=plant_state, target=target, progress_s=progress, imu=imu,
                              end_cause=end_cause.astype(jnp.int32), done=done, faults=fault_state)

    def _mismatch(state: SimState, target: jax.Array, finished: jax.Array, missed: jax.Array):
        """Whether the lap ends as ``target_mismatch``: the controller's target has differed from the world's
        ``target`` for longer than ``config.target_mismatch_s``, or the world's gate was missed while they
        differ. -> (ends, ticks in a row they have differed)."""
        differ = (state.target_est != target) & ~finished
        ticks = jnp.where(differ, state.mismatch_ticks + 1, 0).astype(jnp.int32)
        limit = int(round(config.target_mismatch_s / CONTROL_DT))
        return differ & ((ticks > limit) | missed), ticks

    return Env(reset=reset, observe=observe, step=step, config=config)
