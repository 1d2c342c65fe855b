"""The simulated vehicle: a FlightGoggles-like quadrotor at 960 Hz that the controller does not see exactly.

The controller's model (``dynamics/quadrotor.py``) follows commanded body rates at once. The plant puts the
low-level loop of the AlphaPilot FlightGoggles drone between the command and the rigid body
(``pixelmpc_jax/data/alphapilot_course.json``, block ``vehicle``):

    gyro -> 2nd-order low-pass (30 Hz, damping 0.707) -> rate PID (P 9, I 3, D 0.3 on the filtered rate
    derivative) -> angular acceleration * inertia = torque -> mixer (+ collective thrust) -> motor speed
    commands clipped to [0, 2200] rad/s -> first-order motor lag (0.02 s) -> rigid body with drag and
    process noise, explicit Euler -> true state and IMU readings.

Modelling choices (where the reference leaves a choice open):

- Mixer layout: quad-X as in FlightGoggles. Body x forward, y left, z up; motor ``i`` sits at
  ``moment_arm * (sx_i, sy_i)`` with lever ``moment_arm`` about both body x and y (the FlightGoggles
  convention: roll/pitch torque per motor is ``moment_arm * k_f * w^2``). Motors, in order, are front-left,
  rear-left, rear-right, front-right, with yaw reaction signs ``(-1, +1, -1, +1)``:

      tau_x = l k_f (w1^2 + w2^2 - w3^2 - w4^2)
      tau_y = l k_f (-w1^2 + w2^2 + w3^2 - w4^2)
      tau_z = k_t (-w1^2 + w2^2 - w3^2 + w4^2)
      T     = k_f (w1^2 + w2^2 + w3^2 + w4^2)

  The sign columns are orthogonal, so the mixer is the exact inverse: ``w_i^2 = s_i . (tau / (4 l k_f),
  tau_z / (4 k_t)) + T / (4 k_f)``; collective thrust gives ``T / 4`` per motor before torque allocation.
- Process noise: the reference values are the auto-correlations (power spectral densities) of continuous
  white noise on the *accelerations*, as in the FlightGoggles dynamics node: angular ``0.00025 rad^2/s^3``,
  linear ``0.0005 m^2/s^3``. One Euler step of length ``dt`` draws ``N(0, psd / dt)`` per axis, so the
  velocity random walk is ``sqrt(psd * t)`` whatever the step. The linear noise is a world-frame force, so
  the accelerometer feels it (as in FlightGoggles).
- IMU noise: the reference values are variances of white noise added per sample (per substep): accelerometer
  std ``sqrt(0.005) = 0.071 m/s^2``, gyro std ``sqrt(0.003) = 0.055 rad/s``.
- The rate loop runs on the noisy gyro, as in FlightGoggles: gyro -> low-pass -> PID.
- The low-pass is discretised implicitly (backward Euler on its two states, as FlightGoggles does), which is
  stable for any step; the rigid body and the motors use explicit Euler (the motor step is capped at one time
  constant so a coarse ``dt`` cannot overshoot).
- Order inside a substep: PID on the filter state (which holds the previous gyro sample), Euler step of the
  body and motors, IMU sample at the new state, low-pass update with that gyro sample.

Everything is written for one vehicle and is pure; batch with ``jax.vmap``. ``plant_tick`` runs one control
period (24 substeps = 1/40 s) with ``lax.scan``; jit it with ``static_argnames=("substeps",)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics.quadrotor import (
    CONTROL_DIM,
    QUAT,
    STATE_DIM,
    QuadParams,
    dynamics,
    normalize_quat,
    quat_exp,
    quat_multiply,
    quat_rotate,
    rotation_matrix,
)

PLANT_DT = timing.PLANT_DT  # 960 Hz (pixelmpc_jax.timing)
SUBSTEPS_PER_TICK = timing.SUBSTEPS_PER_TICK  # 960 Hz / 40 Hz = 24

# Quad-X sign pattern, motors (front-left, rear-left, rear-right, front-right): rows are roll, pitch, yaw.
_MIX_SIGNS = ((1.0, 1.0, -1.0, -1.0), (-1.0, 1.0, 1.0, -1.0), (-1.0, 1.0, -1.0, 1.0))


@struct.dataclass
class PlantParams:
    """Facts of the simulated vehicle; defaults equal the reference file. A pytree (no recompilation).

    Attributes:
        mass: kg.
        inertia: (3,) diagonal of the inertia matrix, kg m^2.
        gravity: m/s^2 along world -z.
        moment_arm: m, lever of each motor about body x and y.
        thrust_coefficient: ``k_f``, motor thrust ``k_f w^2`` (N per (rad/s)^2).
        torque_coefficient: ``k_t``, motor yaw reaction ``k_t w^2`` (N m per (rad/s)^2).
        motor_time_constant: s, first-order lag of the motor speed.
        motor_speed_max: rad/s; motor speeds lie in ``[0, motor_speed_max]``.
        drag_coefficient: ``c_d`` of the world-frame drag ``-c_d |v| v`` (N per (m/s)^2).
        angular_noise_psd: rad^2/s^3, PSD of the white angular-acceleration process noise.
        linear_noise_psd: m^2/s^3, PSD of the white linear-acceleration process noise (world frame).
        accel_noise_variance: (m/s^2)^2 per accelerometer sample.
        gyro_noise_variance: (rad/s)^2 per gyro sample.
        lowpass_cutoff_hz, lowpass_damping: the gyro filter ``f'' = w_c^2 (gyro - f) - 2 zeta w_c f'``.
        rate_gain_p, rate_gain_i, rate_gain_d: rate PID gains (1/s, 1/s^2, 1), same on all axes.
        integrator_bound: bound on each PID integrator state (rad).
        mixer_thrust_coefficient: the ``k_f`` the rate loop's mixer assumes when it turns torque and thrust
            into motor speeds; None: the motors' own ``thrust_coefficient`` (a mixer that knows its motors). Set
            apart from it, the motors make ``thrust_coefficient / mixer_thrust_coefficient`` times the commanded
            thrust (a thrust-constant model error, :mod:`pixelmpc_jax.sim.faults`).
    """

    mass: float | jax.Array = 1.0
    inertia: tuple | jax.Array = (0.0049, 0.0049, 0.0049)
    gravity: float | jax.Array = 9.81
    moment_arm: float | jax.Array = 0.08
    thrust_coefficient: float | jax.Array = 1.91e-6
    torque_coefficient: float | jax.Array = 2.6e-7
    motor_time_constant: float | jax.Array = 0.02
    motor_speed_max: float | jax.Array = 2200.0
    drag_coefficient: float | jax.Array = 0.1
    angular_noise_psd: float | jax.Array = 0.00025
    linear_noise_psd: float | jax.Array = 0.0005
    accel_noise_variance: float | jax.Array = 0.005
    gyro_noise_variance: float | jax.Array = 0.003
    lowpass_cutoff_hz: float | jax.Array = 30.0
    lowpass_damping: float | jax.Array = 0.707
    rate_gain_p: float | jax.Array = 9.0
    rate_gain_i: float | jax.Array = 3.0
    rate_gain_d: float | jax.Array = 0.3
    integrator_bound: float | jax.Array = 1000.0
    mixer_thrust_coefficient: float | jax.Array | None = None

    @classmethod
    def from_reference(cls, vehicle: dict) -> PlantParams:
        """PlantParams from the ``vehicle`` block of ``alphapilot_course.json``; raises KeyError if a fact is
        missing. The filter's cut-off and damping are the defaults (the file states them in prose)."""
        required = (
            "mass_kg", "inertia_kgm2", "moment_arm_m", "motor_time_constant_s", "max_prop_speed_rad_s",
            "thrust_coefficient", "torque_coefficient", "drag_coefficient", "process_noise",
            "imu_noise_variance", "rate_controller",
        )  # fmt: skip
        missing = [k for k in required if k not in vehicle]
        if missing:
            raise KeyError(f"vehicle block lacks {missing}; expected the keys {list(required)}")
        inertia = tuple(float(i) for i in vehicle["inertia_kgm2"])
        if len(inertia) != 3:
            raise ValueError(f"inertia_kgm2 must hold the 3 diagonal entries, got {len(inertia)}")
        pid = vehicle["rate_controller"]["pid"]
        return cls(
            mass=float(vehicle["mass_kg"]),
            inertia=inertia,
            moment_arm=float(vehicle["moment_arm_m"]),
            thrust_coefficient=float(vehicle["thrust_coefficient"]),
            torque_coefficient=float(vehicle["torque_coefficient"]),
            motor_time_constant=float(vehicle["motor_time_constant_s"]),
            motor_speed_max=float(vehicle["max_prop_speed_rad_s"]),
            drag_coefficient=float(vehicle["drag_coefficient"]),
            angular_noise_psd=float(vehicle["process_noise"]["angular"]),
            linear_noise_psd=float(vehicle["process_noise"]["linear"]),
            accel_noise_variance=float(vehicle["imu_noise_variance"]["accelerometer"]),
            gyro_noise_variance=float(vehicle["imu_noise_variance"]["gyro"]),
            rate_gain_p=float(pid["P"]),
            rate_gain_i=float(pid["I"]),
            rate_gain_d=float(pid["D"]),
            integrator_bound=float(vehicle["rate_controller"]["integrator_bound"]),
        )

    def without_noise(self) -> PlantParams:
        """The same vehicle with process and IMU noise switched off (deterministic, key-independent)."""
        return self.replace(
            angular_noise_psd=0.0, linear_noise_psd=0.0, accel_noise_variance=0.0, gyro_noise_variance=0.0
        )

    @property
    def hover_thrust(self):
        return self.mass * self.gravity

    @property
    def hover_motor_speed(self):
        """rad/s of each motor when the four together carry ``m g``."""
        return (self.hover_thrust / (4.0 * self.thrust_coefficient)) ** 0.5

    @property
    def max_total_thrust(self):
        """N, all four motors at ``motor_speed_max`` (36.98 N for the reference vehicle)."""
        return 4.0 * self.thrust_coefficient * self.motor_speed_max**2

    def quad_params(self, rate_max=(6.0, 6.0, 6.0)) -> QuadParams:
        """The controller's model of this vehicle (mass, drag, gravity, thrust range)."""
        return QuadParams(
            mass=self.mass,
            drag_coefficient=self.drag_coefficient,
            gravity=self.gravity,
            thrust_min=0.0,
            thrust_max=self.max_total_thrust,
            rate_max=rate_max,
        )


