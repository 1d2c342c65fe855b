"""The paper's particle filter (Section V-D): IMU motion update, gate-corner sensor update, 6,400 particles.

The filter tracks the robot state ``x = [p, q(wxyz), v]`` (10,) of ``dynamics/quadrotor.py`` with P
particles. One control tick (``dt = 1/40`` s) is :func:`tick`: predict with the tick's IMU, update with
the tick's detection of the target gate, resample when the effective sample size falls below a fraction
of P. Everything is written for one filter and vmapped over particles; batch filters with ``jax.vmap``. The
filter as an estimator (pure ``init`` and ``step``; the caller compiles them) is :func:`make_particle_filter`.

Choices where the paper leaves one open:

- Motion noise. The paper injects Gaussian noise "with mean 0 and variance 0.2 directly on position" and
  adds noise of variance 0.2 to the accelerometer and 0.1 to the gyro readings. The IMU noises are per
  reading: the loop feeds the filter each tick's 24 samples preintegrated (``sim.plant.TickIMU``), so a
  particle's noise on the tick's mean reading has 1/24 of that variance. The position noise is read as
  a rate, variance ``0.2 * dt`` per update (``PFConfig.position_noise_per_second``, default True). Read
  literally as a variance per 40 Hz update (std 0.45 m per tick), it kept the estimate 0.6-0.7 m off the
  truth even while the gate was detected, and the controllers crashed before the first gate in our loop;
  as a rate the estimate stayed within ~0.1 m while detecting and laps were completed.
- Motion model. With preintegrated samples (``TickIMU``, what the closed loop feeds): ``q' = q dq``,
  ``v' = v + g dt + R dv``, ``p' = p + v dt + g dt^2 / 2 + R dp`` (:func:`propagate_preintegrated`); at racing
  rates the mean gyro alone misses the rotation's change within the tick. With one mean sample: attitude
  first, exactly for constant rates over the tick: ``q' = q * exp(w dt / 2)``; the
  body specific force is rotated to the world with the mid-tick attitude, gravity ``[0, 0, -9.81]`` is added,
  and ``v`` and ``p`` are integrated with constant acceleration (``p' = p + v dt + a dt^2 / 2``). Drag needs
  no model: the accelerometer measures it.
- Sensor model. Only the gate the detection names (``Detection.gate_id``, the target gate) is predicted:
  the loop's detector only ever looks for the target, so another gate in view is not "missing" from its
  report, and predicting it would penalise the true pose. Its 4 inner corners are projected into each
  particle's camera; a corner counts as expected when in front of the camera and inside the image. Per
  corner, the error is the Euclidean pixel distance when both expected and detected, ``4 W`` pixels
  (the paper's penalty, W the image width) when exactly one of the two holds, 0 when neither. A negative
  ``gate_id`` carries no information and leaves the weights alone, and so, by default, does a detection
  with ``found=False``. The paper also penalises the expected corners when the target is not detected at
  all (every expected corner pays the penalty); that is ``PFConfig.penalise_undetected_target``, off by
  default: when the target has just left the image the true pose sits at the edge of the field of view
  and the penalty removes the particles on its inner side at every tick, which pushed the estimate away
  from the truth (with it on, our laps crashed within 2-4 gates; off, laps were completed).
- Likelihood. Default ``"laplace"``: ``log l = -sum_k e_k / sigma``, the summed pixel error the paper
  describes (its penalty is a number of pixels added to that sum) turned into a weight. Linear in the
  error, it keeps a one-corner mismatch (816 px at W = 204) a large but finite handicap that a particle
  matching the other corners can survive against particles matching none, where a Gaussian would
  square it into ``-0.5 (816 / sigma)^2`` and let one detector glitch decide everything; it is also
  robust to the detector's occasional bad corner. ``"gaussian"`` (``-0.5 sum_k (e_k / sigma)^2``) is
  available for comparison.
- IMU biases (an option, off by default as in the paper): with ``PFConfig.imu_bias_std`` each particle also
  carries an accelerometer and a gyro bias (``PFState.bias``, (P, 6)), drawn with those stds, subtracted from the
  readings it integrates and walking by ``imu_bias_walk`` per square-root second; resampling keeps the biases
  that explain the detections. Without it, a constant bias of a few tenths of a m/s^2 or a hundredth of a rad/s
  drifts the velocity and attitude faster than position noise and detections pull them back.
- Numerics. Log weights, normalised with log-sum-exp. A non-finite particle or likelihood gets weight
  zero; if no weight is left (all ``-inf``/NaN) the particles are kept, the weights reset to uniform and
  ``info.degenerate`` is set.
- Resampling: systematic, only when ``ESS < resample_threshold * P``. One uniform draw places P evenly
  spaced pointers on the weights' CDF: O(P) (a sorted search), the lowest resampling variance of the
  standard schemes (each particle is copied ``floor(P w)`` or ``ceil(P w)`` times), and vectorised with no
  per-particle random numbers.
- Estimate: weighted mean of position and velocity, weighted position covariance; the attitude is the
  weighted quaternion mean of Markley et al. (2007), the eigenvector of the largest eigenvalue of
  ``sum_i w_i q_i q_i^T`` (4, 4), which is blind to the sign ambiguity ``q ~ -q`` and needs no reference
  particle; its sign is chosen with ``qw >= 0``. It is computed after the sensor update and before
  resampling (resampling only adds noise to the weighted mean).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics.quadrotor import POS, QUAT, STATE_DIM, VEL
from pixelmpc_jax.perception.estimator import Estimate, Estimator, EstimatorParams, checked_spread, checked_x0
from pixelmpc_jax.world import camera as camera_lib

GRAVITY = 9.81
LIKELIHOODS = ("laplace", "gaussian")
_BIAS_STREAM = 0x0B1A5  # folded into a step's position key for the biases' draws, leaving the other draws alone


@dataclasses.dataclass(frozen=True)
class PFConfig:
    """Static filter configuration (hashable: a new config compiles once).

    Attributes:
        num_particles: P, 6,400 in the paper.
        position_noise_variance: m^2, Gaussian noise added to each particle's position per update (see
            ``position_noise_per_second``). 0.2 in the paper.
        position_noise_per_second: True (default): the variance is a rate, ``variance * dt`` per update;
            False: it is per update, the paper's literal reading (module docstring: why not the default).
        accel_noise_variance: (m/s^2)^2 per axis, added to the accelerometer reading per particle. 0.2.
        gyro_noise_variance: (rad/s)^2 per axis, added to the gyro reading per particle. 0.1.
        missing_corner_penalty_widths: a corner expected but not detected, or detected but not expected,
            costs this many image widths in pixels. 4 in the paper.
        measurement_sigma_px: pixel scale of the likelihood.
        likelihood: "laplace" (``-sum e / sigma``) or "gaussian" (``-0.5 sum (e / sigma)^2``).
        resample_threshold: resample when ESS < threshold * P (1.0: every update).
        penalise_undetected_target: True (the paper): when the target is not detected at all, every particle
            that expects its corners in view pays the missing-corner penalty. False (default): a tick without
            a detection leaves the weights alone (corners missing from a detection are still penalised).
            When the target has just left the image, the true pose sits at the field of view's edge and
            the penalty removes the particles on its inner side at every tick, pushing the estimate away
            from the truth (in our loop the attitude error grew ~0.5 deg/s while the target was out of view).
        imu_bias_std: (accelerometer m/s^2, gyro rad/s), the initial spread of each particle's IMU bias; (0, 0)
            (default, the paper's filter): the particles carry no bias (module docstring).
        imu_bias_walk: (m/s^2, rad/s) per square-root second, the random walk of each particle's bias.
        dt: s, one update per control tick (the tick of :mod:`pixelmpc_jax.timing`); used by the one-mean-sample
            motion model (a preintegrated ``TickIMU`` carries its own ``dt``).
        gravity: m/s^2 along world -z.
    """

    num_particles: int = 6400
    position_noise_variance: float = 0.2
    position_noise_per_second: bool = True
    accel_noise_variance: float = 0.2
    gyro_noise_variance: float = 0.1
    missing_corner_penalty_widths: float = 4.0
    measurement_sigma_px: float = 3.0
    likelihood: str = "laplace"
    resample_threshold: float = 0.5
    penalise_undetected_target: bool = False
    imu_bias_std: tuple = (0.0, 0.0)
    imu_bias_walk: tuple = (0.0, 0.0)
    dt: float = timing.CONTROL_DT
    gravity: float = GRAVITY

    def __post_init__(self):
        if int(self.num_particles) < 1:
            raise ValueError(f"num_particles must be >= 1, got {self.num_particles}")
        for name in ("position_noise_variance", "accel_noise_variance", "gyro_noise_variance",
                     "missing_corner_penalty_widths"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("measurement_sigma_px", "dt"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ValueError(f"resample_threshold must lie in [0, 1], got {self.resample_threshold!r}")
        if self.likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood must be one of {LIKELIHOODS}, got {self.likelihood!r}")
        for name in ("imu_bias_std", "imu_bias_walk"):
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 2 or not all(math.isfinite(v) and v >= 0 for v in value):
                raise ValueError(f"{name} must be 2 finite numbers >= 0 (accelerometer, gyro), got "
                                 f"{getattr(self, name)!r}")
            object.__setattr__(self, name, value)

    @property
    def estimates_bias(self) -> bool:
        """Whether each particle carries an IMU bias (``PFState.bias``)."""
        return any(self.imu_bias_std) or any(self.imu_bias_walk)

    @property
    def position_noise_std(self) -> float:
        """m, std of the position noise of one update."""
        scale = self.dt if self.position_noise_per_second else 1.0
        return math.sqrt(self.position_noise_variance * scale)


@struct.dataclass
class PFState:
    """The filter's particles and weights.

    Attributes:
        particles: (P, 10) robot states ``[p, q(wxyz), v]``.
        log_weights: (P,) normalised log weights (``logsumexp == 0``).
        key: PRNG key, split with purpose names at every step.
        bias: (P, 6) each particle's accelerometer (m/s^2) and gyro (rad/s) bias with
            ``PFConfig.imu_bias_std``, else None.
        unexplained: () int32, the divergence guard's count of informative detections in a row that no particle
            explained (:mod:`~pixelmpc_jax.perception.filter_guards`), else None. The filter's own steps carry it.
    """

    particles: jax.Array
    log_weights: jax.Array
    key: jax.Array
    bias: jax.Array | None = None
    unexplained: jax.Array | None = None


class PFEstimate(NamedTuple):
    """The filter's state estimate. mean: (10,) ``[p, q, v]``; position_cov: (3, 3), m^2."""

    mean: jax.Array
    position_cov: jax.Array


class PFInfo(NamedTuple):
    """Diagnostics of one step.

    Attributes:
        ess: () effective sample size ``1 / sum w^2`` after the sensor update, before resampling.
        position_cov_trace: () m^2, trace of the estimate's position covariance.
        degenerate: () bool, no finite weight was left; particles kept, weights reset to uniform.
        resampled: () bool, the particles were resampled this step.
        max_log_likelihood: () the best particle's log-likelihood of the detection (0 without an update).
        position_cov: (3, 3) m^2, the estimate's position covariance.
    """

    ess: jax.Array
    position_cov_trace: jax.Array
    degenerate: jax.Array
    resampled: jax.Array
    max_log_likelihood: jax.Array
    position_cov: jax.Array


# --------------------------------------------------------------------------------------------------
# Input checks (outside jit: shapes are static, so these also run under jit and vmap tracing).
# --------------------------------------------------------------------------------------------------


def _check_state(state: PFState, config: PFConfig) -> None:
    P = config.num_particles
    if jnp.shape(state.particles) != (P, STATE_DIM) or jnp.shape(state.log_weights) != (P,):
        raise ValueError(
            f"PFState for one filter (vmap batches) with P={P} needs particles ({P}, {STATE_DIM}) and "
            f"log_weights ({P},); got {jnp.shape(state.particles)} and {jnp.shape(state.log_weights)}"
        )
    if config.estimates_bias != (state.bias is not None) or (state.bias is not None and
                                                             jnp.shape(state.bias) != (P, 6)):
        raise ValueError(f"PFState.bias must be ({P}, 6) when the config estimates IMU biases and None otherwise; "
                         f"got {None if state.bias is None else jnp.shape(state.bias)} with imu_bias_std "
                         f"{config.imu_bias_std} and imu_bias_walk {config.imu_bias_walk}")


def _check_imu(imu) -> None:
    for name in ("accel", "gyro"):
        if not hasattr(imu, name):
            raise ValueError(f"imu needs fields 'accel' (3,) and 'gyro' (3,) (e.g. sim.plant.IMU); got {imu!r}")
        if jnp.shape(getattr(imu, name)) != (3,):
            raise ValueError(f"imu.{name} must have shape (3,), got {jnp.shape(getattr(imu, name))}")


def _check_detection(detection) -> None:
    if jnp.shape(detection.corners) != (4, 2) or jnp.shape(detection.corners_visible) != (4,):
        raise ValueError(
            "detection must be one Detection (vmap batches) with corners (4, 2) and corners_visible (4,); got "
            f"{jnp.shape(detection.corners)} and {jnp.shape(detection.corners_visible)}"
        )


# --------------------------------------------------------------------------------------------------
# Initialisation.
# --------------------------------------------------------------------------------------------------


def _small_rotation(rotvec: jax.Array) -> jax.Array:
    """Quaternion (4,) of the rotation vector (3,) (angle = norm, rad)."""
    return quadrotor.quat_exp(rotvec, 1.0)


def init_particles(key: jax.Array, x0: jax.Array, config: PFConfig, spread: tuple) -> PFState:
    """P particles around ``x0`` (10,) with uniform weights (and, with ``config.estimates_bias``, their IMU biases).

    Args:
        key: PRNG key; the filter keeps a split of it.
        x0: (10,) initial state ``[p, q, v]``.
        spread: Gaussian std of ``(position m, attitude rad (body-frame rotation vector), velocity m/s)``, floats.
    """
    P = config.num_particles
    key, key_pos, key_att, key_vel = jax.random.split(key, 4)
    position_std, attitude_std, velocity_std = spread
    dp = position_std * jax.random.normal(key_pos, (P, 3), jnp.float32)
    dtheta = attitude_std * jax.random.normal(key_att, (P, 3), jnp.float32)
    dv = velocity_std * jax.random.normal(key_vel, (P, 3), jnp.float32)
    q0 = quadrotor.normalize_quat(x0[QUAT])
    q = jax.vmap(lambda d: quadrotor.quat_multiply(q0, _small_rotation(d)))(dtheta)  # body-frame perturbation
    particles = jnp.concatenate([x0[POS] + dp, quadrotor.normalize_quat(q), x0[VEL] + dv], axis=-1)
    log_weights = jnp.full((P,), -math.log(P), jnp.float32)
    bias = None
    if config.estimates_bias:  # a stream of its own: the cloud above is drawn as without biases
        std = jnp.repeat(jnp.asarray(config.imu_bias_std, jnp.float32), 3)
        bias = std * jax.random.normal(jax.random.fold_in(key_pos, _BIAS_STREAM), (P, 6), jnp.float32)
    return PFState(particles=particles, log_weights=log_weights, key=key, bias=bias)



# --------------------------------------------------------------------------------------------------
# Motion update.
# --------------------------------------------------------------------------------------------------


def propagate_particle(x: jax.Array, accel: jax.Array, gyro: jax.Array, dt: float, gravity: float = GRAVITY):
    """One particle over one tick with (already noisy) IMU readings. -> (10,).

    q' = q * exp(w dt / 2);  a = R(q_mid) f + [0, 0, -g];  v' = v + a dt;  p' = p + v dt + a dt^2 / 2,
    with ``f`` the body specific force (3,), ``w`` the body rates (3,) and ``q_mid`` the attitude at dt / 2.
    """
    q = x[QUAT]
    q_next = quadrotor.normalize_quat(quadrotor.quat_multiply(q, quadrotor.quat_exp(gyro, dt)))
    q_mid = quadrotor.normalize_quat(quadrotor.quat_multiply(q, quadrotor.quat_exp(gyro, 0.5 * dt)))
    a = quadrotor.quat_rotate(q_mid, accel) + jnp.asarray([0.0, 0.0, -gravity], x.dtype)
    v = x[VEL]
    p_next = x[POS] + v * dt + 0.5 * dt * dt * a
    v_next = v + a * dt
    return jnp.concatenate([p_next, q_next, v_next])


def propagate_preintegrated(x: jax.Array, imu, accel_noise: jax.Array, gyro_noise: jax.Array,
                            gravity: float = GRAVITY) -> jax.Array:
    """One particle over one tick from preintegrated IMU samples (``sim.plant.TickIMU``). -> (10,).

    The particle's noise draws (constant over the tick, like the mean-sample model's) perturb the
    preintegrated rotation by ``exp(n_g dt)`` and the specific force integrals by ``n_a dt`` and
    ``n_a dt^2 / 2``; then ``q' = q dq``, ``v' = v + g dt + R dv``, ``p' = p + v dt + g dt^2 / 2 + R dp``.
    """
    dt = imu.dt
    q = x[QUAT]
    dq = quadrotor.quat_multiply(imu.delta_q, quadrotor.quat_exp(gyro_noise, dt))
    dv = imu.delta_v + accel_noise * dt
    dp = imu.delta_p + 0.5 * accel_noise * dt * dt
    g = jnp.asarray([0.0, 0.0, -gravity], x.dtype)
    v = x[VEL]
    p_next = x[POS] + v * dt + 0.5 * g * dt * dt + quadrotor.quat_rotate(q, dp)
    v_next = v + g * dt + quadrotor.quat_rotate(q, dv)
    q_next = quadrotor.normalize_quat(quadrotor.quat_multiply(q, dq))
    return jnp.concatenate([p_next, q_next, v_next])


def predict(state: PFState, imu, config: PFConfig) -> PFState:
    """Motion update: every particle integrates the IMU with its own noise draw (module docstring).

    ``imu``: the tick's samples preintegrated (``sim.plant.TickIMU``, what the closed loop feeds), or one mean
    sample: anything with ``accel`` (3,) body specific force (m/s^2, +9.81 on body z at rest) and ``gyro``
    (3,) body rates (rad/s), e.g. ``sim.plant.IMU``, integrated over ``config.dt``.
    """
    P = config.num_particles
    key, key_accel, key_gyro, key_pos = jax.random.split(state.key, 4)
    accel_noise = math.sqrt(config.accel_noise_variance) * jax.random.normal(key_accel, (P, 3), jnp.float32)
    gyro_noise = math.sqrt(config.gyro_noise_variance) * jax.random.normal(key_gyro, (P, 3), jnp.float32)
    preintegrated = hasattr(imu, "delta_q")  # the tick's samples (sim.plant.TickIMU), or one mean sample
    if preintegrated:
        imu = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), imu)
        # the noise is per reading: independent over the tick's samples, its mean has 1/S of the variance
        per_reading = jax.lax.rsqrt(jnp.maximum(imu.num_samples, 1.0))
        accel_noise, gyro_noise = accel_noise * per_reading, gyro_noise * per_reading
    bias = state.bias
    if bias is not None:  # each particle reads the IMU less its own bias
        accel_noise, gyro_noise = accel_noise - bias[:, :3], gyro_noise - bias[:, 3:]
    if preintegrated:
        particles = jax.vmap(propagate_preintegrated, in_axes=(0, None, 0, 0, None))(
            state.particles, imu, accel_noise, gyro_noise, config.gravity)
    else:
        accel = jnp.asarray(imu.accel, jnp.float32) + accel_noise
        gyro = jnp.asarray(imu.gyro, jnp.float32) + gyro_noise
        particles = jax.vmap(propagate_particle, in_axes=(0, 0, 0, None, None))(
            state.particles, accel, gyro, config.dt, config.gravity)
    particles = particles.at[:, POS].add(config.position_noise_std * jax.random.normal(key_pos, (P, 3), jnp.float32))
    if bias is not None:
        dt = imu.dt if preintegrated else config.dt
        walk = jnp.repeat(jnp.asarray(config.imu_bias_walk, jnp.float32), 3) * jnp.sqrt(dt)
        bias = bias + walk * jax.random.normal(jax.random.fold_in(key_pos, _BIAS_STREAM), (P, 6), jnp.float32)
    return state.replace(particles=particles, key=key, bias=bias)


