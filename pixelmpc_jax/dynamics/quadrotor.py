"""The paper's 10-state quadrotor model, Eqs. (3)-(6), and quaternion helpers.

State ``x = [px, py, pz, qw, qx, qy, qz, vx, vy, vz]`` (10,), world frame ENU with z up; ``q`` rotates
body to world (the paper's ``R_b^w``). Control ``u = [wx, wy, wz, thrust]`` (4,): body rates in rad/s and
collective thrust in newtons along body +z. The model follows the commanded rates immediately (the
paper's assumption; the simulator's low-level controller lives in ``sim/plant.py``).

Every function here is written for one sample, is pure, and works under ``jit``, ``vmap`` and ``grad``
in float32 or float64 (the dtype of the state decides).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

STATE_DIM = 10
CONTROL_DIM = 4

# Slices into the state vector, in the paper's order.
POS = slice(0, 3)
QUAT = slice(3, 7)
VEL = slice(7, 10)


@struct.dataclass
class QuadParams:
    """Vehicle facts of the AlphaPilot FlightGoggles drone (``pixelmpc_jax/data/alphapilot_course.json``).

    A pytree: a new mass or drag coefficient is a new argument, not a new compilation.

    Attributes:
        mass: kg.
        drag_coefficient: ``c_d`` of the drag force ``f_D = -c_d |v| v`` (N per (m/s)^2).
        gravity: m/s^2, acting along world -z.
        thrust_min, thrust_max: collective thrust limits, N.
        rate_max: (3,) body-rate limits, rad/s, applied symmetrically.
    """

    mass: float | jax.Array = 1.0
    drag_coefficient: float | jax.Array = 0.1
    gravity: float | jax.Array = 9.81
    thrust_min: float | jax.Array = 0.0
    thrust_max: float | jax.Array = 36.98
    rate_max: tuple | jax.Array = (6.0, 6.0, 6.0)

    @property
    def hover_thrust(self):
        return self.mass * self.gravity

    def control_bounds(self):
        """Returns ``(u_min, u_max)``, each (4,), the box the model's controls live in."""
        rate_max = jnp.asarray(self.rate_max, dtype=jnp.float32)
        u_min = jnp.concatenate([-rate_max, jnp.asarray([self.thrust_min], jnp.float32)])
        u_max = jnp.concatenate([rate_max, jnp.asarray([self.thrust_max], jnp.float32)])
        return u_min, u_max


# --------------------------------------------------------------------------------------------------
# Quaternions, scalar first: q = [qw, qx, qy, qz].
# --------------------------------------------------------------------------------------------------


def normalize_quat(q: jax.Array) -> jax.Array:
    """Unit quaternion with ``qw >= 0`` is not enforced; only the norm is fixed. Zero input gives identity."""
    # elementwise, not a reduction: vmapped over samples it fuses with the model (a reduction is its own kernel)
    n2 = (q[..., 0] * q[..., 0] + q[..., 1] * q[..., 1] + q[..., 2] * q[..., 2] + q[..., 3] * q[..., 3])[..., None]
    ok = n2 > 0
    safe = jnp.where(ok, n2, 1.0)
    identity = jnp.zeros_like(q).at[..., 0].set(1.0)
    return jnp.where(ok, q / jnp.sqrt(safe), identity)


def rotation_matrix(q: jax.Array) -> jax.Array:
    """Body-to-world rotation ``R_b^w`` of a unit quaternion, Eq. (5). q: (4,) -> (3, 3)."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (qy**2 + qz**2), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)]),
            jnp.stack([2 * (qx * qy + qz * qw), 1 - 2 * (qx**2 + qz**2), 2 * (qy * qz - qx * qw)]),
            jnp.stack([2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx**2 + qy**2)]),
        ]
    )


def omega_matrix(q: jax.Array) -> jax.Array:
    """The (4, 3) matrix of Eq. (6): ``q_dot = 0.5 * Omega(q) @ w`` for body rates ``w``."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([-qx, -qy, -qz]),
            jnp.stack([qw, -qz, qy]),
            jnp.stack([qz, qw, -qx]),
            jnp.stack([-qy, qx, qw]),
        ]
    )