@struct.dataclass
class PlantState:
    """The plant's full state. Shapes for one vehicle.

    Attributes:
        x: (10,) rigid-body state ``[p, q (wxyz), v]``, the paper's order.
        rates: (3,) true body rates, rad/s.
        motor_speeds: (4,) rad/s, motors front-left, rear-left, rear-right, front-right.
        filtered_rate: (3,) low-pass output (the PID's measurement), rad/s.
        filtered_rate_dot: (3,) its derivative (the D term's input), rad/s^2.
        integrator: (3,) PID integrator, ``int (w_cmd - filtered_rate) dt``, rad.
    """

    x: jax.Array
    rates: jax.Array
    motor_speeds: jax.Array
    filtered_rate: jax.Array
    filtered_rate_dot: jax.Array
    integrator: jax.Array


class IMU(NamedTuple):
    """One IMU sample. accel: (3,) specific force in the body frame, m/s^2 (+g along body z at rest, level).
    gyro: (3,) body rates, rad/s."""

    accel: jax.Array
    gyro: jax.Array


class TickIMU(NamedTuple):
    """The IMU over one control tick: the mean sample and all samples preintegrated.

    accel, gyro: (3,) the mean of the tick's samples (as :class:`IMU`).
    delta_q: (4,) the rotation from the body frame at the tick's start to the one at its end (wxyz).
    delta_v: (3,) integral of the specific force over the tick, rotated into the start body frame, m/s.
    delta_p: (3,) the double integral, m (the displacement beyond ``v dt`` and gravity's part).
    dt: () s, the tick's length.
    num_samples: () the number of IMU samples integrated (a filter adding noise per reading scales by it).

    With R the start attitude: ``q' = q * delta_q``, ``v' = v + g dt + R delta_v``,
    ``p' = p + v dt + g dt^2 / 2 + R delta_p``. Integrating every sample keeps the rotation exact when the
    rates change within the tick, which the mean gyro alone cannot (the coning error: degrees per second
    at racing rates).
    """

    accel: jax.Array
    gyro: jax.Array
    delta_q: jax.Array
    delta_v: jax.Array
    delta_p: jax.Array
    dt: jax.Array
    num_samples: jax.Array