# --------------------------------------------------------------------------------------------------
# Sensor update.
# --------------------------------------------------------------------------------------------------


def corner_log_likelihood(
    x: jax.Array, gate_corners: jax.Array, detected_uv: jax.Array, detected: jax.Array,
    camera: camera_lib.Camera, config: PFConfig,
) -> jax.Array:
    """Log-likelihood () of the detected corners for one particle ``x`` (10,).

    Args:
        gate_corners: (4, 3) the gate's inner corners, world frame.
        detected_uv: (4, 2) detected corners, normalised uv.
        detected: (4,) bool, the corner was detected.

    e_k = |uv_pred - uv_det| in px (both), 4 W (exactly one of expected / detected), 0 (neither);
    log l = -sum_k e_k / sigma (laplace) or -0.5 sum_k (e_k / sigma)^2 (gaussian).
    """
    uv, _, in_front = camera_lib.project(gate_corners, x, camera)  # (4, 2), (4,)
    expected = in_front & camera_lib.in_image(uv)
    scale = jnp.asarray([camera.width, camera.height], uv.dtype)
    diff = (uv - detected_uv) * scale
    dist = jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    penalty = config.missing_corner_penalty_widths * camera.width
    error = jnp.where(expected & detected, dist, jnp.where(expected != detected, penalty, 0.0))  # (4,) px
    error = error / config.measurement_sigma_px
    if config.likelihood == "gaussian":
        return -0.5 * jnp.sum(error * error)
    return -jnp.sum(error)