def quat_multiply(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product ``a * b`` (apply b, then a)."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_conjugate(q: jax.Array) -> jax.Array:
    return q * jnp.asarray([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_from_axis_angle(axis: jax.Array, angle: jax.Array) -> jax.Array:
    """Rotation by ``angle`` (rad) about ``axis`` (3,); the axis need not be unit length (zero -> identity)."""
    axis = jnp.asarray(axis)
    angle = jnp.asarray(angle, dtype=axis.dtype)
    n2 = jnp.sum(axis * axis)
    ok = n2 > 0
    unit = axis / jnp.sqrt(jnp.where(ok, n2, 1.0))
    half = 0.5 * angle
    q = jnp.concatenate([jnp.cos(half)[None], jnp.sin(half) * unit])
    return jnp.where(ok, q, jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype=axis.dtype))


def quat_exp(w: jax.Array, dt) -> jax.Array:
    """The rotation by the body rate ``w`` (3,) (rad/s) held for ``dt`` s, ``exp(w dt / 2)``: the quaternion
    to right-multiply an attitude by, ``q' = q * quat_exp(w, dt)``.

    The same numbers as ``quat_from_axis_angle(w, |w| dt)``; at ``w = 0`` the identity, with a finite
    gradient there too (that of the first-order ``[1, w dt / 2]``, which ``|w|`` alone would make NaN)."""
    w = jnp.asarray(w)
    n2 = jnp.sum(w * w)
    ok = n2 > 0
    angle = jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0) * dt
    first_order = jnp.concatenate([jnp.ones((1,), w.dtype), (0.5 * dt * w).astype(w.dtype)])
    return jnp.where(ok, quat_from_axis_angle(w, angle), first_order)


def quat_from_euler(roll, pitch, yaw) -> jax.Array:
    """Quaternion of intrinsic Z-Y-X (yaw, then pitch, then roll) Euler angles, in rad."""
    cr, sr = jnp.cos(0.5 * roll), jnp.sin(0.5 * roll)
    cp, sp = jnp.cos(0.5 * pitch), jnp.sin(0.5 * pitch)
    cy, sy = jnp.cos(0.5 * yaw), jnp.sin(0.5 * yaw)
    return jnp.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def quat_from_yaw(yaw) -> jax.Array:
    """Level attitude heading ``yaw`` (rad, about world +z)."""
    yaw = jnp.asarray(yaw)
    zero = jnp.zeros_like(yaw)
    return jnp.stack([jnp.cos(0.5 * yaw), zero, zero, jnp.sin(0.5 * yaw)])


def euler_angles(q: jax.Array) -> jax.Array:
    """(roll, pitch, yaw) in rad, Z-Y-X convention, of a unit quaternion; pitch is clipped away from
    +-pi/2 by the arcsin's domain so the result is always finite."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    roll = jnp.arctan2(2 * (qw * qx + qy * qz), 1 - 2 * (qx**2 + qy**2))
    pitch = jnp.arcsin(jnp.clip(2 * (qw * qy - qz * qx), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy**2 + qz**2))
    return jnp.stack([roll, pitch, yaw])


def quat_rotate(q: jax.Array, v: jax.Array) -> jax.Array:
    """Rotate a body-frame vector (3,) into the world frame."""
    return rotation_matrix(q) @ v


# --------------------------------------------------------------------------------------------------
# The model.
# --------------------------------------------------------------------------------------------------


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| of a (3,) vector, with a finite gradient at v = 0 (where the true subgradient of |v| v is 0 anyway)."""
    n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]  # elementwise, not a reduction: fuses when vmapped
    ok = n2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def drag_force(v: jax.Array, params: QuadParams) -> jax.Array:
    """Aerodynamic drag ``f_D = -c_d |v| v`` (N), world frame, isotropic."""
    return -params.drag_coefficient * _safe_norm(v) * v


def check_shapes(x, u) -> None:
    """ValueError unless ``x`` is one state (10,) and ``u`` one control (4,). Shapes are static, so this runs
    once when a function is traced (inside ``jit`` or ``vmap`` too) and costs nothing at run time."""
    if jnp.shape(x) != (STATE_DIM,):
        raise ValueError(f"quadrotor state x must have shape ({STATE_DIM},) = [px, py, pz, qw, qx, qy, qz, vx, vy, "
                         f"vz], got shape {jnp.shape(x)}")
    if jnp.shape(u) != (CONTROL_DIM,):
        raise ValueError(f"quadrotor control u must have shape ({CONTROL_DIM},) = [wx, wy, wz, thrust], got shape "
                         f"{jnp.shape(u)}")