def preintegrate(imus: IMU, dt: float) -> TickIMU:
    """Preintegrate IMU samples (each field (S, 3), one per ``dt``) into a :class:`TickIMU`."""
    dtype = imus.accel.dtype

    def body(carry, sample):
        q, dv, dp = carry
        accel, gyro = sample
        a = quat_rotate(q, accel)  # into the start body frame
        dp = dp + dv * dt + 0.5 * a * dt * dt
        dv = dv + a * dt
        q = normalize_quat(quat_multiply(q, quat_exp(gyro, dt)))
        return (q, dv, dp), None

    start = (jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype), jnp.zeros(3, dtype), jnp.zeros(3, dtype))
    (q, dv, dp), _ = jax.lax.scan(body, start, (imus.accel, imus.gyro))
    count = imus.accel.shape[0]
    return TickIMU(accel=jnp.mean(imus.accel, axis=0), gyro=jnp.mean(imus.gyro, axis=0), delta_q=q, delta_v=dv,
                   delta_p=dp, dt=jnp.asarray(count * dt, dtype), num_samples=jnp.asarray(count, dtype))


def hover_tick_imu(tick_dt: float, num_samples: int = SUBSTEPS_PER_TICK, gravity: float = 9.81,
                   dtype=jnp.float32) -> TickIMU:
    """The TickIMU of a tick at rest and level (the filter's first input)."""
    up = jnp.asarray([0.0, 0.0, gravity], dtype)
    return TickIMU(accel=up, gyro=jnp.zeros(3, dtype), delta_q=jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype),
                   delta_v=up * tick_dt, delta_p=0.5 * up * tick_dt**2, dt=jnp.asarray(tick_dt, dtype),
                   num_samples=jnp.asarray(num_samples, dtype))