def _normalise(log_weights: jax.Array):
    """Finite-safe normalised log weights and the degenerate flag (no finite weight left)."""
    finite = jnp.isfinite(log_weights)
    degenerate = ~jnp.any(finite)
    lw = jnp.where(finite, log_weights, -jnp.inf)
    lw_max = jnp.max(jnp.where(finite, lw, -jnp.finfo(jnp.float32).max))
    lse = lw_max + jnp.log(jnp.sum(jnp.exp(lw - lw_max)))
    uniform = jnp.full_like(log_weights, -math.log(log_weights.shape[0]))
    return jnp.where(degenerate, uniform, lw - lse), degenerate


def update(state: PFState, detection, gates, camera: camera_lib.Camera, config: PFConfig):
    """Sensor update with one detection of one gate (module docstring for the model).

    Args:
        state: the filter.
        detection: a single ``detector.Detection``; its ``gate_id`` names the gate (negative: no update).
        gates: the map's ``Gate`` batch (G leading axis), ``track.gates``.
        camera: the onboard camera.

    Returns:
        state: new log weights (particles unchanged).
        degenerate: () bool, no finite weight was left and the weights were reset to uniform.
        max_log_likelihood: () the best particle's log-likelihood.
    """
    num_gates = gates.centre.shape[0]
    gate_id = jnp.asarray(detection.gate_id, jnp.int32)
    informative = gate_id >= 0
    if not config.penalise_undetected_target:
        informative = informative & jnp.asarray(detection.found, bool)
    gate = jax.tree_util.tree_map(lambda leaf: leaf[jnp.clip(gate_id, 0, num_gates - 1)], gates)
    corners = gate.corners()  # (4, 3)
    detected = jnp.asarray(detection.corners_visible, bool) & jnp.asarray(detection.found, bool)
    detected_uv = jnp.asarray(detection.corners, jnp.float32)
    log_lik = jax.vmap(corner_log_likelihood, in_axes=(0, None, None, None, None, None))(
        state.particles, corners, detected_uv, detected, camera, config)  # (P,)
    ok = jnp.isfinite(log_lik) & jnp.all(jnp.isfinite(state.particles), axis=-1)
    log_lik = jnp.where(informative, jnp.where(ok, log_lik, -jnp.inf), 0.0)
    log_weights, degenerate = _normalise(state.log_weights + log_lik)
    max_ll = jnp.max(log_lik)  # -inf when no particle explains the detection
    return state.replace(log_weights=log_weights), degenerate, max_ll