def dynamics(x: jax.Array, u: jax.Array, params: QuadParams, w_f: jax.Array | None = None) -> jax.Array:
    """Time derivative of the state, Eqs. (3)-(6).

    p_dot = v;  v_dot = g + (R_b^w [0, 0, f_T] + f_D + w_f) / m;  q_dot = 0.5 * Omega(q) w.

    Args:
        x: (10,) state.
        u: (4,) control ``[wx, wy, wz, thrust]``.
        params: vehicle facts.
        w_f: optional (3,) stochastic world-frame force (N), the paper's ``w_f``.

    Returns:
        x_dot: (10,).

    Raises:
        ValueError: ``x`` is not (10,) or ``u`` not (4,) (see :func:`check_shapes`).
    """
    check_shapes(x, u)
    if w_f is not None and jnp.shape(w_f) != (3,):
        raise ValueError(f"w_f must be one world-frame force of shape (3,), got shape {jnp.shape(w_f)}")
    qw, qx, qy, qz = x[3], x[4], x[5], x[6]
    v = x[VEL]
    wx, wy, wz, thrust = u[0], u[1], u[2], u[3]
    # Written out component by component (the third column of R_b^w, Eq. 5, and the rows of Omega(q) w, Eq. 6):
    # vmapped over samples, matrices built with stack become arrays of their own and products of them small
    # kernels, where these scalar expressions fuse into one kernel with the rest of the step.
    body_z = jnp.stack([2 * (qx * qz + qy * qw), 2 * (qy * qz - qx * qw), 1 - 2 * (qx**2 + qy**2)])
    force = body_z * thrust + drag_force(v, params)
    if w_f is not None:
        force = force + w_f
    gravity = jnp.asarray([0.0, 0.0, -1.0], dtype=x.dtype) * params.gravity
    v_dot = gravity + force / params.mass
    q_dot = 0.5 * jnp.stack([-qx * wx - qy * wy - qz * wz,
                             qw * wx - qz * wy + qy * wz,
                             qz * wx + qw * wy - qx * wz,
                             -qy * wx + qx * wy + qw * wz])
    return jnp.concatenate([v, q_dot, v_dot]).astype(x.dtype)


def _renormalize(x: jax.Array) -> jax.Array:
    return x.at[QUAT].set(normalize_quat(x[QUAT]))


def step(x: jax.Array, u: jax.Array, dt: float, params: QuadParams) -> jax.Array:
    """One explicit Euler step (the paper's Algorithm 3), quaternion renormalised. -> (10,)."""
    return _renormalize(x + dt * dynamics(x, u, params))


def step_rk4(x: jax.Array, u: jax.Array, dt: float, params: QuadParams) -> jax.Array:
    """One classical Runge-Kutta step with zero-order-hold control, quaternion renormalised. -> (10,)."""
    k1 = dynamics(x, u, params)
    k2 = dynamics(x + 0.5 * dt * k1, u, params)
    k3 = dynamics(x + 0.5 * dt * k2, u, params)
    k4 = dynamics(x + dt * k3, u, params)
    return _renormalize(x + (dt / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4))


def hover_state(position=(0.0, 0.0, 0.0), yaw: float = 0.0, dtype=jnp.float32) -> jax.Array:
    """Level state at rest at ``position`` heading ``yaw``. -> (10,)."""
    p = jnp.asarray(position, dtype=dtype)
    return jnp.concatenate([p, quat_from_yaw(jnp.asarray(yaw, dtype)), jnp.zeros(3, dtype)])


def hover_control(params: QuadParams, dtype=jnp.float32) -> jax.Array:
    """Zero rates and thrust ``m g``. -> (4,)."""
    return jnp.asarray([0.0, 0.0, 0.0, params.mass * params.gravity], dtype=dtype)


def load_params(vehicle: dict, rate_max=(6.0, 6.0, 6.0)) -> QuadParams:
    """QuadParams from the ``vehicle`` block of the course reference file."""
    return QuadParams(
        mass=float(vehicle["mass_kg"]),
        drag_coefficient=float(vehicle["drag_coefficient"]),
        thrust_max=float(vehicle["max_total_thrust_N"]),
        rate_max=tuple(float(r) for r in rate_max),
    )