def resting_imu(x: jax.Array, seconds: float, key: jax.Array, params: PlantParams) -> TickIMU:
    """The IMU over ``seconds`` at rest (on the pad before take-off) at the pose of ``x`` (10,): the mean of its
    ``seconds`` x 960 Hz samples, gravity's specific force in the body frame plus each sample's noise, and the
    readings preintegrated (no motion: the rotation the identity)."""
    dtype = x.dtype
    num_samples = max(round(seconds / timing.PLANT_DT), 1)
    up = rotation_matrix(normalize_quat(x[QUAT])).T @ jnp.asarray([0.0, 0.0, params.gravity], dtype)
    key_accel, key_gyro = jax.random.split(key)
    per_sample = 1.0 / math.sqrt(num_samples)
    accel = up + jnp.sqrt(params.accel_noise_variance) * per_sample * jax.random.normal(key_accel, (3,), dtype)
    gyro = jnp.sqrt(params.gyro_noise_variance) * per_sample * jax.random.normal(key_gyro, (3,), dtype)
    duration = num_samples * timing.PLANT_DT
    return TickIMU(accel=accel, gyro=gyro, delta_q=jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype),
                   delta_v=accel * duration, delta_p=0.5 * accel * duration**2, dt=jnp.asarray(duration, dtype),
                   num_samples=jnp.asarray(num_samples, dtype))