# --------------------------------------------------------------------------------------------------
# Resampling and the estimate.
# --------------------------------------------------------------------------------------------------


def effective_sample_size(log_weights: jax.Array) -> jax.Array:
    """ESS = 1 / sum w^2 of normalised log weights (P,). -> ()."""
    return jnp.exp(-jax.nn.logsumexp(2.0 * log_weights))


def systematic_resample(key: jax.Array, log_weights: jax.Array) -> jax.Array:
    """(P,) int32 ancestor indices: P pointers ``(i + u) / P``, ``u ~ U[0, 1)``, located on the weights' CDF."""
    P = log_weights.shape[0]
    cdf = jnp.cumsum(jnp.exp(log_weights))
    cdf = cdf / cdf[-1]
    pointers = (jnp.arange(P, dtype=cdf.dtype) + jax.random.uniform(key, (), cdf.dtype)) / P
    return jnp.clip(jnp.searchsorted(cdf, pointers, side="left"), 0, P - 1).astype(jnp.int32)


def _maybe_resample(state: PFState, config: PFConfig):
    P = config.num_particles
    key, key_resample = jax.random.split(state.key)
    ess = effective_sample_size(state.log_weights)
    resample = ess < config.resample_threshold * P

    def do(_):
        idx = systematic_resample(key_resample, state.log_weights)
        bias = None if state.bias is None else state.bias[idx]
        return state.particles[idx], jnp.full((P,), -math.log(P), jnp.float32), bias

    def keep(_):
        return state.particles, state.log_weights, state.bias

    particles, log_weights, bias = jax.lax.cond(resample, do, keep, None)
    return state.replace(particles=particles, log_weights=log_weights, key=key, bias=bias), ess, resample


