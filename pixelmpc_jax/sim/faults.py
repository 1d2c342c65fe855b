"""Faults a real flight brings, as configuration of the world the controller flies in (issue 28).

A :class:`Faults` is frozen and hashable: it is part of the environment's static
:class:`~pixelmpc_jax.sim.env.EnvConfig`. Every fault is off by default, and an off fault is a static Python
branch, so it compiles to nothing: a fault-free episode computes what it computed before faults existed, bit
for bit. No fault reaches the controller's model. The controller keeps its nominal vehicle, the map and the
detector's word; a fault is what the world does to it.

- **Wind**: a steady wind (the air's world-frame velocity, m/s) plus gusts. The gusts are Dryden-like: per axis
  a first-order Gauss-Markov process, the Dryden longitudinal shaping filter ``sigma sqrt(2 L / (pi V)) /
  (1 + s L / V)``, with the low-altitude scales of MIL-F-8785C at about 3 m above the floor and the paper's pace
  (:data:`GUST_TIME_CONSTANT_S`, :data:`GUST_AXIS_SHARE`). The gust is carried in the episode's state and
  advanced once per control tick; the drag acts on the air-relative velocity
  (:func:`~pixelmpc_jax.sim.plant.wind_force`).
- **Model error**: the plant's mass, drag coefficient and motor thrust constant scaled by a factor. The rate
  loop's mixer keeps the nominal thrust constant, so the motors make ``thrust_factor`` times the commanded thrust.
- **Actuation latency**: each command reaches the rate loop ``latency_ticks`` control ticks late (a FIFO of
  commands in the episode's state, filled with hover commands at the start).
- **IMU**: a constant bias and extra white noise on the samples the particle filter integrates: the navigation
  IMU. The rate loop keeps the plant's own gyro. Noise is a std per sample (960 Hz), so the tick's mean carries
  ``std / sqrt(24)``; the bias and noise enter the preintegrated tick as the filter's own noise model does
  (:func:`~pixelmpc_jax.perception.particle_filter.propagate_preintegrated`).
- **Detector**: missed detections at a rate; false detections at a rate, each reported as the target: the next
  gate's image when it is in view (a wrong gate), else a made-up box (a wrong pixel); pixel noise on the centre
  and the corners; and detections arriving ``detection_delay_ticks`` ticks late (a FIFO).
- **Map error**: at the start of each lap every gate is moved horizontally by ``map_error_m`` in a random
  direction. The controller and the filter use the map (``World.track``). The world uses the moved gates:
  detection, visibility, gate passage and collisions.

Random faults draw from keys folded out of the episode's keys (``jax.random.fold_in`` with one stream number per
purpose), so a fault-free episode's draws stay as they were. :data:`FAULT_LEVELS` names a moderate and a severe
level of each fault, each with its reason, and :func:`fault_level` builds them (``"combined"``: every fault at once).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.world import track as track_lib

MAX_DELAY_TICKS = 3  # the longest command or detection delay modelled (75 ms)
VECTOR_FIELDS = ("wind", "imu_accel_bias", "imu_gyro_bias")
INT_FIELDS = ("latency_ticks", "detection_delay_ticks")
# Dryden at low altitude (MIL-F-8785C, h = 10 ft): L_u = L_v = h / (0.177 + 0.000823 h)^1.2 = 23 m, L_w = h = 3 m;
# at the paper's pace (8.5 m/s) the time constants L / V are 2.7 s and 0.35 s; sigma_w / sigma_u = (0.177 +
# 0.000823 h)^0.4 = 0.5.
GUST_TIME_CONSTANT_S = (2.7, 2.7, 0.35)
GUST_AXIS_SHARE = (1.0, 1.0, 0.5)
# fold_in stream numbers of the faults' random draws (one purpose each; far from the small split counts)
_GUST_STREAM, _IMU_STREAM, _DETECTOR_STREAM, _MAP_STREAM = 2801, 2802, 2803, 2804
LEVELS = ("moderate", "severe")


@dataclasses.dataclass(frozen=True)
class Faults:
    """What the world does beyond the nominal model; every field's default is "off".

    Attributes:
        wind: (3,) steady wind, the air's world-frame velocity, m/s.
        gust: m/s, the std of the horizontal gust per axis (the vertical gust's is half of it).
        mass_factor, drag_factor, thrust_factor: the plant's mass, drag coefficient and motor thrust constant as
            multiples of the controller's model.
        latency_ticks: control ticks (0-3) between a command and the rate loop acting on it.
        imu_accel_bias: (3,) m/s^2, added to the filter's accelerometer (body frame).
        imu_gyro_bias: (3,) rad/s, added to the filter's gyro.
        imu_accel_noise, imu_gyro_noise: std per IMU sample (m/s^2, rad/s) of extra white noise on the filter's IMU.
        miss_rate: probability that a detection is dropped.
        false_rate: probability that a tick reports a false detection (a wrong gate or a wrong pixel).
        pixel_noise_px: std of the Gaussian noise on the detected centre and corners, pixels per axis.
        detection_delay_ticks: control ticks (0-3) between an image and its detection reaching the loop.
        map_error_m: m, each gate's horizontal distance from where the map says.
    """

    wind: tuple = (0.0, 0.0, 0.0)
    gust: float = 0.0
    mass_factor: float = 1.0
    drag_factor: float = 1.0
    thrust_factor: float = 1.0
    latency_ticks: int = 0
    imu_accel_bias: tuple = (0.0, 0.0, 0.0)
    imu_gyro_bias: tuple = (0.0, 0.0, 0.0)
    imu_accel_noise: float = 0.0
    imu_gyro_noise: float = 0.0
    miss_rate: float = 0.0
    false_rate: float = 0.0
    pixel_noise_px: float = 0.0
    detection_delay_ticks: int = 0
    map_error_m: float = 0.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            object.__setattr__(self, field.name, _checked(field.name, getattr(self, field.name)))

    def active(self) -> tuple[str, ...]:
        """The names of the faults that are on (the fields that differ from their defaults)."""
        default = Faults()
        return tuple(f.name for f in dataclasses.fields(self) if getattr(self, f.name) != getattr(default, f.name))

    @property
    def has_wind(self) -> bool:
        return any(self.wind) or self.gust > 0

    @property
    def has_model_error(self) -> bool:
        return (self.mass_factor, self.drag_factor, self.thrust_factor) != (1.0, 1.0, 1.0)

    @property
    def has_imu_fault(self) -> bool:
        biased = any(self.imu_accel_bias) or any(self.imu_gyro_bias)
        return biased or self.imu_accel_noise > 0 or self.imu_gyro_noise > 0

    @property
    def has_detector_noise(self) -> bool:
        return self.miss_rate > 0 or self.false_rate > 0 or self.pixel_noise_px > 0


def _checked(name: str, value):
    """``value`` of the fault ``name`` in its one spelling (floats, a tuple of 3 floats, an int), or a ValueError
    saying what the fault accepts."""
    if name in VECTOR_FIELDS:
        try:
            vector = tuple(float(v) for v in value)
        except (TypeError, ValueError):
            vector = ()
        if len(vector) != 3 or not all(math.isfinite(v) for v in vector):
            raise ValueError(f"fault {name} takes 3 finite numbers x,y,z, got {value!r}")
        return vector
    if name in INT_FIELDS:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) \
                or not 0 <= value <= MAX_DELAY_TICKS:
            raise ValueError(f"fault {name} takes an integer number of ticks in [0, {MAX_DELAY_TICKS}], got {value!r}")
        return int(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"fault {name} takes a finite number, got {value!r}")
    value = float(value)
    if name.endswith("_factor") and not 0.2 <= value <= 5.0:
        raise ValueError(f"fault {name} takes a factor in [0.2, 5], got {value:g}")
    if name.endswith("_rate") and not 0.0 <= value <= 1.0:
        raise ValueError(f"fault {name} takes a probability in [0, 1], got {value:g}")
    if not value >= 0.0:
        raise ValueError(f"fault {name} takes a number >= 0, got {value:g}")
    return value


class FaultLevel(NamedTuple):
    """A named level of one fault: the :class:`Faults` fields it sets and why that size."""

    settings: dict
    why: str


FAULT_LEVELS = {
    "wind": {
        "moderate": FaultLevel({"wind": (3.0, 0.0, 0.0)}, "a light breeze (Beaufort 2): an open hall, outdoors"),
        "severe": FaultLevel({"wind": (6.0, 0.0, 0.0)}, "a moderate breeze (Beaufort 4), 70 % of the racing pace"),
    },
    "gust": {
        "moderate": FaultLevel({"gust": 1.5}, "Dryden light turbulence near the ground (W20 = 15 kt)"),
        "severe": FaultLevel({"gust": 3.0}, "Dryden moderate turbulence near the ground (W20 = 30 kt)"),
    },
    "mass": {
        "moderate": FaultLevel({"mass_factor": 1.1}, "a battery or camera 10 % heavier than the model's vehicle"),
        "severe": FaultLevel({"mass_factor": 1.25}, "a payload a quarter of the vehicle's mass"),
    },
    "drag": {
        "moderate": FaultLevel({"drag_factor": 1.5}, "a drag coefficient identified within +-50 %, as is usual"),
        "severe": FaultLevel({"drag_factor": 3.0}, "a prop guard or payload tripling the frontal area"),
    },
    "thrust": {
        "moderate": FaultLevel({"thrust_factor": 0.9}, "worn propellers or a sagging battery: 10 % less thrust"),
        "severe": FaultLevel({"thrust_factor": 0.8}, "a battery near empty: 20 % less thrust per rad/s"),
    },
    "latency": {
        "moderate": FaultLevel({"latency_ticks": 1}, "25 ms from the image to the motors, a fast onboard pipeline"),
        "severe": FaultLevel({"latency_ticks": 3}, "75 ms, a USB camera and a radio link in the loop"),
    },
    "imu_bias": {
        "moderate": FaultLevel({"imu_accel_bias": (0.1, -0.1, 0.2), "imu_gyro_bias": (0.01, -0.01, 0.01)},
                               "a calibrated consumer MEMS IMU after warm-up (10-20 mg, 0.6 deg/s)"),
        "severe": FaultLevel({"imu_accel_bias": (0.3, -0.3, 0.5), "imu_gyro_bias": (0.05, -0.05, 0.05)},
                             "an uncalibrated one (30-50 mg, 3 deg/s)"),
    },
    "imu_noise": {
        "moderate": FaultLevel({"imu_accel_noise": 0.2, "imu_gyro_noise": 0.1},
                               "motor vibration on a stiff race frame, about 3x the vehicle's own IMU noise"),
        "severe": FaultLevel({"imu_accel_noise": 0.6, "imu_gyro_noise": 0.3},
                             "a badly damped mount, 10x the vehicle's own IMU noise"),
    },
    "miss": {
        "moderate": FaultLevel({"miss_rate": 0.2}, "one frame in five lost to motion blur or glare"),
        "severe": FaultLevel({"miss_rate": 0.5}, "every other frame lost (poor light)"),
    },
    "false": {
        "moderate": FaultLevel({"false_rate": 0.05}, "one false detection in 20 frames (a learned detector)"),
        "severe": FaultLevel({"false_rate": 0.2}, "one in five: a cluttered hall of look-alike gates"),
    },
    "pixel_noise": {
        "moderate": FaultLevel({"pixel_noise_px": 2.0}, "2 px at 204 px wide, a corner detector's usual error"),
        "severe": FaultLevel({"pixel_noise_px": 6.0}, "6 px, a coarse detector or a blurred image"),
    },
    "detection_delay": {
        "moderate": FaultLevel({"detection_delay_ticks": 1}, "the detection one frame late (25 ms of inference)"),
        "severe": FaultLevel({"detection_delay_ticks": 2}, "two frames late (50 ms, inference on a small computer)"),
    },
    "map": {
        "moderate": FaultLevel({"map_error_m": 0.3}, "gates placed within 0.3 m of the map (a tape-measured course)"),
        "severe": FaultLevel({"map_error_m": 1.0}, "1 m, the AlphaPilot bound on a gate's position"),
    },
}
COMBINED = "combined"


def fault_level(name: str, level: str) -> Faults:
    """The :class:`Faults` of the named fault at ``level`` ("moderate" or "severe"); ``"combined"``: every fault of
    :data:`FAULT_LEVELS` at that level at once."""
    if level not in LEVELS:
        raise ValueError(f"unknown fault level {level!r}; choose one of {', '.join(LEVELS)}")
    if name == COMBINED:
        return Faults(**{k: v for entry in FAULT_LEVELS.values() for k, v in entry[level].settings.items()})
    if name not in FAULT_LEVELS:
        raise ValueError(f"unknown fault {name!r}; choose one of {', '.join(FAULT_LEVELS)}, {COMBINED}")
    return Faults(**FAULT_LEVELS[name][level].settings)


# --------------------------------------------------------------------------------------------------
# The faults' state in an episode.
# --------------------------------------------------------------------------------------------------


class FaultState(NamedTuple):
    """What the faults carry from tick to tick; a field is None while its fault is off (no leaves, no cost).

    Attributes:
        gust: (3,) m/s, the gust's air velocity.
        commands: (L, 4) the commands not yet applied, oldest first.
        detections: Detection with leading axis D, the detections not yet reported, oldest first.
        gates: the true gates (leading axis G), moved from the map's.
    """

    gust: jax.Array | None = None
    commands: jax.Array | None = None
    detections: detector_lib.Detection | None = None
    gates: track_lib.Gate | None = None


def init_fault_state(faults: Faults, key: jax.Array, gates: track_lib.Gate, hover: jax.Array) -> FaultState:
    """The faults' state at an episode's start: the gust drawn from its stationary law, the command FIFO full
    of ``hover`` (4,), the detection FIFO of "not found", the gates moved from the map's ``gates``; ``key``: the
    episode's reset key (streams folded out of it)."""
    gust = commands = detections = moved = None
    if faults.gust > 0:
        gust = _gust_sigma(faults) * jax.random.normal(jax.random.fold_in(key, _GUST_STREAM), (3,), jnp.float32)
    if faults.latency_ticks:
        commands = jnp.broadcast_to(hover, (faults.latency_ticks, hover.shape[-1]))
    if faults.detection_delay_ticks:
        nothing = detector_lib.Detection(
            found=jnp.asarray(False), centre=jnp.full((2,), 0.5, jnp.float32), bbox=jnp.zeros(4, jnp.float32),
            corners=jnp.zeros((4, 2), jnp.float32), corners_visible=jnp.zeros(4, bool),
            gate_id=jnp.asarray(-1, jnp.int32))
        detections = jax.tree_util.tree_map(lambda a: jnp.stack([a] * faults.detection_delay_ticks), nothing)
    if faults.map_error_m > 0:
        moved = moved_gates(gates, faults.map_error_m, jax.random.fold_in(key, _MAP_STREAM))
    return FaultState(gust=gust, commands=commands, detections=detections, gates=moved)


def true_track(track: track_lib.Track, state: FaultState) -> track_lib.Track:
    """The course the world flies: the map ``track`` with the gates where they really stand."""
    return track if state.gates is None else track.replace(gates=state.gates)


def fifo(queue, item):
    """``(oldest, queue)``: the oldest entry of ``queue`` (a pytree with a leading axis) leaves it and ``item``
    joins at the end."""
    oldest = jax.tree_util.tree_map(lambda q: q[0], queue)
    queue = jax.tree_util.tree_map(lambda q, new: jnp.concatenate([q[1:], jnp.asarray(new, q.dtype)[None]]),
                                   queue, item)
    return oldest, queue


def moved_gates(gates: track_lib.Gate, distance_m: float, key: jax.Array) -> track_lib.Gate:
    """``gates`` (leading axis G) each moved horizontally by ``distance_m`` in a uniformly drawn direction."""
    heading = jax.random.uniform(key, gates.centre.shape[:1], jnp.float32, 0.0, 2.0 * math.pi)
    shift = distance_m * jnp.stack([jnp.cos(heading), jnp.sin(heading), jnp.zeros_like(heading)], axis=-1)
    return gates.replace(centre=gates.centre + shift.astype(gates.centre.dtype))


# --------------------------------------------------------------------------------------------------
# The vehicle: model error and wind.
# --------------------------------------------------------------------------------------------------


def plant_params(params: plant_lib.PlantParams, faults: Faults) -> plant_lib.PlantParams:
    """The vehicle as it is: ``params`` (the model's) with the mass, drag and motor thrust constant scaled; the
    mixer keeps the model's thrust constant. ``params`` itself without a model error."""
    if not faults.has_model_error:
        return params
    return params.replace(mass=params.mass * faults.mass_factor,
                          drag_coefficient=params.drag_coefficient * faults.drag_factor,
                          thrust_coefficient=params.thrust_coefficient * faults.thrust_factor,
                          mixer_thrust_coefficient=params.thrust_coefficient)


def _gust_sigma(faults: Faults) -> jax.Array:
    return faults.gust * jnp.asarray(GUST_AXIS_SHARE, jnp.float32)


def gust_step(gust: jax.Array, key: jax.Array, faults: Faults, dt: float = timing.CONTROL_DT) -> jax.Array:
    """The gust (3,) one tick later: ``g' = a g + sigma sqrt(1 - a^2) n``, ``a = exp(-dt / tau)`` per axis (the
    exact discretisation of the Dryden first-order filter; ``sigma`` is its stationary std)."""
    decay = jnp.exp(-dt / jnp.asarray(GUST_TIME_CONSTANT_S, jnp.float32))
    noise = jax.random.normal(jax.random.fold_in(key, _GUST_STREAM), (3,), jnp.float32)
    return decay * gust + _gust_sigma(faults) * jnp.sqrt(1.0 - decay * decay) * noise


def wind_velocity(faults: Faults, state: FaultState) -> jax.Array | None:
    """(3,) m/s the air moves at now (steady wind plus gust); None in still air."""
    if not faults.has_wind:
        return None
    wind = jnp.asarray(faults.wind, jnp.float32)
    return wind if state.gust is None else wind + state.gust


# --------------------------------------------------------------------------------------------------
# The sensors: the filter's IMU and the detector.
# --------------------------------------------------------------------------------------------------


def corrupt_imu(imu: plant_lib.TickIMU, faults: Faults, key: jax.Array) -> plant_lib.TickIMU:
    """The tick's IMU (:class:`~pixelmpc_jax.sim.plant.TickIMU`) with the bias and extra noise: the mean readings
    get ``b + n`` (``n`` of std ``sigma / sqrt(S)`` over S samples), the rotation ``exp((b_g + n_g) dt)`` on the
    right, the velocity and position integrals ``(b_a + n_a) dt`` and ``(b_a + n_a) dt^2 / 2``."""
    if not faults.has_imu_fault:
        return imu
    key_accel, key_gyro = jax.random.split(jax.random.fold_in(key, _IMU_STREAM))
    per_sample = jax.lax.rsqrt(jnp.maximum(imu.num_samples, 1.0))
    accel = jnp.asarray(faults.imu_accel_bias, imu.accel.dtype) + faults.imu_accel_noise * per_sample * \
        jax.random.normal(key_accel, (3,), imu.accel.dtype)
    gyro = jnp.asarray(faults.imu_gyro_bias, imu.gyro.dtype) + faults.imu_gyro_noise * per_sample * \
        jax.random.normal(key_gyro, (3,), imu.gyro.dtype)
    return imu_with_error(imu, accel, gyro)


def imu_with_error(imu: plant_lib.TickIMU, accel: jax.Array, gyro: jax.Array) -> plant_lib.TickIMU:
    """The tick's IMU with an error of its mean readings, ``accel`` (3,) m/s^2 and ``gyro`` (3,) rad/s (a bias plus
    the tick's mean noise): the rotation gains ``exp(gyro dt)`` on the right, the velocity and position integrals
    ``accel dt`` and ``accel dt^2 / 2``."""
    dt = imu.dt
    return imu._replace(accel=imu.accel + accel, gyro=imu.gyro + gyro,
                        delta_q=quadrotor.normalize_quat(quadrotor.quat_multiply(imu.delta_q,
                                                                                 quadrotor.quat_exp(gyro, dt))),
                        delta_v=imu.delta_v + accel * dt, delta_p=imu.delta_p + 0.5 * accel * dt * dt)


def made_up_box(key: jax.Array, gate_id: jax.Array) -> detector_lib.Detection:
    """A detection of nothing: a square box of half-size 0.05-0.2 image widths at a uniform place of the image's
    inner 70 %, its four corners in view, reported as gate ``gate_id``."""
    key_centre, key_size = jax.random.split(key)
    centre = jax.random.uniform(key_centre, (2,), jnp.float32, 0.15, 0.85)
    half = jax.random.uniform(key_size, (), jnp.float32, 0.05, 0.2)
    signs = jnp.asarray([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], jnp.float32)  # TL, TR, BR, BL
    return detector_lib.Detection(found=jnp.asarray(True), centre=centre,
                                  bbox=jnp.concatenate([centre - half, centre + half]), corners=centre + half * signs,
                                  corners_visible=jnp.ones(4, bool), gate_id=jnp.asarray(gate_id, jnp.int32))


def corrupt_detection(detection: detector_lib.Detection, wrong_gate: detector_lib.Detection, faults: Faults,
                      key: jax.Array, camera) -> detector_lib.Detection:
    """The detector's report with its faults: pixel noise on the centre and the corners, then a miss with
    ``miss_rate``, then with ``false_rate`` a false detection in its place: ``wrong_gate`` (another gate's
    detection, reported under the target's ``gate_id``) when found, else :func:`made_up_box`."""
    if not faults.has_detector_noise:
        return detection
    key_noise, key_miss, key_false, key_box = jax.random.split(jax.random.fold_in(key, _DETECTOR_STREAM), 4)
    key_centre, key_corners = jax.random.split(key_noise)
    if faults.pixel_noise_px > 0:
        sigma = faults.pixel_noise_px / jnp.asarray([camera.width, camera.height], jnp.float32)
        detection = detection.replace(
            centre=detection.centre + sigma * jax.random.normal(key_centre, (2,), jnp.float32),
            corners=detection.corners + sigma * jax.random.normal(key_corners, (4, 2), jnp.float32))
    if faults.miss_rate > 0:
        kept = jax.random.uniform(key_miss, ()) >= faults.miss_rate
        detection = detection.replace(found=detection.found & kept, corners_visible=detection.corners_visible & kept)
    if faults.false_rate > 0:
        decoy = jax.tree_util.tree_map(lambda a, b: jnp.where(wrong_gate.found, a, b),
                                       wrong_gate.replace(gate_id=detection.gate_id),
                                       made_up_box(key_box, detection.gate_id))
        lie = jax.random.uniform(key_false, ()) < faults.false_rate
        detection = jax.tree_util.tree_map(lambda a, b: jnp.where(lie, a, b.astype(a.dtype)), decoy, detection)
    return detection