# --------------------------------------------------------------------------------------------------
# Pieces of the loop.
# --------------------------------------------------------------------------------------------------


def motor_wrench(motor_speeds: jax.Array, params: PlantParams) -> tuple[jax.Array, jax.Array]:
    """Body torque (3,) in N m and collective thrust (scalar, N along body +z) of the four motors."""
    signs = jnp.asarray(_MIX_SIGNS, dtype=motor_speeds.dtype)  # (3, 4)
    speed_sq = motor_speeds * motor_speeds
    scale = jnp.stack(
        [
            params.moment_arm * params.thrust_coefficient,
            params.moment_arm * params.thrust_coefficient,
            jnp.asarray(params.torque_coefficient, dtype=motor_speeds.dtype),
        ]
    ).astype(motor_speeds.dtype)
    torque = scale * (signs @ speed_sq)
    thrust = params.thrust_coefficient * jnp.sum(speed_sq)
    return torque, thrust


def mix(torque: jax.Array, thrust: jax.Array, params: PlantParams) -> jax.Array:
    """Motor speed commands (4,) for a body torque (3,) and collective thrust: the exact inverse of
    ``motor_wrench``, then clipped so each speed lies in ``[0, motor_speed_max]``."""
    dtype = torque.dtype
    signs = jnp.asarray(_MIX_SIGNS, dtype=dtype)  # (3, 4)
    k_f = params.thrust_coefficient if params.mixer_thrust_coefficient is None else params.mixer_thrust_coefficient
    arm_kf = params.moment_arm * k_f
    scale = jnp.stack([arm_kf, arm_kf, jnp.asarray(params.torque_coefficient, dtype)]).astype(dtype)
    per_axis = torque / scale
    speed_sq = (per_axis @ signs + thrust / k_f) / 4.0  # (4,)
    speed_sq = jnp.clip(speed_sq, 0.0, params.motor_speed_max**2)
    return jnp.sqrt(speed_sq)


def lowpass_update(filtered_rate, filtered_rate_dot, gyro, dt, params: PlantParams):
    """One backward-Euler step of ``f'' = w_c^2 (gyro - f) - 2 zeta w_c f'``. Returns ``(f, f')``."""
    w_c = 2.0 * math.pi * params.lowpass_cutoff_hz
    gain_p = w_c * w_c
    gain_q = 2.0 * params.lowpass_damping * w_c
    det = gain_p * dt * dt + gain_q * dt + 1.0
    rate_dot = (filtered_rate_dot + gain_p * dt * (gyro - filtered_rate)) / det
    return filtered_rate + dt * rate_dot, rate_dot


def rate_pid(state: PlantState, rates_cmd: jax.Array, dt, params: PlantParams):
    """FlightGoggles rate PID on the filtered gyro. Returns ``(angular_acceleration_cmd, integrator)``.

    e = w_cmd - f;  I <- clip(I + dt e, +-bound);  a_cmd = P e + I_gain I - D f'.
    """
    error = rates_cmd - state.filtered_rate
    integrator = jnp.clip(state.integrator + dt * error, -params.integrator_bound, params.integrator_bound)
    ang_acc = (
        params.rate_gain_p * error
        + params.rate_gain_i * integrator
        - params.rate_gain_d * state.filtered_rate_dot
    )
    return ang_acc, integrator