def weighted_estimate(state: PFState) -> PFEstimate:
    """Weighted mean state (10,) (Markley quaternion mean, ``qw >= 0``) and position covariance (3, 3)."""
    w = jnp.exp(state.log_weights)
    w = w / jnp.sum(w)
    particles = jnp.where(w[:, None] > 0, state.particles, 0.0)  # a weightless NaN particle must not leak
    p = particles[:, POS]
    p_mean = w @ p
    dp = p - p_mean
    cov = (w[:, None] * dp).T @ dp
    v_mean = w @ particles[:, VEL]
    q = particles[:, QUAT]
    M = (w[:, None] * q).T @ q  # (4, 4), sum_i w_i q_i q_i^T
    _, vecs = jnp.linalg.eigh(M)
    q_mean = vecs[:, -1]
    q_mean = quadrotor.normalize_quat(jnp.where(q_mean[0] < 0, -q_mean, q_mean))
    return PFEstimate(mean=jnp.concatenate([p_mean, q_mean, v_mean]), position_cov=cov)


# --------------------------------------------------------------------------------------------------
# One tick.
# --------------------------------------------------------------------------------------------------




def tick(state: PFState, imu, detection, gates, camera: camera_lib.Camera, config: PFConfig):
    """One control tick: predict with ``imu``, update with ``detection``, resample if ESS < threshold * P.

    Args:
        state: the filter.
        imu: the IMU over the tick that led to now (a ``sim.plant.TickIMU``, or one mean sample with
            ``accel`` (3,), ``gyro`` (3,); see :func:`predict`), or None to skip the motion update (the first tick).
        detection: the target gate's ``Detection`` now (``found=False``: nothing detected; the weights are
            left alone unless ``config.penalise_undetected_target``), or None to skip the sensor update.
        gates: the map's ``Gate`` batch (G leading axis): the known corners.
        camera: the onboard camera.

    Returns:
        state: the filter after the tick (resampled or not).
        estimate: ``PFEstimate`` of the weighted particles after the update (before resampling).
        info: ``PFInfo``.
    """
    if imu is not None:
        state = predict(state, imu, config)
    if detection is not None:
        state, degenerate, max_ll = update(state, detection, gates, camera, config)
    else:
        log_weights, degenerate = _normalise(state.log_weights)
        state, max_ll = state.replace(log_weights=log_weights), jnp.asarray(0.0, jnp.float32)
    estimate = weighted_estimate(state)
    state, ess, resampled = _maybe_resample(state, config)
    info = PFInfo(
        ess=ess,
        position_cov_trace=jnp.trace(estimate.position_cov),
        degenerate=degenerate,
        resampled=resampled,
        max_log_likelihood=max_ll,
        position_cov=estimate.position_cov,
    )
    return state, estimate, info


