"""The paper's quadrotor model, Eqs. (3)-(6): equations, transformations, numerics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pixelmpc_jax.dynamics import quadrotor as Q

P = Q.QuadParams()


def test_default_params_match_reference_facts():
    assert P.mass == 1.0 and P.drag_coefficient == 0.1 and P.gravity == 9.81
    assert P.thrust_min == 0.0 and P.thrust_max == pytest.approx(36.98)
    lo, hi = P.control_bounds()
    np.testing.assert_allclose(lo, [-6, -6, -6, 0])
    np.testing.assert_allclose(hi, [6, 6, 6, 36.98], rtol=1e-6)


def test_hover_has_zero_acceleration():
    x = Q.hover_state((1.0, 2.0, 3.0), yaw=0.7)
    x_dot = Q.dynamics(x, Q.hover_control(P), P)
    np.testing.assert_allclose(x_dot, np.zeros(10), atol=1e-6)


def test_free_fall():
    x = Q.hover_state((0.0, 0.0, 10.0))
    x_dot = Q.dynamics(x, jnp.zeros(4), P)
    np.testing.assert_allclose(x_dot[7:], [0, 0, -9.81], atol=1e-6)
    x1 = Q.step(x, jnp.zeros(4), 0.1, P)
    np.testing.assert_allclose(x1[7:], [0, 0, -0.981], atol=1e-6)


def test_pure_yaw_rate_leaves_position_and_tilt_unchanged():
    x = Q.hover_state((1.0, -2.0, 3.0), yaw=0.3)
    u = jnp.asarray([0.0, 0.0, 1.5, P.mass * P.gravity])
    for _ in range(100):
        x = Q.step(x, u, 0.01, P)
    np.testing.assert_allclose(x[:3], [1.0, -2.0, 3.0], atol=1e-5)
    roll, pitch, yaw = Q.euler_angles(x[3:7])
    assert abs(float(roll)) < 1e-5 and abs(float(pitch)) < 1e-5
    # 1.5 rad/s for 1 s, wrapped: 0.3 + 1.5 = 1.8 rad
    assert float(yaw) == pytest.approx(1.8, abs=1e-3)


def test_thrust_direction_under_known_roll():
    roll = 0.4
    q = Q.quat_from_euler(roll, 0.0, 0.0)
    x = jnp.concatenate([jnp.zeros(3), q, jnp.zeros(3)])
    f = 20.0
    acc = Q.dynamics(x, jnp.asarray([0.0, 0.0, 0.0, f]), P)[7:]
    # body z after a positive roll about +x points to world -y: (0, -sin r, cos r)
    expected = np.array([0.0, -f * np.sin(roll), f * np.cos(roll) - 9.81])
    np.testing.assert_allclose(acc, expected, atol=1e-5)


def test_drag_opposes_velocity_with_quadratic_magnitude():
    v = jnp.asarray([3.0, -4.0, 0.0])  # |v| = 5
    x = jnp.concatenate([jnp.zeros(3), jnp.asarray([1.0, 0, 0, 0]), v])
    acc = Q.dynamics(x, Q.hover_control(P), P)[7:]  # hover thrust cancels gravity
    assert float(jnp.linalg.norm(acc)) == pytest.approx(0.1 * 25 / 1.0, rel=1e-6)
    np.testing.assert_allclose(acc / jnp.linalg.norm(acc), -v / 5.0, atol=1e-6)


def test_omega_matrix_is_half_quaternion_product():
    q = Q.normalize_quat(jnp.asarray([0.9, 0.1, -0.3, 0.2]))
    w = jnp.asarray([0.4, -1.0, 2.0])
    product = Q.quat_multiply(q, jnp.concatenate([jnp.zeros(1), w]))
    np.testing.assert_allclose(Q.omega_matrix(q) @ w, product, atol=1e-6)


def test_dynamics_written_out_equals_the_matrix_form_of_eqs_4_and_6():
    """The model's component-by-component expressions are R_b^w [0, 0, f_T] and 0.5 Omega(q) w (Eqs. 5, 6)."""
    key_q, key_v, key_u = jax.random.split(jax.random.PRNGKey(3), 3)
    qs = Q.normalize_quat(jax.random.normal(key_q, (64, 4)))
    vs = 6.0 * jax.random.normal(key_v, (64, 3))
    us = jnp.asarray([3.0, 3.0, 3.0, 10.0]) * jax.random.normal(key_u, (64, 4))
    for q, v, u in zip(qs, vs, us):
        x = jnp.concatenate([jnp.asarray([1.0, -2.0, 3.0]), q, v])
        x_dot = Q.dynamics(x, u, P)
        thrust = Q.rotation_matrix(q) @ jnp.asarray([0.0, 0.0, u[3]])
        v_dot = jnp.asarray([0.0, 0.0, -P.gravity]) + (thrust + Q.drag_force(v, P)) / P.mass
        np.testing.assert_allclose(x_dot[:3], v, atol=1e-6)
        np.testing.assert_allclose(x_dot[3:7], 0.5 * Q.omega_matrix(q) @ u[:3], atol=1e-5)
        np.testing.assert_allclose(x_dot[7:], v_dot, atol=1e-5)