def specific_force_body(
    x: jax.Array, motor_speeds: jax.Array, accel_noise_world: jax.Array, params: PlantParams
):
    """What an ideal accelerometer reads (3,): ``R^T (thrust e3_world + f_drag / m + w_a)``, body frame."""
    rot = rotation_matrix(normalize_quat(x[QUAT]))
    _, thrust = motor_wrench(motor_speeds, params)
    v = x[7:10]
    drag = -params.drag_coefficient * _safe_norm(v) * v
    world = rot[:, 2] * thrust / params.mass + drag / params.mass + accel_noise_world
    return rot.T @ world


def wind_force(v: jax.Array, wind: jax.Array, params: PlantParams) -> jax.Array:
    """(3,) N, what a wind ``wind`` (3,) (the air's world-frame velocity, m/s) adds to the still-air drag of a
    vehicle at velocity ``v`` (3,): ``-c_d |v - w| (v - w) + c_d |v| v``."""
    air = v - wind
    return -params.drag_coefficient * (_safe_norm(air) * air - _safe_norm(v) * v)


def _safe_norm(v: jax.Array) -> jax.Array:
    n2 = jnp.sum(v * v)
    ok = n2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _check_inputs(state: PlantState, u_cmd) -> None:
    if jnp.shape(state.x) != (STATE_DIM,):
        raise ValueError(
            f"state.x must have shape ({STATE_DIM},) for one vehicle (vmap batches), got {jnp.shape(state.x)}"
        )
    if jnp.shape(u_cmd) != (CONTROL_DIM,):
        raise ValueError(
            f"u_cmd must have shape ({CONTROL_DIM},) = [wx, wy, wz, thrust], got {jnp.shape(u_cmd)}"
        )


# --------------------------------------------------------------------------------------------------
# Public API.
# --------------------------------------------------------------------------------------------------


def init_plant(x0: jax.Array, params: PlantParams) -> PlantState:
    """Plant at rigid-body state ``x0`` (10,) with zero body rates and the motors at hover speed, so a hover
    command ``[0, 0, 0, m g]`` holds altitude from t = 0. The quaternion is renormalised."""
    x0 = jnp.asarray(x0)
    if x0.shape != (STATE_DIM,):
        raise ValueError(f"x0 must have shape ({STATE_DIM},) = [p, q(wxyz), v], got {x0.shape}")
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.float32)
    dtype = x0.dtype
    zeros3 = jnp.zeros(3, dtype)
    return PlantState(
        x=x0.at[QUAT].set(normalize_quat(x0[QUAT])),
        rates=zeros3,
        motor_speeds=jnp.full((4,), params.hover_motor_speed, dtype=dtype),
        filtered_rate=zeros3,
        filtered_rate_dot=zeros3,
        integrator=zeros3,
    )


