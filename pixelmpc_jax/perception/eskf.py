"""An error-state Kalman filter (ESKF) on the tick's preintegrated IMU and the detected gate's corners.

An alternative to the particle filter of Section V-D (:mod:`~pixelmpc_jax.perception.particle_filter`), fed the
same way, one :func:`tick` per control tick (the estimator of :func:`make_eskf`): the IMU of the tick that led to now
(``sim.plant.TickIMU``) and the detection of the target gate (``detector.Detection``, its corners reprojected
through the map and the camera). It estimates the robot state ``x = [p, q(wxyz), v]`` (10,) and the IMU's biases.

- State. The nominal state holds position, velocity, attitude (``q``, body to world) and the accelerometer
  (m/s^2) and gyro (rad/s) biases (:class:`ESKFBelief`); the error state is 15-dimensional, ``dx = [dp, dv,
  dtheta, dba, dbg]``, with the attitude error in the body frame: ``q_true = q * exp(dtheta)``. The true state is
  the nominal one with the error injected (:func:`inject`); the covariance is that of ``dx``.
- Propagation. The nominal state moves exactly as a particle of the particle filter does
  (:func:`~pixelmpc_jax.perception.particle_filter.propagate_preintegrated`), with the bias estimate subtracted:
  ``q' = q dq exp(-b_g dt)``, ``v' = v + g dt + R (dv - b_a dt)``, ``p' = p + v dt + g dt^2 / 2 + R (dp - b_a
  dt^2 / 2)``. The covariance: ``P' = F P F^T + G Q G^T + Q_walk``, with ``F`` and ``G`` the Jacobians of that
  same propagation with respect to the error state and to the tick's mean IMU noise (analytic,
  :func:`propagation_jacobians`, checked against ``jax.jacfwd`` in the tests: it compiles in a fifth of the
  time), the noise's variance ``density^2 / dt`` per axis (the mean of a tick's samples of white noise of that
  density), the biases walking by ``walk^2 dt``, and the velocity and attitude by the small walks that cover what
  preintegration misses of the simulated plant (``ESKFConfig.velocity_walk``, ``attitude_walk``).
- Update. The 4 inner corners of the gate the detection names are projected into the camera; per detected corner
  (not within ``ESKFConfig.border_margin_px`` of the image border), the innovation is the detected minus the
  predicted pixel (px), ``H`` its Jacobian with respect to the error state (:func:`reproject_corners`, analytic,
  checked against ``jax.jacfwd``), ``R = sigma^2 I`` (with ``ESKFConfig.map_sigma_m``, plus the gate's offset from
  the map, which its corners share). A corner whose Mahalanobis distance ``d^2 = r^T S_k^-1 r`` under its own
  prior innovation covariance ``S_k`` exceeds ``ESKFConfig.gate_chi2`` is rejected; an accepted one is reweighted
  by a Huber (or Cauchy) weight ``w(d)``, its noise inflated to ``R / w``. With
  ``ESKFConfig.joint_gate`` the accepted corners are then gated together: when their joint ``r^T S^-1 r`` exceeds
  the 99.9 % quantile of chi-square with two degrees of freedom per corner, the whole detection is rejected. A
  false detection (another gate's image under the target's name) moves every corner a little, each within its own
  gate, in a pattern (a shrunk or shifted outline) that no error of the pose explains; the joint gate catches it
  where the per-corner one cannot. The accepted corners are applied together (Joseph form, symmetrised, then the
  ESKF reset of the attitude block). A tick whose corners are all rejected leaves the belief exactly as a tick
  without a detection (the update is skipped, not applied with zero gain). With
  ``ESKFConfig.noise_adapt_rate`` > 0 the corners' noise follows what the innovations show: a scale of ``R`` in
  the belief, moved after each tick by the corners' clipped Mahalanobis distances (a detector noisier than the
  filter was told otherwise starves it: the gate rejects most corners and the estimate drifts off).
- Late detections. A detection captured ``delay_ticks`` ticks before it reaches the filter is applied at the tick
  it was captured. The state keeps a fixed-lag window (``ESKFConfig.max_delay_ticks`` ticks): the belief before
  the window (the anchor) and the window's IMU inputs and detections (:class:`ESKFState`). Each step appends the
  tick, files the detection at its capture tick, and replays the window from the anchor (predict, update, per
  tick); the belief after the window's first tick becomes the next anchor. A detection on time is filed at the
  newest tick, a late one further back: both go through the same code, so a detection delivered late gives the
  estimate a filter that received it on time gives, once it has been delivered (to the bit, on one device). The
  price is ``max_delay_ticks + 1`` predictions and updates per step.

Numerics: float32 as the rest of the project; covariances symmetrised after every prediction and update;
quaternions renormalised; the attitude logarithm and the padding ticks of the window (``dt = 0``) take branches
that cannot make NaN. :func:`nees` and :func:`state_error` compare an estimate with a true state.

Consistency (``tests/test_eskf.py``, 20 replays of 20 s of flown laps, 2 px corners, initial errors and IMU
biases drawn from the prior): the run-averaged NEES of position, velocity and attitude lies in its 95 % band on
85-92 % of the ticks with a detection (four sets of 20 laps; a consistent filter would give about 95 %), the NIS
on 94-95 %. The NEES is a little high (about 10) in the first 5 s, while large initial errors are worked off,
and it swings with the geometry afterwards. What remains is the EKF's own: linearised about its estimate, it
gains a little information that is not there along weakly observed directions (yaw against lateral position
when a far gate shows two corners). Before a gate at rest its NEES creeps from 7 to 12 over 10 s, which
Jacobians taken at the true state do not do; relinearising the update (iterated EKF), a statistically
linearised update and a right-invariant error state were tried and did not help on the laps. After seconds
without a detection (metres of position uncertainty) one corner can pull the estimate the wrong way and the
gate then rejects the true corners: the filter has no recovery of its own (the particle filter's guards do).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics.quadrotor import POS, QUAT, STATE_DIM, VEL
from pixelmpc_jax.perception.estimator import Estimate, Estimator, EstimatorParams, checked_spread, checked_x0
from pixelmpc_jax.perception.particle_filter import GRAVITY, propagate_preintegrated
from pixelmpc_jax.settings import Range, check, setting
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import track as track_lib

ERROR_DIM = 15  # [dp, dv, dtheta, dba, dbg]
NAV_DIM = 9  # [dp, dv, dtheta]: what NEES is computed over
NOISE_DIM = 6  # the tick's mean IMU noise [accelerometer, gyro]
NUM_CORNERS = 4
ROBUST_LOSSES = ("huber", "cauchy", "none")
CHI2_2DOF_999 = 13.815510557964274  # 99.9 % quantile of chi-square with 2 degrees of freedom: one corner
# 99.9 % quantiles of chi-square with 2, 4, 6 and 8 degrees of freedom: the joint gate of 1-4 accepted corners
CHI2_JOINT_999 = (13.815510557964274, 18.46682695290317, 22.457744484825323, 26.12448155837614)
# m, std per axis of a gate's surveyed position: a tape-measured course (the moderate map fault moves each gate 0.3 m
# horizontally, 0.21 m per horizontal axis on average); the default ``ESKFConfig.map_sigma_m``
SURVEYED_MAP_SIGMA_M = 0.2
# The simulated IMU (alphapilot_course.json, vehicle.imu_noise_variance; sim/plant.py): white noise of these
# variances per sample at the plant's rate; as densities, sigma * sqrt(sample interval).
PLANT_ACCEL_VARIANCE = 0.005  # (m/s^2)^2 per sample
PLANT_GYRO_VARIANCE = 0.003  # (rad/s)^2 per sample
_SMALL_ANGLE_SQ = 1e-10  # below this |q_vec|^2 the attitude logarithm is its first order, 2 q_vec


@dataclasses.dataclass(frozen=True)
class ESKFConfig:
    """Static filter configuration (hashable: a new config compiles once).

    Attributes:
        accel_noise_density: m/s^2/sqrt(Hz), white noise of the accelerometer. Default: the simulated IMU's
            (variance 0.005 per sample at 960 Hz).
        gyro_noise_density: rad/s/sqrt(Hz), white noise of the gyro. Default: the simulated IMU's (0.003 at 960 Hz).
        accel_bias_walk: m/s^3/sqrt(Hz), random walk of the accelerometer bias.
        gyro_bias_walk: rad/s^2/sqrt(Hz), random walk of the gyro bias.
        accel_bias_std: m/s^2, prior std of the accelerometer bias per axis (about a zero estimate at the start):
            the moderate IMU bias of ``sim/faults.py`` (0.1-0.2 m/s^2) is within 1 sigma, its severe one (0.3-0.5)
            is still learnt (about 15 s on a lap).
        gyro_bias_std: rad/s, prior std of the gyro bias per axis (moderate fault 0.01, severe 0.05 rad/s).
        velocity_walk: m/s/sqrt(s), random walk of the velocity beyond the IMU's noise: what preintegrated samples
            miss of the vehicle's motion. The simulated plant integrates each 960 Hz substep with explicit Euler on
            the substep's start while its IMU samples its end, so a tick's preintegrated velocity is off by the
            change of specific force over the tick times 1/960 s (measured on flown laps: a few mm/s per tick at
            racing jerk, up to 0.015 m/s accumulated); 0.005 covers it (0.016 m/s after 10 s).
        attitude_walk: rad/sqrt(s), the same for the attitude (the plant turns with the substep's starting rate,
            the gyro samples the end rate: up to ~6 mrad accumulated on flown laps).
        measurement_sigma_px: pixels, std of a detected corner per image axis.
        border_margin_px: pixels; a detected corner closer than this to the image border is not used. A detector
            reports a corner only when it falls inside the image, so a noisy corner near the border is reported
            more often on the inner side (a bias); the image detector itself keeps corners 2 px inside.
        gate_chi2: a corner whose squared Mahalanobis distance under its prior innovation covariance exceeds this
            is rejected (default: the 99.9 % quantile of chi-square with 2 degrees of freedom).
        robust_loss: "huber" (``w = min(1, c / d)``), "cauchy" (``w = 1 / (1 + d^2 / c^2)``) or "none"; an
            accepted corner's noise is inflated to ``R / w`` (``d`` its Mahalanobis distance, ``c`` below).
        robust_threshold: ``c``, the Mahalanobis distance where the robust weight departs from 1 (Huber).
        joint_gate: also reject the whole detection when its accepted corners together fail the chi-square gate
            (:data:`CHI2_JOINT_999`); False: the per-corner gate only.
        max_delay_ticks: the latest a detection may arrive, in control ticks; the window's length.
        map_sigma_m: m, std per axis of each gate's position in the map (0: the map is exact; the default,
            :data:`SURVEYED_MAP_SIGMA_M`, a tape-measured course's accuracy: over the fault grid's moderate cells
            on the ESKF it finished 258 of 300 laps against the exact map's 247, and 9/10 and 10/10 with the gates
            0.3 m from the map against 3/10 and 7/10; docs/robustness.md). A gate
            placed off its mapped position moves all its corners together; with this > 0 the corners' noise gains
            that shared part, ``sigma^2 H_p H_p^T`` (``H_p`` their Jacobian with respect to the position, which is
            minus that with respect to the gate's), in the gate, the weights and the update alike. The offset is
            taken afresh at each detection (not kept as a state), so a gate seen for long still pulls the
            estimate onto itself, more slowly.
        align_s: s of IMU readings at rest before the lap that :func:`align` averages (0: none, the default; the
            lap's first tick is the filter's first input). On the pad the vehicle neither moves nor turns, so the mean
            gyro reading is the gyro bias and the mean accelerometer reading is gravity's specific force plus the
            accelerometer bias: one update with the readings' own noise over that time (``density^2 / align_s``)
            learns the gyro bias and the accelerometer's bias along gravity. Its bias across gravity reads as a tilt
            does, so the update only ties the two together (the attitude prior decides how much each gets).
        noise_adapt_rate: how fast the corners' noise follows what the innovations show (0: never, the default;
            the noise stays ``measurement_sigma_px``). With ``a`` > 0 the belief carries a scale ``s`` of the
            corners' variance (``R = s sigma^2 I``). After each tick with usable corners, ``s`` becomes
            ``s (1 - a + a m)``, where ``m`` is the corners' mean squared Mahalanobis distance per degree of
            freedom under their prior innovation covariance, each distance clipped at ``gate_chi2``. A consistent
            filter has ``m`` = 1 on average, so ``s`` holds; corners k times noisier than ``sigma`` take ``s`` to
            about k^2 within a few ``1 / a`` detections. The clip bounds what one false corner can add.
        noise_scale_max: the largest ``s`` (its smallest is 1: the configured noise is a floor).
        gravity: m/s^2 along world -z.
    """

    accel_noise_density: float = math.sqrt(PLANT_ACCEL_VARIANCE * timing.PLANT_DT)
    gyro_noise_density: float = math.sqrt(PLANT_GYRO_VARIANCE * timing.PLANT_DT)
    accel_bias_walk: float = 1e-3
    gyro_bias_walk: float = 1e-4
    accel_bias_std: float = 0.2
    gyro_bias_std: float = 0.02
    velocity_walk: float = 0.005
    attitude_walk: float = 5e-4
    measurement_sigma_px: float = 2.0
    border_margin_px: float = 2.0
    gate_chi2: float = CHI2_2DOF_999
    robust_loss: str = "huber"
    robust_threshold: float = 3.0
    joint_gate: bool = True
    max_delay_ticks: int = 3
    gravity: float = GRAVITY
    map_sigma_m: float = setting(
        SURVEYED_MAP_SIGMA_M, range=Range(0.0, 100.0, unit="m"),
        help="Kalman filter: each gate stands within M, in {range}, per axis (1 sigma) of where the map says, so a "
             "gate's corners share that offset in the filter's update (0: an exact map; the default, a tape-measured "
             "course's accuracy)")
    align_s: float = setting(
        0.0, range=Range(0.0, 60.0, unit="s"),
        help="Kalman filter: the filter averages S, in {range}, of its IMU's readings at rest before the lap (on the "
             "pad) and learns the gyro bias and the accelerometer's along gravity from them (0: none; 2 is a usual "
             "pre-flight wait)")
    noise_adapt_rate: float = setting(
        0.0, range=Range(0.0, 1.0),
        help="Kalman filter: the corners' noise follows what the filter's innovations show, moving by RATE, in "
             "{range}, of the way at each detection, never below measurement_sigma_px (0: the noise stays; 0.05 takes "
             "a 6 px detector in a few seconds)")
    noise_scale_max: float = 25.0

    def __post_init__(self):
        check(self)  # the map's sigma, the alignment and the noise's adaptation, each in its field's range
        for name in ("accel_noise_density", "gyro_noise_density", "accel_bias_walk", "gyro_bias_walk",
                     "accel_bias_std", "gyro_bias_std", "velocity_walk", "attitude_walk", "border_margin_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("measurement_sigma_px", "gate_chi2", "robust_threshold", "gravity"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not isinstance(self.joint_gate, bool):
            raise ValueError(f"joint_gate must be True or False, got {self.joint_gate!r}")
        if self.robust_loss not in ROBUST_LOSSES:
            raise ValueError(f"robust_loss must be one of {ROBUST_LOSSES}, got {self.robust_loss!r}")
        top = self.noise_scale_max
        if isinstance(top, bool) or not isinstance(top, (int, float)) or not (math.isfinite(top) and top >= 1):
            raise ValueError(f"noise_scale_max must be a finite number >= 1, got {top!r}")
        delay = self.max_delay_ticks
        if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= 16:
            raise ValueError(f"max_delay_ticks must be an integer number of ticks in [0, 16], got {delay!r}")


@struct.dataclass
class ESKFBelief:
    """The nominal state and the error state's covariance at one tick.

    Attributes:
        x: (10,) nominal robot state ``[p, q(wxyz), v]``.
        bias: (6,) nominal IMU biases ``[b_a (m/s^2), b_g (rad/s)]``, body frame, added to the true readings.
        cov: (15, 15) covariance of the error state ``[dp, dv, dtheta, dba, dbg]``.
        noise_scale: () the corners' noise variance as a multiple of ``measurement_sigma_px^2`` (1 unless
            ``ESKFConfig.noise_adapt_rate`` > 0).
        gate_offset: (G, 4) with the gates as states (:func:`init_belief`'s ``gate_std``), each gate's estimated
            offset from the map ``[dx, dy, dz (m), dyaw (rad)]`` (``track.offset_gates``), its error the covariance's
            rows ``15 + 4 g`` to ``19 + 4 g``; None: the map's gates are taken as they are.
    """

    x: jax.Array
    bias: jax.Array
    cov: jax.Array
    noise_scale: jax.Array
    gate_offset: jax.Array | None = None


class ImuInput(NamedTuple):
    """What the filter integrates of a tick's IMU (``sim.plant.TickIMU``): delta_q (4,), delta_v (3,), delta_p
    (3,) and dt (), with the TickIMU's meanings. A window's padding tick has dt = 0 and is not integrated."""

    delta_q: jax.Array
    delta_v: jax.Array
    delta_p: jax.Array
    dt: jax.Array


class CornerInput(NamedTuple):
    """What the filter uses of a detection: corners (4, 2) normalised uv; detected (4,) bool (found and in view,
    of a named gate); gate_id () int32 (negative: none)."""

    corners: jax.Array
    detected: jax.Array
    gate_id: jax.Array


@struct.dataclass
class ESKFState:
    """The filter: the belief before its window, the window's inputs, and the newest belief.

    With D = ``ESKFConfig.max_delay_ticks`` after a step at tick k, the window holds ticks k-D+1..k.

    Attributes:
        anchor: the belief at tick k-D, after its update: where every step's replay starts.
        imu: ImuInput, leaves with leading axis D: the IMU into each tick of the window, oldest first.
        imu_valid: (D,) bool, the tick was integrated (False: before the first step, or a step without IMU).
        detections: CornerInput, leaves with leading axis D: the detection captured at each tick of the window (D, K
            with K > 1 detections a tick (:func:`make_eskf`'s ``detections_per_tick``): each tick's K gates').
        latest: the belief at tick k, after its update (what :func:`eskf_estimate` reports).
    """

    anchor: ESKFBelief
    imu: ImuInput
    imu_valid: jax.Array
    detections: CornerInput
    latest: ESKFBelief


class ESKFEstimate(NamedTuple):
    """The filter's estimate (the fields of ``PFEstimate`` first).

    Attributes:
        mean: (10,) ``[p, q, v]``, ``qw >= 0``.
        position_cov: (3, 3) m^2.
        bias: (6,) ``[b_a (m/s^2), b_g (rad/s)]``.
        covariance: (15, 15) of the error state ``[dp, dv, dtheta, dba, dbg]`` (15 + 4G square with the gates as
            states, their offsets' errors after the vehicle's).
        gate_offset: (G, 4) each gate's estimated offset from the map (:class:`ESKFBelief`); None without gate states.
    """

    mean: jax.Array
    position_cov: jax.Array
    bias: jax.Array
    covariance: jax.Array
    gate_offset: jax.Array | None = None


class ESKFInfo(NamedTuple):
    """Diagnostics of one step; the corner fields describe the detection delivered at this step, as updated at
    the tick it was captured (zeros where it was dropped or there was none).

    Attributes:
        position_cov_trace: () m^2, trace of the newest position covariance.
        innovation: (4, 2) px, detected minus predicted corner (0 where not usable: not detected, behind the
            camera, or within ``border_margin_px`` of the image border).
        innovation_cov: (4, 2, 2) px^2, each corner's prior innovation covariance ``S_k = H_k P H_k^T + R``.
        corner_mahalanobis2: (4,) ``r_k^T S_k^-1 r_k`` (0 where not usable).
        accepted: (4,) bool, the corner passed the chi-square gate (and the detection the joint one) and
            was applied.
        weight: (4,) the robust weight of each accepted corner (its noise was ``R / weight``); 1 otherwise.
        nis: () the accepted corners' joint normalised innovation squared ``r^T S^-1 r`` (unweighted ``R``).
        nis_dof: () int32, its degrees of freedom, 2 per accepted corner.
        delay_ticks: () int32, the delay the detection arrived with.
        dropped: () bool, the detection was later than ``max_delay_ticks`` (or earlier than now) and was dropped.
        noise_scale: () the newest belief's scale of the corners' noise variance (1 unless
            ``ESKFConfig.noise_adapt_rate`` > 0).
        estimate: the filter's whole estimate at now (:class:`ESKFEstimate`: its biases and error covariance too).
    """

    position_cov_trace: jax.Array
    innovation: jax.Array
    innovation_cov: jax.Array
    corner_mahalanobis2: jax.Array
    accepted: jax.Array
    weight: jax.Array
    nis: jax.Array
    nis_dof: jax.Array
    delay_ticks: jax.Array
    dropped: jax.Array
    noise_scale: jax.Array
    estimate: ESKFEstimate


# --------------------------------------------------------------------------------------------------
# The error state: injection and difference.
# --------------------------------------------------------------------------------------------------


def skew(v: jax.Array) -> jax.Array:
    """(3, 3) cross-product matrix of ``v`` (3,): ``skew(a) @ b = a x b``."""
    zero = jnp.zeros((), v.dtype)
    return jnp.stack([jnp.stack([zero, -v[2], v[1]]), jnp.stack([v[2], zero, -v[0]]),
                      jnp.stack([-v[1], v[0], zero])])


def rotation_vector(q: jax.Array) -> jax.Array:
    """(3,) rotation vector (axis times angle, rad, angle in [0, pi]) of a unit quaternion (4,): the logarithm
    ``theta`` with ``q = exp(theta)`` up to sign. NaN-free with a finite derivative at the identity (its first
    order ``2 q_vec`` below a tiny angle)."""
    q = jnp.where(q[0] < 0, -q, q)
    w, v = q[0], q[1:]
    n2 = jnp.sum(v * v)
    big = n2 > _SMALL_ANGLE_SQ
    n = jnp.sqrt(jnp.where(big, n2, 1.0))
    return jnp.where(big, (2.0 * jnp.arctan2(n, w) / n) * v, 2.0 * v)


def inject(x: jax.Array, bias: jax.Array, dx: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The state with the error ``dx`` (15,) ``[dp, dv, dtheta, dba, dbg]`` injected: ``p + dp``, ``v + dv``,
    ``q exp(dtheta)`` (renormalised), ``bias + [dba, dbg]``. -> ``(x (10,), bias (6,))``."""
    q = quadrotor.normalize_quat(quadrotor.quat_multiply(x[QUAT], quadrotor.quat_exp(dx[6:9], 1.0)))
    return jnp.concatenate([x[POS] + dx[0:3], q, x[VEL] + dx[3:6]]), bias + dx[9:15]


def state_error(x_ref: jax.Array, x: jax.Array) -> jax.Array:
    """(9,) ``[dp, dv, dtheta]`` with ``x = x_ref`` injected with them: ``p - p_ref``, ``v - v_ref``,
    ``log(q_ref^-1 q)`` (body frame of ``x_ref``). Both states (10,) ``[p, q, v]``."""
    dq = quadrotor.quat_multiply(quadrotor.quat_conjugate(quadrotor.normalize_quat(x_ref[QUAT])),
                                 quadrotor.normalize_quat(x[QUAT]))
    return jnp.concatenate([x[POS] - x_ref[POS], x[VEL] - x_ref[VEL], rotation_vector(dq)])


def _corrected(belief: ESKFBelief, dx: jax.Array, cov: jax.Array) -> ESKFBelief:
    """The belief after an update: the error ``dx`` (15,) injected (15 + 4G: the gates' offsets' errors added to
    them), and the updated covariance ``cov`` moved into the new attitude's frame (the ESKF reset of the attitude
    block) and symmetrised."""
    x, bias = inject(belief.x, belief.bias, dx[:ERROR_DIM])
    gate_offset = belief.gate_offset
    if gate_offset is not None:
        gate_offset = gate_offset + dx[ERROR_DIM:].reshape(gate_offset.shape)
    reset = jnp.eye(cov.shape[0], dtype=cov.dtype).at[6:9, 6:9].add(-skew(0.5 * dx[6:9]))  # the attitude error's frame
    return ESKFBelief(x=x, bias=bias, cov=_symmetric(reset @ _symmetric(cov) @ reset.T),
                      noise_scale=belief.noise_scale, gate_offset=gate_offset)


def _symmetric(P: jax.Array) -> jax.Array:
    return 0.5 * (P + P.T)


def _tree_where(condition: jax.Array, a, b):
    return jax.tree_util.tree_map(lambda u, v: jnp.where(condition, u, v), a, b)


# --------------------------------------------------------------------------------------------------
# Propagation.
# --------------------------------------------------------------------------------------------------


def propagate_nominal(x: jax.Array, bias: jax.Array, imu, gravity: float = GRAVITY) -> jax.Array:
    """The nominal state (10,) one tick later: the particle filter's preintegrated motion with the bias estimate
    subtracted (``propagate_preintegrated`` with noise ``-bias``)."""
    return propagate_preintegrated(x, imu, -bias[:3], -bias[3:], gravity)


def propagation_jacobians(belief: ESKFBelief, imu) -> tuple[jax.Array, jax.Array]:
    """The error state's transition over one tick: ``dx' = F dx + G n``, with ``n`` (6,) the tick's mean IMU noise
    (accelerometer m/s^2, gyro rad/s) entering as the bias does (:func:`propagate_nominal`).

    With ``R`` the attitude now, ``dR`` the bias-corrected rotation over the tick, ``dv_c = dv - b_a dt``,
    ``dp_c = dp - b_a dt^2 / 2`` and ``J = I + [b_g dt]x / 2`` (the right Jacobian of ``exp(-b_g dt)``, first order):
    ``dp' = dp + dt dv - R [dp_c]x dtheta - dt^2 / 2 R dba``, ``dv' = dv - R [dv_c]x dtheta - dt R dba``,
    ``dtheta' = dR^T dtheta - dt J dbg``; the noise as ``-dba`` and ``-dbg``. These are the derivatives of
    :func:`propagate_nominal` through :func:`inject` and :func:`state_error` (``tests/test_eskf.py`` checks them
    against ``jax.jacfwd``). -> F (15, 15), G (15, 6).
    """
    dtype = belief.x.dtype
    dt = jnp.asarray(imu.dt, dtype)
    accel_bias, gyro_bias = belief.bias[:3], belief.bias[3:]
    R = quadrotor.rotation_matrix(quadrotor.normalize_quat(belief.x[QUAT]))
    dR = quadrotor.rotation_matrix(quadrotor.normalize_quat(
        quadrotor.quat_multiply(imu.delta_q, quadrotor.quat_exp(-gyro_bias, dt))))
    dv = imu.delta_v - accel_bias * dt
    dp = imu.delta_p - 0.5 * accel_bias * dt * dt
    I3, Z3 = jnp.eye(3, dtype=dtype), jnp.zeros((3, 3), dtype)
    J = I3 + 0.5 * skew(gyro_bias * dt)
    F = jnp.block([[I3, dt * I3, -R @ skew(dp), -0.5 * dt * dt * R, Z3],
                   [Z3, I3, -R @ skew(dv), -dt * R, Z3],
                   [Z3, Z3, dR.T, Z3, -dt * J],
                   [Z3, Z3, Z3, I3, Z3],
                   [Z3, Z3, Z3, Z3, I3]])
    G = (-F[:, 9:15]).at[9:].set(0.0)  # the noise enters as the biases do, but the biases do not keep it
    return F, G


def _predict(belief: ESKFBelief, imu: ImuInput, config: ESKFConfig) -> ESKFBelief:
    """Propagate the nominal state and the covariance over one tick (module docstring)."""
    dtype = belief.x.dtype
    F, G = propagation_jacobians(belief, imu)
    dt = jnp.asarray(imu.dt, dtype)
    dt_safe = jnp.where(dt > 0, dt, 1.0)  # a padding tick (dt = 0) has G = 0: its noise must not be inf
    densities = jnp.asarray([config.accel_noise_density] * 3 + [config.gyro_noise_density] * 3, dtype)
    mean_noise_var = densities**2 / dt_safe  # (6,) variance of the tick's mean reading
    walk = jnp.asarray([0.0] * 3 + [config.velocity_walk] * 3 + [config.attitude_walk] * 3
                       + [config.accel_bias_walk] * 3 + [config.gyro_bias_walk] * 3, dtype)
    x_next = propagate_nominal(belief.x, belief.bias, imu, config.gravity)
    if belief.gate_offset is None:
        cov = F @ belief.cov @ F.T + (G * mean_noise_var) @ G.T + jnp.diag(walk**2 * dt)
    else:  # the gates stand still: their block keeps, their cross-covariance with the vehicle moves with it
        vehicle, cross = belief.cov[:ERROR_DIM, :ERROR_DIM], F @ belief.cov[:ERROR_DIM, ERROR_DIM:]
        moved = F @ vehicle @ F.T + (G * mean_noise_var) @ G.T + jnp.diag(walk**2 * dt)
        cov = jnp.block([[moved, cross], [cross.T, belief.cov[ERROR_DIM:, ERROR_DIM:]]])
    return belief.replace(x=x_next, cov=_symmetric(cov))


# --------------------------------------------------------------------------------------------------
# Corner update.
# --------------------------------------------------------------------------------------------------


def reproject_corners(x: jax.Array, gate_corners: jax.Array, camera: camera_lib.Camera):
    """The gate's corners seen from ``x`` (10,) and their Jacobian with respect to the error state.

    With ``b = R^T (P - p)`` a corner in the body frame and ``C`` the body-to-camera rotation, the camera point is
    ``c = C b`` and, the error injected, ``dc = -C R^T dp + C [b]x dtheta``; the pinhole gives
    ``du = fx (dc_x - u' dc_z) / c_z``, ``dv = fy (dc_y - v' dc_z) / c_z`` with ``u' = c_x / c_z``, ``v' = c_y / c_z``
    (``tests/test_eskf.py`` checks this against ``jax.jacfwd`` of the projection of the injected state).

    Args:
        gate_corners: (4, 3) world points.

    Returns:
        uv_px: (4, 2) predicted pixels (u right, v down; ``camera.project``'s ``uv * (W, H)``).
        jacobian: (4, 2, 15) ``d uv_px / d dx`` at ``dx = 0`` (only ``dp`` and ``dtheta`` act).
        in_front: (4,) bool, the corner lies in front of the camera (the Jacobian of one behind is finite, unused).
    """
    dtype = x.dtype
    uv, depth, in_front = camera_lib.project(gate_corners, x, camera)
    uv_px = uv * jnp.asarray([camera.width, camera.height], dtype)
    R = quadrotor.rotation_matrix(quadrotor.normalize_quat(x[QUAT]))
    C = camera_lib.body_to_camera(camera).astype(dtype)
    body = (gate_corners - x[POS]) @ R  # (4, 3) rows R^T (P - p)
    cam = body @ C.T  # (4, 3)
    d_position = jnp.broadcast_to(-C @ R.T, (NUM_CORNERS, 3, 3))
    d_attitude = C @ jax.vmap(skew)(body)  # (4, 3, 3)
    z = jnp.where(in_front, depth, 1.0)[:, None]  # (4, 1)
    f = jnp.asarray([camera.fx, camera.fy], dtype)
    ratio = cam[:, :2] / z  # (4, 2)
    d_camera = jnp.concatenate([d_position, d_attitude], axis=-1)  # (4, 3, 6)
    d_pixels = f[None, :, None] * (d_camera[:, :2, :] - ratio[:, :, None] * d_camera[:, 2:3, :]) / z[:, :, None]
    jacobian = jnp.zeros((NUM_CORNERS, 2, ERROR_DIM), dtype)
    jacobian = jacobian.at[:, :, 0:3].set(d_pixels[..., :3]).at[:, :, 6:9].set(d_pixels[..., 3:])
    return uv_px, jacobian, in_front


def robust_weight(mahalanobis2: jax.Array, config: ESKFConfig) -> jax.Array:
    """Weights in (0, 1] of corners (...,) at squared Mahalanobis distances ``d^2``: Huber ``min(1, c / d)``,
    Cauchy ``1 / (1 + d^2 / c^2)``, or 1 (``config.robust_loss``, ``c = config.robust_threshold``)."""
    c = config.robust_threshold
    if config.robust_loss == "huber":
        d = jnp.sqrt(jnp.maximum(mahalanobis2, c * c))  # d >= c > 0: the untaken branch has no 0 / 0
        return jnp.where(mahalanobis2 <= c * c, 1.0, c / d)
    if config.robust_loss == "cauchy":
        return 1.0 / (1.0 + mahalanobis2 / (c * c))
    return jnp.ones_like(mahalanobis2)


def _solve_spd(S: jax.Array, B: jax.Array) -> jax.Array:
    """``S^-1 B`` for a symmetric positive definite ``S`` (Cholesky)."""
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(S), True), B)


class _CornerReport(NamedTuple):
    innovation: jax.Array
    innovation_cov: jax.Array
    corner_mahalanobis2: jax.Array
    accepted: jax.Array
    weight: jax.Array
    nis: jax.Array
    nis_dof: jax.Array


def gate_jacobian(H: jax.Array, corners: jax.Array, centre: jax.Array) -> jax.Array:
    """(4, 2, 4) the corners' pixels' Jacobian with respect to their gate's offset ``[dx, dy, dz, dyaw]``
    (``track.offset_gates``), from their Jacobian ``H`` (4, 2, 15) with respect to the error state: a corner moved by
    ``d`` shows as the vehicle moved by ``-d``, and a turn ``dyaw`` about z through the gate's ``centre`` (3,) moves
    the corner (4, 3) by ``e_z x (corner - centre) dyaw``."""
    d_world = -H[..., 0:3]  # (4, 2, 3)
    arm = corners - centre
    turn = jnp.stack([-arm[:, 1], arm[:, 0], jnp.zeros_like(arm[:, 0])], axis=-1)  # (4, 3) e_z x arm
    return jnp.concatenate([d_world, jnp.einsum("kij,kj->ki", d_world, turn)[..., None]], axis=-1)


def estimated_gates(gates, belief: ESKFBelief):
    """The map's ``gates`` (G-batch) where the belief places them: moved by its ``gate_offset``; as given without."""
    return gates if belief.gate_offset is None else track_lib.offset_gates(gates, belief.gate_offset)


def seen_gate_std(belief: ESKFBelief, gates) -> jax.Array:
    """(G,) m, how far each gate's centre, seen from the estimate, may stand off where the belief places it (1 sigma):
    its own position's larger horizontal std (with gate states), the vehicle's larger position std, and its largest
    attitude std turning the line of sight over the gate's distance, together."""
    diagonal = jnp.diagonal(belief.cov)
    position_var, attitude_var = jnp.max(diagonal[0:3]), jnp.max(diagonal[6:9])
    depth = jnp.linalg.norm(gates.centre - belief.x[POS], axis=-1)
    variance = position_var + attitude_var * depth**2
    if belief.gate_offset is not None:
        own = diagonal[ERROR_DIM:].reshape(-1, 4)
        variance = variance + jnp.maximum(own[:, 0], own[:, 1])
    return jnp.sqrt(variance)


def _update(belief: ESKFBelief, detection: CornerInput, gates, camera: camera_lib.Camera, config: ESKFConfig):
    """The gated, robustly weighted corner update of one tick (module docstring). -> (belief, _CornerReport)."""
    dtype = belief.x.dtype
    num_gates = gates.centre.shape[0]
    gate_id = jnp.asarray(detection.gate_id, jnp.int32)
    index = jnp.clip(gate_id, 0, num_gates - 1)
    gate = jax.tree_util.tree_map(lambda leaf: leaf[index], estimated_gates(gates, belief))
    P = belief.cov
    n = P.shape[0]
    corners = gate.corners().astype(dtype)
    predicted, H, in_front = reproject_corners(belief.x, corners, camera)  # (4, 2), (4, 2, 15)
    if belief.gate_offset is not None:  # the detected gate's offset enters too; the other gates' columns are 0
        one_hot = (jnp.arange(num_gates) == index).astype(dtype)
        gate_columns = one_hot[None, None, :, None] * gate_jacobian(H, corners, gate.centre.astype(dtype))[:, :, None]
        H = jnp.concatenate([H, gate_columns.reshape(NUM_CORNERS, 2, n - ERROR_DIM)], axis=-1)
    scale = jnp.asarray([camera.width, camera.height], dtype)
    observed = jnp.asarray(detection.corners, dtype) * scale
    residual = observed - predicted  # (4, 2) px
    margin = config.border_margin_px
    inside = jnp.all((observed >= margin) & (observed <= scale - margin), axis=-1)
    usable = (jnp.asarray(detection.detected, bool) & (gate_id >= 0) & in_front & inside
              & jnp.all(jnp.isfinite(residual), axis=-1))
    residual = jnp.where(usable[:, None], residual, 0.0)

    r_var = jnp.asarray(config.measurement_sigma_px**2, dtype)
    if config.noise_adapt_rate > 0:  # static: without adapting the noise is the configured one, bit for bit
        r_var = r_var * belief.noise_scale
    S_corner = H @ P @ jnp.swapaxes(H, -1, -2) + r_var * jnp.eye(2, dtype=dtype)  # (4, 2, 2), >= R: invertible
    map_var = config.map_sigma_m**2 if belief.gate_offset is None else 0.0  # with gate states the offset is a state
    if map_var > 0:  # the gate's offset from the map, shared by its corners (static: an exact map adds nothing)
        H_pos = H[..., 0:3]
        S_corner = S_corner + map_var * H_pos @ jnp.swapaxes(H_pos, -1, -2)
    a, b, c, d = S_corner[:, 0, 0], S_corner[:, 0, 1], S_corner[:, 1, 0], S_corner[:, 1, 1]
    ru, rv = residual[:, 0], residual[:, 1]
    mahalanobis2 = (d * ru * ru - (b + c) * ru * rv + a * rv * rv) / (a * d - b * c)  # (4,)
    accepted = usable & (mahalanobis2 <= config.gate_chi2)

    rows = jnp.repeat(accepted, 2)  # (8,)
    H_used = jnp.where(rows[:, None], H.reshape(2 * NUM_CORNERS, n), 0.0)  # (8, n)
    r_used = jnp.where(rows, residual.reshape(2 * NUM_CORNERS), 0.0)  # (8,)
    HPHt = H_used @ P @ H_used.T
    if map_var > 0:  # the map's share of the corners' noise, on the used rows (the others have H = 0)
        HPHt = HPHt + map_var * H_used[:, 0:3] @ H_used[:, 0:3].T
    # rows not used have H = 0 and r = 0: R on their diagonal, nothing in the sum
    nis = r_used @ _solve_spd(HPHt + r_var * jnp.eye(2 * NUM_CORNERS, dtype=dtype), r_used)
    if config.joint_gate:  # all or nothing: a rejected detection uses no row
        count = jnp.sum(accepted.astype(jnp.int32))
        kept = nis <= jnp.asarray(CHI2_JOINT_999, dtype)[jnp.clip(count - 1, 0, NUM_CORNERS - 1)]
        accepted, H_used, r_used, HPHt, nis = (accepted & kept, jnp.where(kept, H_used, 0.0),
                                               jnp.where(kept, r_used, 0.0), jnp.where(kept, HPHt, 0.0),
                                               jnp.where(kept, nis, 0.0))
    weight = jnp.where(accepted, robust_weight(mahalanobis2, config), 1.0)

    noise = jnp.repeat(r_var / weight, 2)  # (8,) R / w per row
    gain = _solve_spd(HPHt + jnp.diag(noise), H_used @ P).T  # (n, 8), K = P H^T S^-1
    dx = gain @ r_used
    I_KH = jnp.eye(n, dtype=dtype) - gain @ H_used
    if map_var > 0:  # Joseph form with the whole measurement noise, the corners' own and the map's
        map_noise = map_var * H_used[:, 0:3] @ H_used[:, 0:3].T
        cov = I_KH @ P @ I_KH.T + gain @ (jnp.diag(noise) + map_noise) @ gain.T
    else:
        cov = I_KH @ P @ I_KH.T + (gain * noise) @ gain.T  # Joseph form
    updated = _corrected(belief, dx, cov)
    belief = _tree_where(jnp.any(accepted), updated, belief)  # nothing accepted: the belief untouched, bit for bit
    if config.noise_adapt_rate > 0:
        belief = belief.replace(noise_scale=_adapted_noise_scale(belief.noise_scale, mahalanobis2, usable, config))

    report = _CornerReport(innovation=residual, innovation_cov=S_corner,
                           corner_mahalanobis2=jnp.where(usable, mahalanobis2, 0.0), accepted=accepted,
                           weight=weight, nis=nis, nis_dof=2 * jnp.sum(accepted.astype(jnp.int32)))
    return belief, report


def _adapted_noise_scale(scale: jax.Array, mahalanobis2: jax.Array, usable: jax.Array, config: ESKFConfig):
    """The corners' noise scale after a tick (``ESKFConfig.noise_adapt_rate``): moved towards what the usable
    corners' prior Mahalanobis distances (4,), each clipped at the gate, say of it. No usable corner: unchanged."""
    count = jnp.sum(usable.astype(scale.dtype))
    clipped = jnp.where(usable, jnp.minimum(mahalanobis2, config.gate_chi2), 0.0)
    per_dof = jnp.sum(clipped) / (2.0 * jnp.maximum(count, 1.0))
    rate = config.noise_adapt_rate
    adapted = jnp.clip(scale * (1.0 - rate + rate * per_dof), 1.0, config.noise_scale_max)
    return jnp.where(count > 0, adapted, scale)


# --------------------------------------------------------------------------------------------------
# One tick: file the inputs in the window and replay it.
# --------------------------------------------------------------------------------------------------


def _no_corners(dtype, leading: tuple = ()) -> CornerInput:
    return CornerInput(corners=jnp.zeros((*leading, NUM_CORNERS, 2), dtype),
                       detected=jnp.zeros((*leading, NUM_CORNERS), bool),
                       gate_id=jnp.full(leading, -1, jnp.int32))


def _no_imu(dtype, leading: tuple = ()) -> ImuInput:
    identity = jnp.zeros((*leading, 4), dtype).at[..., 0].set(1.0)
    return ImuInput(delta_q=identity, delta_v=jnp.zeros((*leading, 3), dtype), delta_p=jnp.zeros((*leading, 3), dtype),
                    dt=jnp.zeros(leading, dtype))


def _replay(anchor: ESKFBelief, imus: ImuInput, imu_valid: jax.Array, detections: CornerInput, gates, camera,
            config: ESKFConfig):
    """Predict and update tick by tick from ``anchor`` over a window (leading axis L). -> beliefs and reports,
    each with leading axis L."""

    def tick(belief, inputs):
        imu, valid, detection = inputs
        belief = _tree_where(valid, _predict(belief, imu, config), belief)
        if detection.gate_id.ndim == 0:
            belief, report = _update(belief, detection, gates, camera, config)
        else:  # several gates' detections, one after the other; the report is the first's (the target gate's)
            reports = []
            for k in range(detection.gate_id.shape[0]):
                belief, seen = _update(belief, jax.tree_util.tree_map(lambda a, k=k: a[k], detection), gates, camera,
                                       config)
                reports.append(seen)
            report = reports[0]
        return belief, (belief, report)

    _, (beliefs, reports) = jax.lax.scan(tick, anchor, (imus, imu_valid, detections))
    return beliefs, reports


def _estimate(belief: ESKFBelief) -> ESKFEstimate:
    q = belief.x[QUAT]
    mean = belief.x.at[QUAT].set(jnp.where(q[0] < 0, -q, q))
    return ESKFEstimate(mean=mean, position_cov=belief.cov[0:3, 0:3], bias=belief.bias, covariance=belief.cov,
                        gate_offset=belief.gate_offset)


def _step(state: ESKFState, imu: ImuInput, imu_valid, detection: CornerInput, delay_ticks, gates, camera,
          config: ESKFConfig):
    D = config.max_delay_ticks
    dtype = state.latest.x.dtype
    append = functools.partial(jax.tree_util.tree_map, lambda window, new: jnp.concatenate([window, new[None]]))
    imus = append(state.imu, imu)  # (D + 1, ...): ticks k-D..k
    valid = jnp.concatenate([state.imu_valid, jnp.asarray(imu_valid, bool)[None]])
    detections = append(state.detections, _no_corners(dtype, state.detections.gate_id.shape[1:]))
    delay = jnp.asarray(delay_ticks, jnp.int32)
    in_window = (delay >= 0) & (delay <= D)
    slot = D - jnp.clip(delay, 0, D)  # the capture tick's place in the window
    detections = jax.tree_util.tree_map(
        lambda window, new: window.at[slot].set(jnp.where(in_window, new, window[slot])), detections, detection)
    beliefs, reports = _replay(state.anchor, imus, valid, detections, gates, camera, config)
    anchor = jax.tree_util.tree_map(lambda a: a[0], beliefs)
    latest = jax.tree_util.tree_map(lambda a: a[-1], beliefs)
    report = jax.tree_util.tree_map(lambda a: jnp.where(in_window, a[slot], jnp.zeros_like(a[slot])), reports)
    drop_first = functools.partial(jax.tree_util.tree_map, lambda a: a[1:])
    state = ESKFState(anchor=anchor, imu=drop_first(imus), imu_valid=valid[1:], detections=drop_first(detections),
                      latest=latest)
    estimate = _estimate(latest)
    info = ESKFInfo(position_cov_trace=jnp.trace(latest.cov[0:3, 0:3]), **report._asdict(), delay_ticks=delay,
                    dropped=~in_window, noise_scale=latest.noise_scale, estimate=estimate)
    return state, estimate, info


def tick(state: ESKFState, imu, detection, delay_ticks, gates, camera: camera_lib.Camera, config: ESKFConfig):
    """One control tick: append the tick's IMU, file the detection at the tick it was captured, replay the window.

    Args:
        state: the filter.
        imu: the IMU over the tick that led to now (``sim.plant.TickIMU``: ``delta_q``, ``delta_v``, ``delta_p``,
            ``dt``), or None: no motion update this tick.
        detection: the target gate's ``Detection`` delivered now (``found=False`` or a negative ``gate_id``: nothing
            detected), or None; where the state was made for K > 1 detections a tick (:func:`init_belief`), K
            gates' detections stacked on a leading axis, the target's first.
        delay_ticks: () int, how many ticks before now the detection's image was taken (0: on time); at most
            ``config.max_delay_ticks`` (a traced later one is dropped and reported in ``info.dropped``).
        gates: the map's ``Gate`` batch (G leading axis): the known corners.
        camera: the onboard camera.

    Returns:
        state: the filter after the tick.
        estimate: ``ESKFEstimate`` at now.
        info: ``ESKFInfo``.

    The inputs' conversions run here, in the caller's compiled call: done eagerly on the host they cost about as
    much as the filter itself.
    """
    dtype = state.latest.x.dtype
    if imu is None:
        imu_input, imu_valid = _no_imu(dtype), jnp.asarray(False)
    else:
        imu_input = ImuInput(*(jnp.asarray(getattr(imu, name), dtype) for name in IMU_FIELDS))
        imu_valid = jnp.asarray(True)
    if detection is None:
        corners = _no_corners(dtype, state.detections.gate_id.shape[1:])
    else:
        corners_xy, corners_visible, found, gate_id = (getattr(detection, name) for name in DETECTION_FIELDS)
        gate_id = jnp.asarray(gate_id, jnp.int32)
        detected = jnp.asarray(corners_visible, bool) & (jnp.asarray(found, bool) & (gate_id >= 0))[..., None]
        corners = CornerInput(corners=jnp.asarray(corners_xy, dtype), detected=detected, gate_id=gate_id)
    return _step(state, imu_input, imu_valid, corners, jnp.asarray(delay_ticks, jnp.int32), gates, camera, config)


# --------------------------------------------------------------------------------------------------
# Input checks (shapes are static: these also run under jit and vmap tracing).
# --------------------------------------------------------------------------------------------------


def _check_state(state: ESKFState, config: ESKFConfig) -> None:
    D = config.max_delay_ticks
    offset = state.latest.gate_offset
    n = ERROR_DIM if offset is None else ERROR_DIM + 4 * jnp.shape(offset)[0]
    shapes = (jnp.shape(state.latest.x), jnp.shape(state.latest.cov), jnp.shape(state.imu_valid))
    if shapes != ((STATE_DIM,), (n, n), (D,)):
        raise ValueError(f"ESKFState for one filter (vmap batches) with max_delay_ticks={D} needs x ({STATE_DIM},), "
                         f"cov ({ERROR_DIM}, {ERROR_DIM}) and a window of {D} ticks; got {shapes} (from the init of "
                         f"another config?)")


IMU_FIELDS = {"delta_q": (4,), "delta_v": (3,), "delta_p": (3,), "dt": ()}
DETECTION_FIELDS = {"corners": (NUM_CORNERS, 2), "corners_visible": (NUM_CORNERS,), "found": (), "gate_id": ()}


def _check_imu(imu) -> None:
    """The tick's IMU's fields and shapes (None: no IMU)."""
    if imu is None:
        return
    for name, shape in IMU_FIELDS.items():
        if not hasattr(imu, name) or jnp.shape(getattr(imu, name)) != shape:
            raise ValueError(f"imu must be one tick's preintegrated IMU (sim.plant.TickIMU) with delta_q (4,), "
                             f"delta_v (3,), delta_p (3,), dt (); {name} is "
                             f"{jnp.shape(getattr(imu, name)) if hasattr(imu, name) else 'missing'}")


def _check_detection(detection, per_tick: int = 1) -> None:
    """The detection's fields and shapes (None: nothing delivered): one gate's, or ``per_tick`` > 1 gates' stacked."""
    if detection is None:
        return
    leading = () if per_tick == 1 else (per_tick,)
    shapes = tuple(jnp.shape(getattr(detection, name, None)) for name in DETECTION_FIELDS)
    if shapes != tuple((*leading, *shape) for shape in DETECTION_FIELDS.values()):
        what = "one detector.Detection" if per_tick == 1 else f"{per_tick} detector.Detections stacked"
        raise ValueError(f"detection must be {what} with corners {(*leading, 4, 2)}, corners_visible {(*leading, 4)}, "
                         f"found {leading} and gate_id {leading}; got shapes {shapes}")


def _check_delay(delay_ticks, config: ESKFConfig) -> None:
    integer = jnp.issubdtype(jnp.result_type(delay_ticks), jnp.integer)
    if isinstance(delay_ticks, bool) or jnp.ndim(delay_ticks) != 0 or not integer:
        raise ValueError(f"delay_ticks must be one integer number of ticks, got {delay_ticks!r}")
    if not isinstance(delay_ticks, jax.core.Tracer) and not 0 <= int(delay_ticks) <= config.max_delay_ticks:
        raise ValueError(f"delay_ticks must lie in [0, max_delay_ticks={config.max_delay_ticks}], got {delay_ticks}")


# --------------------------------------------------------------------------------------------------
# The first state, the alignment on the pad, the estimator.
# --------------------------------------------------------------------------------------------------


def init_belief(x0: jax.Array, bias0: jax.Array, config: ESKFConfig, spread: tuple, gate_std=None,
                detections_per_tick: int = 1) -> ESKFState:
    """The filter at ``x0`` (10,) ``[p, q, v]`` and IMU biases ``bias0`` (6,) ``[b_a, b_g]``, with an empty window.

    ``spread``: prior std of ``(position m, attitude rad (body-frame rotation vector), velocity m/s)``, per axis, in
    the order of the particle filter's; the biases' prior stds are the config's. ``gate_std``: (G, 4), the gates as
    states: each gate's offset from the map ``[dx, dy, dz (m), dyaw (rad)]`` starts at 0 with these prior stds (what
    the drone was told of its map: ``course.gate_prior_std``); None: the map's gates as they are.
    ``detections_per_tick``: K, the gates' detections each tick brings (1: the target's; 2: the next gate's too).
    """
    dtype = x0.dtype
    x0 = x0.at[QUAT].set(quadrotor.normalize_quat(x0[QUAT]))
    position_std, attitude_std, velocity_std = spread
    stds = jnp.asarray([position_std] * 3 + [velocity_std] * 3 + [attitude_std] * 3 + [config.accel_bias_std] * 3
                       + [config.gyro_bias_std] * 3, dtype)
    gate_offset = None
    if gate_std is not None:
        gate_std = jnp.asarray(gate_std, dtype)
        if gate_std.ndim != 2 or gate_std.shape[-1] != 4:
            raise ValueError(f"gate_std must have shape (G, 4) = [dx, dy, dz, dyaw] per gate, got {gate_std.shape}")
        stds, gate_offset = jnp.concatenate([stds, gate_std.reshape(-1)]), jnp.zeros_like(gate_std)
    belief = ESKFBelief(x=x0, bias=bias0, cov=jnp.diag(stds**2), noise_scale=jnp.ones((), dtype),
                        gate_offset=gate_offset)
    D = config.max_delay_ticks
    per_tick = () if detections_per_tick == 1 else (detections_per_tick,)
    return ESKFState(anchor=belief, imu=_no_imu(dtype, (D,)), imu_valid=jnp.zeros((D,), bool),
                     detections=_no_corners(dtype, (D, *per_tick)), latest=belief)


def align(state: ESKFState, accel_mean, gyro_mean, config: ESKFConfig) -> ESKFState:
    """The filter before its first step, after ``config.align_s`` seconds at rest (``ESKFConfig.align_s``).

    Args:
        state: the filter from its ``init`` (no step taken yet).
        accel_mean: (3,) m/s^2, the accelerometer's mean reading at rest (body frame, its bias included).
        gyro_mean: (3,) rad/s, the gyro's mean reading at rest.
        config: the filter's configuration; its ``align_s`` > 0 is the readings' time.

    Returns:
        the filter with one Kalman update of its attitude and biases by those readings.
    """
    for name, value in (("accel_mean", accel_mean), ("gyro_mean", gyro_mean)):
        if jnp.shape(value) != (3,):
            raise ValueError(f"{name} must have shape (3,), got {jnp.shape(value)}")
    belief = state.latest
    dtype = belief.x.dtype
    P = belief.cov
    rotation = quadrotor.rotation_matrix(quadrotor.normalize_quat(belief.x[QUAT]))
    rest_force = rotation.T @ jnp.asarray([0.0, 0.0, config.gravity], dtype)  # the specific force at rest, body frame
    # readings = [R^T (0, 0, g) + b_a, b_g] + noise; with q_true = q exp(dtheta), R_true^T g = f + f x dtheta
    n = P.shape[0]
    H = jnp.zeros((6, n), dtype).at[0:3, 6:9].set(skew(rest_force)).at[0:3, 9:12].set(jnp.eye(3, dtype=dtype))
    H = H.at[3:6, 12:15].set(jnp.eye(3, dtype=dtype))
    residual = jnp.concatenate([jnp.asarray(accel_mean, dtype) - rest_force - belief.bias[:3],
                                jnp.asarray(gyro_mean, dtype) - belief.bias[3:]])
    densities = jnp.asarray([config.accel_noise_density] * 3 + [config.gyro_noise_density] * 3, dtype)
    noise = densities**2 / config.align_s  # the variance of the readings' mean over align_s
    gain = _solve_spd(H @ P @ H.T + jnp.diag(noise), H @ P).T  # (n, 6)
    dx = gain @ residual
    I_KH = jnp.eye(n, dtype=dtype) - gain @ H
    cov = I_KH @ P @ I_KH.T + (gain * noise) @ gain.T  # Joseph form
    aligned = _corrected(belief, dx, cov)
    return state.replace(anchor=aligned, latest=aligned)


def eskf_estimate(state: ESKFState) -> ESKFEstimate:
    """The estimate (:class:`ESKFEstimate`) at the newest tick."""
    return _estimate(state.latest)


def _as_gated(detection, info: ESKFInfo):
    """``detection`` as the loop should use it: none (``found`` and ``corners_visible`` cleared) when the filter's
    gate rejected every corner it could use."""
    if detection is None:
        return None
    usable = info.corner_mahalanobis2 > 0
    rejected = jnp.any(usable) & ~jnp.any(info.accepted)
    return detection.replace(found=detection.found & ~rejected, corners_visible=detection.corners_visible & ~rejected)


def make_eskf(config: ESKFConfig = ESKFConfig(), spread=(0.3, 0.03, 0.2), bias0=None,
              detections_per_tick: int = 1) -> Estimator:
    """The error-state Kalman filter as an :class:`~pixelmpc_jax.perception.estimator.Estimator`.

    Args:
        config: the filter's configuration (noises, gates, window length, ``align_s``).
        spread: prior std of ``(position m, attitude rad (body-frame rotation vector), velocity m/s)``, per axis.
        bias0: (6,) initial bias estimate ``[b_a, b_g]`` (None: zeros); its prior std is the config's.
        detections_per_tick: K, the gates' detections each step takes: 1, the target gate's; 2, the next gate's too
            (stacked, the target's first: the gates estimated as states are seen before they become the target).

    ``init(key, x0)``: :func:`init_belief` (``key`` unused: the filter draws nothing). ``step(state, imu, detection,
    params)``: :func:`tick` with ``params.delay_ticks``, ``params.gates``, ``params.camera``; its ``info`` is
    :class:`ESKFInfo` (``info.estimate`` the whole :class:`ESKFEstimate`), its estimate's detection none when the
    gate rejected every usable corner. ``align``: :func:`align` when ``config.align_s`` > 0, else None.
    """
    spread = checked_spread(spread)
    if detections_per_tick not in (1, 2):
        raise ValueError(f"detections_per_tick must be 1 or 2, got {detections_per_tick!r}")
    bias0 = jnp.zeros(6, jnp.float32) if bias0 is None else jnp.asarray(bias0, jnp.float32)
    if bias0.shape != (6,):
        raise ValueError(f"bias0 must have shape (6,) = [b_a, b_g], got {bias0.shape}")

    def init(key: jax.Array, x0: jax.Array, gate_std=None) -> ESKFState:
        del key
        return init_belief(checked_x0(x0), bias0, config, spread, gate_std, detections_per_tick)

    def step(state: ESKFState, imu, detection, params: EstimatorParams):
        state, estimate, info = tick(state, imu, detection, params.delay_ticks, params.gates, params.camera, config)
        gates = None if state.latest.gate_offset is None else estimated_gates(params.gates, state.latest)
        if detection is not None and detections_per_tick > 1:  # the target's, first of the tick's detections
            detection = jax.tree_util.tree_map(lambda a: a[0], detection)
        return (Estimate(mean=estimate.mean, position_cov_trace=info.position_cov_trace,
                         detection=_as_gated(detection, info), gates=gates), state, info)

    def check(state: ESKFState, imu, detection, params: EstimatorParams):
        _check_state(state, config)
        _check_delay(params.delay_ticks, config)
        _check_imu(imu)
        _check_detection(detection, detections_per_tick)
        return state, imu, detection, params

    def align_on_pad(state: ESKFState, accel_mean, gyro_mean) -> ESKFState:
        return align(state, accel_mean, gyro_mean, config)

    def place_gates(state: ESKFState, gates):
        belief = state.latest
        placed = estimated_gates(gates, belief)
        return placed, seen_gate_std(belief, placed)

    return Estimator(init=init, step=step, check=check, config=config,
                     align=align_on_pad if config.align_s > 0 else None, place_gates=place_gates,
                     detections_per_tick=detections_per_tick)


def nees(estimate: ESKFEstimate, x_true: jax.Array) -> jax.Array:
    """() normalised estimation error squared over position, velocity and attitude (9 dof):
    ``e^T P_9^-1 e`` with ``e = state_error(estimate.mean, x_true)`` and ``P_9`` the covariance's first 9 rows and
    columns. Batch with ``jax.vmap``."""
    error = state_error(estimate.mean, jnp.asarray(x_true, estimate.mean.dtype))
    return error @ _solve_spd(estimate.covariance[:NAV_DIM, :NAV_DIM], error)