def check_inputs(state: PFState, imu, detection, config: PFConfig) -> None:
    """The shapes of a tick's inputs (outside jit; shapes are static, so this also runs while tracing)."""
    _check_state(state, config)
    if imu is not None:
        _check_imu(imu)
    if detection is not None:
        _check_detection(detection)


# --------------------------------------------------------------------------------------------------
# The estimator.
# --------------------------------------------------------------------------------------------------


def make_particle_filter(config: PFConfig = PFConfig(), spread=(0.5, 0.05, 0.5)) -> Estimator:
    """The particle filter as an :class:`~pixelmpc_jax.perception.estimator.Estimator` (pure ``init``, ``step``).

    Args:
        config: the filter's configuration.
        spread: Gaussian std of the initial cloud about ``x0``: ``(position m, attitude rad (body-frame rotation
            vector), velocity m/s)``.

    ``init(key, x0)``: :func:`init_particles`. ``step(state, imu, detection, params)``: :func:`tick` on
    ``params.gates`` and ``params.camera``; its ``info`` is :class:`PFInfo`, the detection passes as given.
    """
    spread = checked_spread(spread)

    def init(key: jax.Array, x0: jax.Array) -> PFState:
        return init_particles(key, checked_x0(x0), config, spread)

    def step(state: PFState, imu, detection, params: EstimatorParams):
        state, estimate, info = tick(state, imu, detection, params.gates, params.camera, config)
        estimated = Estimate(mean=estimate.mean, position_cov_trace=info.position_cov_trace, detection=detection)
        return estimated, state, info

    def check(state: PFState, imu, detection, params: EstimatorParams):
        check_inputs(state, imu, detection, config)
        return state, imu, detection, params

    return Estimator(init=init, step=step, check=check, config=config)