def plant_substep(
    state: PlantState, u_cmd: jax.Array, key: jax.Array, params: PlantParams, dt: float = PLANT_DT,
    wind: jax.Array | None = None,
) -> tuple[PlantState, IMU]:
    """One 960 Hz step of the vehicle under the rate command ``u_cmd = [wx, wy, wz, thrust]`` (4,).

    ``wind``: (3,) the air's world-frame velocity, m/s (None: still air); the drag acts on the air-relative
    velocity (:func:`wind_force`), and the accelerometer feels it. Returns the new state and the IMU sample
    taken at it.
    """
    _check_inputs(state, u_cmd)
    dtype = state.x.dtype
    u_cmd = jnp.asarray(u_cmd, dtype)
    key_linear, key_angular, key_accel, key_gyro = jax.random.split(key, 4)
    inertia = jnp.asarray(params.inertia, dtype)

    # Low-level controller: PID on the filtered gyro -> torque -> mixer -> motor speed commands.
    ang_acc_cmd, integrator = rate_pid(state, u_cmd[:3], dt, params)
    motor_cmd = mix(inertia * ang_acc_cmd, u_cmd[3], params)

    # Process noise, drawn per step from the continuous-time PSDs.
    linear_noise = jnp.sqrt(params.linear_noise_psd / dt) * jax.random.normal(key_linear, (3,), dtype)
    angular_noise = jnp.sqrt(params.angular_noise_psd / dt) * jax.random.normal(key_angular, (3,), dtype)

    # Rigid body, explicit Euler: translation and attitude by the paper's model with the true rates/thrust.
    torque, thrust = motor_wrench(state.motor_speeds, params)
    quad = QuadParams(mass=params.mass, drag_coefficient=params.drag_coefficient, gravity=params.gravity)
    u_true = jnp.concatenate([state.rates, thrust[None]]).astype(dtype)
    external = params.mass * linear_noise
    if wind is not None:
        external = external + wind_force(state.x[7:10], wind, params)
    x_next = state.x + dt * dynamics(state.x, u_true, quad, w_f=external)
    x_next = x_next.at[QUAT].set(normalize_quat(x_next[QUAT]))
    gyroscopic = jnp.cross(state.rates, inertia * state.rates)
    rates_dot = (torque - gyroscopic) / inertia + angular_noise
    rates_next = state.rates + dt * rates_dot
    lag = jnp.minimum(dt / params.motor_time_constant, 1.0)
    motors_next = jnp.clip(
        state.motor_speeds + lag * (motor_cmd - state.motor_speeds), 0.0, params.motor_speed_max
    )

    # IMU at the new state; the gyro sample feeds the low-pass for the next step's PID.
    felt = linear_noise if wind is None else linear_noise + wind_force(x_next[7:10], wind, params) / params.mass
    accel_true = specific_force_body(x_next, motors_next, felt, params)
    accel = accel_true + jnp.sqrt(params.accel_noise_variance) * jax.random.normal(key_accel, (3,), dtype)
    gyro = rates_next + jnp.sqrt(params.gyro_noise_variance) * jax.random.normal(key_gyro, (3,), dtype)
    filtered_rate, filtered_rate_dot = lowpass_update(
        state.filtered_rate, state.filtered_rate_dot, gyro, dt, params
    )

    new_state = PlantState(
        x=x_next.astype(dtype),
        rates=rates_next.astype(dtype),
        motor_speeds=motors_next.astype(dtype),
        filtered_rate=filtered_rate.astype(dtype),
        filtered_rate_dot=filtered_rate_dot.astype(dtype),
        integrator=integrator.astype(dtype),
    )
    return new_state, IMU(accel=accel.astype(dtype), gyro=gyro.astype(dtype))


def plant_tick(
    state: PlantState,
    u_cmd: jax.Array,
    key: jax.Array,
    params: PlantParams,
    substeps: int = SUBSTEPS_PER_TICK,
    dt: float = PLANT_DT,
    wind: jax.Array | None = None,
) -> tuple[PlantState, IMU, TickIMU]:
    """One control period (``substeps * dt``, 1/40 s by default) with the command held, by ``lax.scan``.

    ``substeps`` is static (jit with ``static_argnames=("substeps",)``); the key is split once per substep.
    ``wind``: (3,) m/s, held over the tick (see :func:`plant_substep`; None: still air).

    Returns:
        state: the plant after the tick.
        imu_last: the last IMU sample, each field (3,).
        imu_tick: the tick's ``substeps`` IMU samples: their mean (``accel``, ``gyro``) and their
            preintegration (:class:`TickIMU`).
    """
    _check_inputs(state, u_cmd)
    substep_keys = jax.random.split(key, substeps)

    def substep(carry, substep_key):
        return plant_substep(carry, u_cmd, substep_key, params, dt, wind)

    state, imus = jax.lax.scan(substep, state, substep_keys)  # each IMU field (substeps, 3)
    imu_last = jax.tree.map(lambda a: a[-1], imus)
    return state, imu_last, preintegrate(imus, dt)
