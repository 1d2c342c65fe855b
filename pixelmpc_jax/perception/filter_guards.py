"""Guards of the particle filter against a lying detector and its own divergence (issue 28), both off by default.

- **Detection gate** (``detection_gate_px``): after the motion update each particle predicts where the named
  gate's centre appears in the image. A detection whose centre lies farther than the gate's radius from the
  prediction of every particle but a share below :data:`GATE_MIN_SHARE` of the weight is rejected. The filter
  then skips it, and the loop passes it on as "not found". Gating on the particles, not on their mean, keeps a
  spread (or re-spread) cloud open to the detections that can bring it back.
- **Divergence recovery** (``recover_error_px``): when a detection is informative but the best particle's summed
  corner error still exceeds this many pixels, no particle explains it. When that happens to
  ``recover_after_ticks`` informative detections in a row (ticks without a detection do not break the row), the
  estimate has diverged: the predicted particles are re-spread by ``recover_spread`` (position m, attitude rad as
  a body rotation, velocity m/s), their weights reset, and the detection weighs the re-spread cloud instead. The
  default, 1, re-spreads at the first; but one false detection (another gate's image passing the detection gate)
  is not a divergence, and the robustness experiment's levers wait for 3.
- **IMU bias states** (``imu_bias_std``): the filter estimates its IMU's biases, each particle carrying its own
  (``PFConfig.imu_bias_std``; :func:`filter_config` gives the filter's configuration with them), walking by
  :data:`BIAS_WALK_SHARE` of their spread per square-root second.

:func:`guarded_tick` is :func:`~pixelmpc_jax.perception.particle_filter.tick` with the guards between the motion
and the sensor update; :func:`make_guarded_particle_filter` the filter with its guards as an
:class:`~pixelmpc_jax.perception.estimator.Estimator` (with no guard on, the plain filter's).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics.quadrotor import POS, QUAT, VEL
from pixelmpc_jax.perception import particle_filter as pf_lib
from pixelmpc_jax.perception.estimator import Estimate, Estimator, EstimatorParams, checked_spread, checked_x0
from pixelmpc_jax.settings import Range, check, setting
from pixelmpc_jax.world import camera as camera_lib

GATE_MIN_SHARE = 0.01  # the weight share of particles that must place the gate near a detection to keep it
BIAS_WALK_SHARE = 0.1  # per square-root second, of the bias states' initial spread


@dataclasses.dataclass(frozen=True)
class GuardConfig:
    """Static settings of the filter's guards (hashable; None: the guard is off).

    Attributes:
        detection_gate_px: pixels, the radius around the particles' predicted gate centre within which a
            detection's centre is kept.
        recover_error_px: pixels, the best particle's summed corner error above which the filter re-spreads.
        recover_spread: (position m, attitude rad, velocity m/s) stds of the re-spread.
        recover_after_ticks: how many informative detections in a row no particle explains before the re-spread.
        imu_bias_std: (accelerometer m/s^2, gyro rad/s), the spread of the IMU bias each particle carries, or
            None: the filter estimates no bias (the paper's).
    """

    detection_gate_px: float | None = setting(
        None, range=Range(0.0, 1e4, lo_open=True, unit="px"), none="off", help="particle filter: reject a detection "
        "farther than PX pixels, in {range}, from where the filter's particles put the gate")
    recover_error_px: float | None = setting(
        None, range=Range(0.0, 1e5, lo_open=True, unit="px"), none="off", help="particle filter: re-spread the "
        "particles when no particle explains a detection within PX pixels, in {range}, summed over its corners, N "
        "detections in a row (recover_after_ticks)")
    recover_spread: tuple = (1.0, 0.05, 0.5)
    recover_after_ticks: int = setting(
        1, range=Range(1, 1000, integer=True), help="particle filter, with the recovery: re-spread after N "
        "unexplained detections in a row, N in {range} (3 lets one false detection pass without a re-spread)")
    imu_bias_std: tuple | None = setting(
        None, none="off", help="particle filter: the filter estimates its IMU's biases, each particle carrying its "
        "own, spread by ACCEL m/s^2 and GYRO rad/s (e.g. 0.3,0.02)")

    def __post_init__(self):
        check(self)  # the gate, the recovery's error and its count, each in its field's range
        for name in ("detection_gate_px", "recover_error_px"):
            value = getattr(self, name)
            object.__setattr__(self, name, None if value is None else float(value))
        spread = tuple(float(s) for s in self.recover_spread)
        if len(spread) != 3 or not all(math.isfinite(s) and s >= 0 for s in spread):
            raise ValueError(f"recover_spread must be 3 finite stds >= 0 (position, attitude, velocity), got "
                             f"{self.recover_spread!r}")
        object.__setattr__(self, "recover_spread", spread)
        if self.imu_bias_std is not None:
            bias = tuple(float(s) for s in self.imu_bias_std)
            if len(bias) != 2 or not all(math.isfinite(s) and s > 0 for s in bias):
                raise ValueError(f"imu_bias_std must be 2 positive finite stds (accelerometer m/s^2, gyro rad/s) or "
                                 f"None, got {self.imu_bias_std!r}")
            object.__setattr__(self, "imu_bias_std", bias)

    @property
    def active(self) -> bool:
        return self.detection_gate_px is not None or self.recover_error_px is not None


def init_guards(state: pf_lib.PFState, guards: GuardConfig) -> pf_lib.PFState:
    """A fresh filter ``state`` with what its guards carry: the recovery's count of unexplained detections (zero)
    when the recovery is on; ``state`` itself otherwise."""
    if guards.recover_error_px is None:
        return state
    return state.replace(unexplained=jnp.zeros((), jnp.int32))


def filter_config(config: pf_lib.PFConfig, guards: GuardConfig) -> pf_lib.PFConfig:
    """The filter's configuration with the guards' IMU bias states (``config`` itself without them)."""
    if guards.imu_bias_std is None:
        return config
    return dataclasses.replace(config, imu_bias_std=guards.imu_bias_std,
                               imu_bias_walk=tuple(BIAS_WALK_SHARE * s for s in guards.imu_bias_std))


class GuardInfo(NamedTuple):
    """What the guards did at a tick. accepted: () bool, the detection passed the gate (True without it);
    recovered: () bool, the filter re-spread its particles."""

    accepted: jax.Array
    recovered: jax.Array


def detection_accepted(state: pf_lib.PFState, detection, gates, camera: camera_lib.Camera,
                       gate_px: float) -> jax.Array:
    """() bool: no detection, a detection of no named gate, or one whose centre lies within ``gate_px`` pixels of
    the named gate's centre as particles holding at least :data:`GATE_MIN_SHARE` of the weight see it."""
    gate_id = jnp.asarray(detection.gate_id, jnp.int32)
    centre = gates.centre[jnp.clip(gate_id, 0, gates.centre.shape[0] - 1)]
    uv, _, in_front = jax.vmap(lambda x: camera_lib.project(centre, x, camera))(state.particles)  # (P, 2), (P,)
    scale = jnp.asarray([camera.width, camera.height], uv.dtype)
    distance = jnp.linalg.norm((uv - jnp.asarray(detection.centre, uv.dtype)) * scale, axis=-1)  # (P,) px
    share = jnp.sum(jnp.exp(state.log_weights) * (in_front & (distance <= gate_px)))
    found = jnp.asarray(detection.found, bool)
    return ~found | (gate_id < 0) | (share >= GATE_MIN_SHARE)


def respread(state: pf_lib.PFState, spread: tuple, key: jax.Array) -> pf_lib.PFState:
    """The particles each moved by Gaussian noise of ``spread`` (position m, attitude rad, velocity m/s), uniform
    weights."""
    P = state.particles.shape[0]
    key_pos, key_att, key_vel = jax.random.split(key, 3)
    position_std, attitude_std, velocity_std = spread
    particles = state.particles
    q = jax.vmap(lambda q, d: quadrotor.quat_multiply(q, quadrotor.quat_exp(d, 1.0)))(
        particles[:, QUAT], attitude_std * jax.random.normal(key_att, (P, 3), particles.dtype))
    particles = jnp.concatenate([
        particles[:, POS] + position_std * jax.random.normal(key_pos, (P, 3), particles.dtype),
        quadrotor.normalize_quat(q),
        particles[:, VEL] + velocity_std * jax.random.normal(key_vel, (P, 3), particles.dtype)], axis=-1)
    return state.replace(particles=particles, log_weights=jnp.full((P,), -math.log(P), state.log_weights.dtype))


def _error_log_likelihood(error_px: float, config: pf_lib.PFConfig) -> float:
    """The log-likelihood of a summed corner error of ``error_px`` pixels under the filter's likelihood."""
    scaled = error_px / config.measurement_sigma_px
    return -0.5 * scaled * scaled if config.likelihood == "gaussian" else -scaled


def _recover(state: pf_lib.PFState, detection, gates, camera, config: pf_lib.PFConfig, guards: GuardConfig):
    """``(state, recovered)``: the predicted filter, re-spread when no particle has explained ``detection`` nor the
    informative detections before it, ``guards.recover_after_ticks`` in a row (the count in ``state.unexplained``)."""
    key, key_spread = jax.random.split(state.key)
    state = state.replace(key=key)
    _, _, max_ll = pf_lib.update(state, detection, gates, camera, config)
    informative = jnp.asarray(detection.found, bool) & (jnp.asarray(detection.gate_id) >= 0)
    unexplained = informative & (max_ll < _error_log_likelihood(guards.recover_error_px, config))
    count = jnp.where(unexplained, state.unexplained + 1, jnp.where(informative, 0, state.unexplained))
    diverged = count >= guards.recover_after_ticks
    spread = respread(state, guards.recover_spread, key_spread)
    state = jax.tree_util.tree_map(lambda a, b: jnp.where(diverged, a, b), spread, state)
    return state.replace(unexplained=jnp.where(diverged, 0, count)), diverged


class GuardedInfo(NamedTuple):
    """Diagnostics of one guarded tick: the filter's (``PFInfo``) and its guards' (``GuardInfo``)."""

    filter: pf_lib.PFInfo
    guards: GuardInfo


def guarded_tick(state: pf_lib.PFState, imu, detection, gates, camera: camera_lib.Camera, config: pf_lib.PFConfig,
                 guards: GuardConfig):
    """One control tick of the filter with its guards on (``guards.active``): predict with ``imu``, gate
    ``detection``, re-spread a diverged cloud, then update, estimate and resample
    (:func:`~pixelmpc_jax.perception.particle_filter.tick`).

    Returns ``(state, estimate, info, GuardInfo, detection)``, the detection as the loop should use it: the given one
    with ``found`` and ``corners_visible`` masked by ``GuardInfo.accepted``."""
    state = pf_lib.predict(state, imu, config)
    accepted = jnp.asarray(True)
    if guards.detection_gate_px is not None:
        accepted = detection_accepted(state, detection, gates, camera, guards.detection_gate_px)
        detection = detection.replace(found=detection.found & accepted,
                                      corners_visible=detection.corners_visible & accepted)
    recovered = jnp.asarray(False)
    if guards.recover_error_px is not None:
        if state.unexplained is None:
            raise ValueError("the divergence recovery counts unexplained detections in the filter's state: start it "
                             "with init_guards(state, guards) (make_guarded_particle_filter's init does)")
        state, recovered = _recover(state, detection, gates, camera, config, guards)
    state, estimate, info = pf_lib.tick(state, None, detection, gates, camera, config)
    return state, estimate, info, GuardInfo(accepted, recovered), detection


def make_guarded_particle_filter(config: pf_lib.PFConfig, guards: GuardConfig = GuardConfig(),
                                 spread=(0.5, 0.05, 0.5)) -> Estimator:
    """The particle filter with its guards as an :class:`~pixelmpc_jax.perception.estimator.Estimator`.

    The filter runs on :func:`filter_config` (``config`` with the guards' IMU bias states). With no guard on
    (``guards.active`` False) it is :func:`~pixelmpc_jax.perception.particle_filter.make_particle_filter`'s filter;
    otherwise ``init`` also starts what the guards carry (:func:`init_guards`), ``step`` is :func:`guarded_tick`,
    its ``info`` a :class:`GuardedInfo` and its estimate's detection the one the detection gate let through.

    Args:
        config: the filter's configuration.
        guards: the guards (their IMU bias states, detection gate and divergence recovery).
        spread: Gaussian std of the initial cloud (position m, attitude rad, velocity m/s).
    """
    pf_config = filter_config(config, guards)
    if not guards.active:
        return pf_lib.make_particle_filter(pf_config, spread)
    spread = checked_spread(spread)

    def init(key: jax.Array, x0: jax.Array) -> pf_lib.PFState:
        return init_guards(pf_lib.init_particles(key, checked_x0(x0), pf_config, spread), guards)

    def step(state: pf_lib.PFState, imu, detection, params: EstimatorParams):
        state, estimate, info, guard, detection = guarded_tick(state, imu, detection, params.gates, params.camera,
                                                               pf_config, guards)
        return (Estimate(mean=estimate.mean, position_cov_trace=info.position_cov_trace, detection=detection), state,
                GuardedInfo(filter=info, guards=guard))

    def check(state: pf_lib.PFState, imu, detection, params: EstimatorParams):
        if imu is None or detection is None:
            raise ValueError("the guarded filter's step needs the tick's imu and detection (None given)")
        pf_lib.check_inputs(state, imu, detection, pf_config)
        return state, imu, detection, params

    return Estimator(init=init, step=step, check=check, config=pf_config)