def test_normalize_quat_over_a_batch_and_at_zero():
    q = jnp.asarray([[2.0, 0.0, 0.0, 0.0], [1.0, -1.0, 1.0, -1.0], [0.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(Q.normalize_quat(q), [[1, 0, 0, 0], [0.5, -0.5, 0.5, -0.5], [1, 0, 0, 0]], atol=1e-7)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_rotation_matrix_is_orthonormal(values):
    q = Q.normalize_quat(jnp.asarray(values, jnp.float32))
    R = Q.rotation_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    assert float(jnp.linalg.det(R)) == pytest.approx(1.0, abs=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.5, 1.5), st.floats(-3, 3))
def test_euler_round_trip(roll, pitch, yaw):
    angles = Q.euler_angles(Q.quat_from_euler(roll, pitch, yaw))
    np.testing.assert_allclose(angles, [roll, pitch, yaw], atol=2e-3)


def test_axis_angle_and_yaw_helpers_agree():
    np.testing.assert_allclose(Q.quat_from_axis_angle(jnp.asarray([0.0, 0.0, 2.0]), 0.8), Q.quat_from_yaw(0.8),
                               atol=1e-7)
    np.testing.assert_allclose(Q.quat_from_axis_angle(jnp.zeros(3), 0.8), [1, 0, 0, 0])


def test_quat_exp_is_the_axis_angle_form_and_safe_at_zero_rate():
    dt = 0.025
    rates = jax.random.normal(jax.random.PRNGKey(0), (64, 3), jnp.float32) * 4.0

    def axis_angle(w, dt):  # the form the rate-integration call sites used before quat_exp
        return Q.quat_from_axis_angle(w, jnp.sqrt(jnp.sum(w * w)) * dt)

    np.testing.assert_array_equal(jax.vmap(Q.quat_exp, (0, None))(rates, dt),
                                  jax.vmap(axis_angle, (0, None))(rates, dt))
    # jitted, XLA may fuse the form's operations and round otherwise (at its cheapest compilation, by 1 ulp)
    np.testing.assert_array_max_ulp(jax.jit(Q.quat_exp)(rates[0], dt), axis_angle(rates[0], dt), maxulp=2)
    zero = jnp.zeros(3, jnp.float32)
    np.testing.assert_array_equal(Q.quat_exp(zero, dt), [1.0, 0.0, 0.0, 0.0])
    assert bool(jnp.any(jnp.isnan(jax.jacobian(axis_angle)(zero, dt))))  # what quat_exp avoids
    jac = jax.jacobian(Q.quat_exp)(zero, dt)  # d q / d w at rest: [0; dt / 2 I], like the small-angle form
    np.testing.assert_allclose(jac, np.vstack([np.zeros((1, 3)), 0.5 * dt * np.eye(3)]), atol=1e-7)
    jac_dt = jax.jacobian(Q.quat_exp, argnums=1)(zero, dt)
    assert np.all(np.isfinite(jac_dt))
    small = jnp.asarray([1e-3, -2e-3, 5e-4], jnp.float32)  # near zero: the gradient is continuous
    np.testing.assert_allclose(jax.jacobian(Q.quat_exp)(small, dt), jac, atol=1e-6)


def test_quaternion_norm_after_10000_random_steps():
    key = jax.random.PRNGKey(3)
    controls = jax.random.uniform(key, (10_000, 4), minval=jnp.asarray([-6, -6, -6, 0.0]),
                                  maxval=jnp.asarray([6, 6, 6, 36.98]))

    def body(x, u):
        x = Q.step(x, u, 0.025, P)
        return x, jnp.linalg.norm(x[3:7])

    _, norms = jax.lax.scan(body, Q.hover_state(), controls)
    assert float(jnp.max(jnp.abs(norms - 1.0))) < 1e-5


def test_rk4_agrees_with_euler_for_small_steps_and_is_more_accurate():
    x0 = jnp.concatenate([jnp.zeros(3), Q.quat_from_euler(0.2, -0.1, 0.5), jnp.asarray([4.0, 1.0, 0.0])])
    u = jnp.asarray([0.3, -0.2, 0.5, 12.0])

    def integrate(step, dt, n):
        return jax.lax.fori_loop(0, n, lambda i, x: step(x, u, dt, P), x0)

    with jax.enable_x64(True):
        x64 = x0.astype(jnp.float64)
        fine = jax.lax.fori_loop(0, 4000, lambda i, x: Q.step_rk4(x, u.astype(jnp.float64), 0.00025, P), x64)
    euler = integrate(Q.step, 0.025, 40)
    rk4 = integrate(Q.step_rk4, 0.025, 40)
    err_euler = float(jnp.linalg.norm(euler - fine))
    err_rk4 = float(jnp.linalg.norm(rk4 - fine))
    assert err_rk4 < 0.05 * err_euler
    assert err_euler < 0.5


def test_jit_equals_no_jit_and_vmap_equals_loop():
    key = jax.random.PRNGKey(0)
    xs = jnp.concatenate([
        jax.random.normal(key, (8, 3)),
        Q.normalize_quat(jax.random.normal(jax.random.fold_in(key, 1), (8, 4))),
        jax.random.normal(jax.random.fold_in(key, 2), (8, 3)) * 5,
    ], axis=1)
    us = jax.random.uniform(jax.random.fold_in(key, 3), (8, 4), maxval=10.0)
    batched = jax.vmap(Q.step, in_axes=(0, 0, None, None))(xs, us, 0.025, P)
    jitted = jax.jit(Q.step)(xs[0], us[0], 0.025, P)
    for i in range(8):
        plain = Q.step(xs[i], us[i], 0.025, P)
        np.testing.assert_allclose(batched[i], plain, atol=1e-6)
    np.testing.assert_allclose(jitted, Q.step(xs[0], us[0], 0.025, P), atol=1e-6)


def test_float64_is_preserved_and_grad_matches_finite_differences():
    with jax.enable_x64(True):
        x = jnp.concatenate([jnp.asarray([0.5, -1.0, 2.0]), Q.quat_from_euler(0.3, -0.2, 1.0),
                             jnp.asarray([3.0, -2.0, 1.0])]).astype(jnp.float64)
        u = jnp.asarray([0.5, -0.4, 0.9, 14.0], dtype=jnp.float64)
        assert Q.step(x, u, 0.025, P).dtype == jnp.float64

        def f(x, u):
            return jnp.sum(jnp.sin(jnp.arange(1, 11) * Q.step(x, u, 0.025, P)))

        gx, gu = jax.grad(f, argnums=(0, 1))(x, u)
        h = 1e-6
        for i in range(10):
            e = jnp.zeros(10).at[i].set(h)
            fd = (f(x + e, u) - f(x - e, u)) / (2 * h)
            assert float(gx[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-7)
        for i in range(4):
            e = jnp.zeros(4).at[i].set(h)
            fd = (f(x, u + e) - f(x, u - e)) / (2 * h)
            assert float(gu[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-7)


def test_drag_gradient_is_finite_at_rest():
    grad = jax.grad(lambda v: jnp.sum(Q.drag_force(v, P)))(jnp.zeros(3))
    assert bool(jnp.all(jnp.isfinite(grad)))


def test_stochastic_force_enters_acceleration():
    x = Q.hover_state()
    acc = Q.dynamics(x, Q.hover_control(P), P, w_f=jnp.asarray([1.0, -2.0, 0.5]))[7:]
    np.testing.assert_allclose(acc, [1.0, -2.0, 0.5], atol=1e-6)
