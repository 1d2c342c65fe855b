"""Generic MPPI: behaviour on small problems, numerics, determinism, compilation, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.apps.racing.waypoint import fly_to_waypoint
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi
from pixelmpc_jax.control.sampling import importance_weights
from pixelmpc_jax.devices import compile_controller
from pixelmpc_jax.dynamics import quadrotor as Q

DT = 0.05


def double_integrator(x, u, params):
    pos, vel = x[:2], x[2:]
    vel = vel + DT * u
    return jnp.concatenate([pos + DT * vel, vel])


def goal_cost(x, u, t, goal):
    return jnp.sum((x[:2] - goal) ** 2) + 0.1 * jnp.sum(x[2:] ** 2) + 0.01 * jnp.sum(u**2)


def closed_loop(ctrl, state, x, params, steps, plant):
    def tick(carry, _):
        x, state = carry
        u, state, info = ctrl.step(state, x, params)
        return (plant(x, u, params), state), (x, u)

    (x, state), (xs, us) = jax.jit(lambda c: jax.lax.scan(tick, c, None, length=steps))((x, state))
    return x, state, xs, us


def test_importance_weights_formula_and_nonfinite_exclusion():
    costs = jnp.asarray([3.0, 1.0, jnp.nan, 2.0, jnp.inf])
    w, finite = importance_weights(costs, 0.5)
    expected = np.exp(-(np.array([3.0, 1.0, 2.0]) - 1.0) / 0.5)
    expected /= expected.sum()
    np.testing.assert_allclose(w[jnp.asarray([0, 1, 3])], expected, rtol=1e-6)
    assert float(w[2]) == 0.0 and float(w[4]) == 0.0
    assert finite.tolist() == [True, True, False, True, False]
    w_all, _ = importance_weights(jnp.full(4, jnp.nan), 1.0)
    assert float(jnp.sum(w_all)) == 0.0


def test_double_integrator_reaches_goal():
    cfg = MPPIConfig(num_samples=256, horizon=30, dt=DT, noise_sigma=(1.0, 1.0), temperature=1.0,
                     u_min=(-3.0, -3.0), u_max=(3.0, 3.0))
    ctrl = make_mppi(cfg, double_integrator, goal_cost)
    goal = jnp.asarray([2.0, -1.0])
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    x, _, _, us = closed_loop(ctrl, state, jnp.zeros(4), goal, 120, double_integrator)
    assert float(jnp.linalg.norm(x[:2] - goal)) < 0.1
    assert float(jnp.linalg.norm(x[2:])) < 0.2
    assert float(jnp.max(jnp.abs(us))) <= 3.0 + 1e-6  # bounds respected


def test_pendulum_swings_up_with_limited_torque():
    def pendulum(x, u, params):
        theta, omega = x[0], x[1]
        omega = omega + DT * (-9.81 * jnp.sin(theta) - 0.1 * omega + u[0])
        return jnp.stack([theta + DT * omega, omega])

    def cost(x, u, t, params):
        return 10.0 * (1.0 + jnp.cos(x[0])) + 0.1 * x[1] ** 2 + 0.001 * u[0] ** 2

    # torque 4 < m g l = 9.81: the pendulum must pump energy to get up
    cfg = MPPIConfig(num_samples=256, horizon=40, dt=DT, noise_sigma=(2.0,), temperature=0.5,
                     u_min=(-4.0,), u_max=(4.0,))
    ctrl = make_mppi(cfg, pendulum, cost)
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(1))
    _, _, xs, _ = closed_loop(ctrl, state, jnp.zeros(2), None, 200, pendulum)
    upright = np.cos(np.asarray(xs[:, 0])) < -0.95
    assert upright[-60:].all(), "the pendulum must be up and stay up for the last 3 s"


def test_quadrotor_flies_to_waypoint_5m_away_and_holds_it():
    start = Q.hover_state((0.0, 0.0, 2.0))
    waypoint = jnp.asarray([5.0, 0.0, 2.0, 0.0])
    flight = fly_to_waypoint(start, waypoint, num_ticks=200, seed=1)
    error = np.linalg.norm(np.asarray(flight.states[:, :3]) - np.asarray(waypoint[:3]), axis=1)
    assert error[0] == pytest.approx(5.0)
    assert error[-80:].max() < 0.15, "holds within 15 cm over the last 2 s"
    assert np.linalg.norm(np.asarray(flight.states[-1, 7:])) < 0.2


def test_same_key_identical_results_different_key_differs():
    cfg = MPPIConfig(num_samples=64, horizon=10, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    goal = jnp.asarray([1.0, 1.0])
    outs = []
    for seed in (0, 0, 1):
        state = ctrl.init(jax.random.PRNGKey(seed), jnp.zeros(2))
        u, state, info = ctrl.step(state, jnp.zeros(4), goal)
        u2, _, _ = ctrl.step(state, jnp.ones(4), goal)
        outs.append(np.concatenate([u, u2]))
    np.testing.assert_array_equal(outs[0], outs[1])
    assert not np.allclose(outs[0], outs[2])


def test_key_is_split_every_step():
    cfg = MPPIConfig(num_samples=16, horizon=5, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    _, state2, _ = ctrl.step(state, jnp.zeros(4), jnp.zeros(2))
    assert not np.array_equal(jax.random.key_data(state.key), jax.random.key_data(state2.key))


def test_nonfinite_samples_are_ignored():
    # Any sample whose first control in channel 0 is positive gets a NaN cost: the update must come
    # only from the others, so the plan's first control must move negative.
    def cost(x, u, t, goal):
        poison = jnp.where((t == 0) & (u[0] > 0.0), jnp.nan, 0.0)
        return goal_cost(x, u, t, goal) + poison

    cfg = MPPIConfig(num_samples=128, horizon=10, dt=DT, noise_sigma=(1.0, 1.0), nominal_sample=False)
    ctrl = compile_controller(make_mppi(cfg, double_integrator, cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    u0, state, info = ctrl.step(state, jnp.zeros(4), jnp.asarray([5.0, 0.0]))
    assert 0 < int(info.num_nonfinite) < 128
    assert not bool(info.all_nonfinite)
    assert float(u0[0]) < 0.0
    assert bool(jnp.all(jnp.isfinite(state.plan)))
    assert np.isfinite(float(info.min_cost)) and np.isfinite(float(info.mean_cost))


def test_all_nonfinite_keeps_the_plan_and_says_so():
    def cost(x, u, t, params):
        return jnp.nan * jnp.sum(x)

    cfg = MPPIConfig(num_samples=32, horizon=6, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, cost))
    plan = jnp.stack([jnp.arange(6.0), -jnp.arange(6.0)], axis=1)
    state = ctrl.init(jax.random.PRNGKey(0), plan)
    u0, new_state, info = ctrl.step(state, jnp.zeros(4), None)
    assert bool(info.all_nonfinite) and int(info.num_nonfinite) == 32
    np.testing.assert_array_equal(u0, plan[0])
    np.testing.assert_array_equal(new_state.plan[:-1], plan[1:])  # kept, then shifted


def test_update_uses_clipped_noise_and_stays_in_bounds():
    cfg = MPPIConfig(num_samples=64, horizon=8, dt=DT, noise_sigma=(5.0, 5.0), u_min=(-1.0, -1.0),
                     u_max=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.asarray([0.9, -0.9]))
    for _ in range(5):
        u0, state, _ = ctrl.step(state, jnp.zeros(4), jnp.asarray([100.0, -100.0]))
        assert float(jnp.max(jnp.abs(state.plan))) <= 1.0 + 1e-6
    np.testing.assert_allclose(u0, [1.0, -1.0], atol=0.05)


def test_info_shapes_and_nominal_trajectory_follows_the_plan():
    cfg = MPPIConfig(num_samples=32, horizon=7, dt=DT, noise_sigma=(0.5, 0.5), iterations=3)
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    x0 = jnp.asarray([0.1, 0.2, 0.0, 0.0])
    u0, new_state, info = ctrl.step(state, x0, jnp.ones(2))
    assert info.nominal_trajectory.shape == (8, 4)
    assert info.costs.shape == (32,)
    np.testing.assert_allclose(info.nominal_trajectory[0], x0)
    np.testing.assert_allclose(info.nominal_trajectory[1], double_integrator(x0, u0, None), atol=1e-6)
    assert 1.0 <= float(info.effective_sample_size) <= 32.0


def test_gamma_control_cost_changes_the_result():
    base = dict(num_samples=64, horizon=8, dt=DT, noise_sigma=(1.0, 1.0))
    goal = jnp.asarray([1.0, 1.0])
    results = []
    for gamma in (0.0, 5.0):
        config = MPPIConfig(**base, control_cost_weight=gamma)
        ctrl = compile_controller(make_mppi(config, double_integrator, goal_cost))
        state = ctrl.init(jax.random.PRNGKey(0), jnp.ones(2))
        results.append(ctrl.step(state, jnp.zeros(4), goal)[2].costs)
    assert not np.allclose(results[0], results[1])
    np.testing.assert_allclose(results[0][0], results[1][0], rtol=1e-6)  # nominal sample has eps = 0


def test_no_recompilation_across_20_steps_with_new_params_and_state():
    cfg = MPPIConfig(num_samples=32, horizon=10, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    x = jnp.zeros(4)
    assert ctrl.num_compilations() == 0
    for i in range(20):
        u, state, _ = ctrl.step(state, x, jnp.asarray([float(i), -float(i)]))
        x = double_integrator(x, u, None)
    assert ctrl.num_compilations() == 1
    # the counter does move: a params pytree of another shape is a new signature
    ctrl.step(state, x, jnp.zeros(3)[:2].reshape(1, 2))
    assert ctrl.num_compilations() == 2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(temperature=0.0), "temperature"),
        (dict(temperature=-1.0), "temperature"),
        (dict(horizon=0), "horizon"),
        (dict(num_samples=-5), "num_samples"),
        (dict(iterations=0), "iterations"),
        (dict(noise_sigma=((1.0, 2.0),)), "noise_sigma"),
        (dict(noise_sigma=(1.0, -1.0)), "noise_sigma"),
        (dict(u_min=(0.0, 1.0), u_max=(1.0, 0.0)), "u_min > u_max"),
        (dict(u_min=(0.0,)), r"u_min must have shape \(2,\)"),
    ],
)
def test_bad_config_is_rejected_with_a_clear_message(kwargs, match):
    base = dict(num_samples=8, horizon=4, dt=DT, noise_sigma=(1.0, 1.0))
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        MPPIConfig(**base)


def test_bad_u_init_and_x0_are_rejected_before_tracing():
    cfg = MPPIConfig(num_samples=8, horizon=4, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    with pytest.raises(ValueError, match=r"u_init must have shape \(4, 2\)"):
        ctrl.init(jax.random.PRNGKey(0), jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="u_init must be finite"):
        ctrl.init(jax.random.PRNGKey(0), jnp.asarray([jnp.nan, 0.0]))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"x0 must be one state of shape \(n,\)"):
        ctrl.step(state, jnp.zeros((2, 4)), jnp.zeros(2))
    with pytest.raises(ValueError, match="x0"):
        ctrl.step(state, jnp.zeros(3), jnp.zeros(2))


def test_an_integer_state_steps_as_the_float_state():
    cfg = MPPIConfig(num_samples=8, horizon=4, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, double_integrator, goal_cost))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    x = jnp.asarray([1, 0, -2, 1])
    u_int, _, info_int = ctrl.step(state, x.astype(jnp.int32), jnp.zeros(2))
    u_float, _, info_float = ctrl.step(state, x.astype(jnp.float32), jnp.zeros(2))
    assert u_int.dtype == jnp.float32 and ctrl.num_compilations() == 1  # converted before the jit: one signature
    np.testing.assert_array_equal(u_int, u_float)
    np.testing.assert_array_equal(info_int.costs, info_float.costs)


def test_prefix_equals_one_time_varying_rollout():
    # A costly extra state (x[4]) that only matters over the first 5 steps: running it only in the prefix
    # must give exactly what one full-horizon rollout with a time switch gives.
    from pixelmpc_jax.control.rollout import Prefix, rollout_cost, rollout_states

    def full_dynamics(x, u, t, params):
        extra = jnp.where(t < 5, x[4] + DT * jnp.sin(x[0] + u[0]), x[4])
        return jnp.concatenate([double_integrator(x[:4], u, params), extra[None]])

    def full_cost(x, u, t, goal):
        return goal_cost(x[:4], u, t, goal) + jnp.where(t < 5, 3.0 * x[4] ** 2, 0.0)

    def prefix_dynamics(x, u, params):
        return jnp.concatenate([double_integrator(x[:4], u, params), (x[4] + DT * jnp.sin(x[0] + u[0]))[None]])

    def main_dynamics(x, u, params):
        return jnp.concatenate([double_integrator(x[:4], u, params), x[4:]])

    prefix = Prefix(5, prefix_dynamics, lambda x, u, t, g: goal_cost(x[:4], u, t, g) + 3.0 * x[4] ** 2)
    main_cost = lambda x, u, t, g: goal_cost(x[:4], u, t, g)  # noqa: E731

    def reference(x0, controls, goal):
        def body(x, inputs):
            t, u = inputs
            x_next = full_dynamics(x, u, t, goal)
            return x_next, (full_cost(x_next, u, t, goal), x_next)

        _, (costs, states) = jax.lax.scan(body, x0, (jnp.arange(12), controls))
        return jnp.sum(costs), jnp.concatenate([x0[None], states])

    x0 = jnp.asarray([0.3, -0.2, 0.1, 0.0, 0.5])
    controls = jax.random.normal(jax.random.PRNGKey(0), (12, 2))
    goal = jnp.asarray([1.0, 1.0])
    ref_cost, ref_states = reference(x0, controls, goal)
    split_cost = rollout_cost(main_dynamics, main_cost, None, x0, controls, goal, prefix)
    split_states = rollout_states(main_dynamics, x0, controls, goal, prefix)
    np.testing.assert_allclose(split_cost, ref_cost, rtol=1e-6)
    np.testing.assert_allclose(split_states, ref_states, atol=1e-6)
    # and the controller built with the prefix runs, keeping the extra state in its prediction
    cfg = MPPIConfig(num_samples=16, horizon=12, dt=DT, noise_sigma=(1.0, 1.0))
    ctrl = compile_controller(make_mppi(cfg, main_dynamics, main_cost, prefix=prefix))
    _, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2)), x0, goal)
    assert info.nominal_trajectory.shape == (13, 5)
    with pytest.raises(ValueError, match="prefix.steps"):
        make_mppi(cfg, main_dynamics, main_cost, prefix=Prefix(13, prefix_dynamics, main_cost))


def test_batch_cost_gives_the_same_rollout_costs_as_the_one_sample_cost():
    """A BatchCost sees all samples at once; each sample's cost must be its own (no mixing across samples)."""
    from pixelmpc_jax.control.rollout import BatchCost, rollout_cost, rollout_costs

    goal = jnp.asarray([1.0, -0.5])

    def batch_goal_cost(X, U, t, goal):  # samples on the last axis inside, as a real batch cost lays it out
        Xt, Ut = X.T, U.T
        return (jnp.sum((Xt[:2] - goal[:, None]) ** 2, axis=0) + 0.1 * jnp.sum(Xt[2:] ** 2, axis=0)
                + 0.01 * jnp.sum(Ut**2, axis=0))

    controls = jax.random.normal(jax.random.PRNGKey(3), (16, 12, 2))
    x0 = jnp.asarray([0.0, 0.0, 0.3, 0.0])
    expected = jnp.stack([rollout_cost(double_integrator, goal_cost, None, x0, c, goal) for c in controls])
    got_vmapped = rollout_costs(double_integrator, goal_cost, None, x0, controls, goal)
    got_batch = rollout_costs(double_integrator, BatchCost(batch_goal_cost), None, x0, controls, goal)
    np.testing.assert_allclose(got_vmapped, expected, rtol=1e-5)
    np.testing.assert_allclose(got_batch, expected, rtol=1e-5)
    # called on one sample, a BatchCost runs as a batch of one
    x1 = double_integrator(x0, controls[0, 0], goal)
    np.testing.assert_allclose(BatchCost(batch_goal_cost)(x1, controls[0, 0], 0, goal),
                               goal_cost(x1, controls[0, 0], 0, goal), rtol=1e-6)


def test_batch_and_trajectory_costs_give_the_one_sample_costs():
    """A running cost written for one sample (vmapped), for each step's batch (BatchCost) or for every step at once
    (TrajectoryCost) charges every sample the sum a plain loop over the steps gives, with and without a prefix
    whose model and cost differ from the main ones."""
    from pixelmpc_jax.control.rollout import BatchCost, Prefix, TrajectoryCost, rollout_costs

    goal = jnp.asarray([1.0, -0.5])

    def step_goal_cost(x, u, t, goal):  # depends on the step index
        return goal_cost(x, u, t, goal) * (1.0 + t)

    def batch_goal_cost(X, U, t, goal):
        return jax.vmap(step_goal_cost, in_axes=(0, 0, None, None))(X, U, t, goal)

    def trajectory_goal_cost(X, U, steps, goal):  # (T, N, n) -> (T, N)
        return jax.vmap(batch_goal_cost, in_axes=(0, 0, 0, None))(X, U, steps, goal)

    prefix = Prefix(4, lambda x, u, p: double_integrator(x, 2.0 * u, p), lambda x, u, t, g: 3.0 * goal_cost(x, u, t, g))
    controls = jax.random.normal(jax.random.PRNGKey(3), (16, 12, 2))
    x0 = jnp.asarray([0.0, 0.0, 0.3, 0.0])

    def loop(sequence, pre):  # one sample, step by step
        x, total = x0, 0.0
        for t in range(sequence.shape[0]):
            in_prefix = pre is not None and t < pre.steps
            x = (pre.dynamics if in_prefix else double_integrator)(x, sequence[t], goal)
            total = total + (pre.running_cost if in_prefix else step_goal_cost)(x, sequence[t], t, goal)
        return total

    for pre in (None, prefix):
        expected = jax.vmap(lambda c, pre=pre: loop(c, pre))(controls)
        for cost in (step_goal_cost, BatchCost(batch_goal_cost), TrajectoryCost(trajectory_goal_cost)):
            got = rollout_costs(double_integrator, cost, None, x0, controls, goal, pre)
            np.testing.assert_allclose(got, expected, rtol=1e-6)
    # the step costs really depend on the step index: a trajectory cost that ignored it would differ
    flat = rollout_costs(double_integrator, goal_cost, None, x0, controls, goal)
    assert not np.allclose(got, flat)


def test_sample_weights_and_update_are_the_mppi_equations():
    """The pieces of one iteration against the formulas: controls = clip(U + sigma * white) with sample 0 the plan,
    eps = controls - U; S_k = cost_k + gamma sum_t U_t^T Sigma^-1 eps_{k,t}; w = softmax(-(S - min S) / lambda) over
    the finite S; U <- clip(U + sum_k w_k eps_k), or U kept when every S_k is non-finite."""
    from pixelmpc_jax.control import mppi

    config = MPPIConfig(num_samples=6, horizon=3, dt=DT, noise_sigma=(0.5, 2.0), temperature=0.7,
                        control_cost_weight=0.3, u_min=(-1.0, -1.0), u_max=(1.0, 1.5))
    sampling = mppi._sampling(config)
    plan = jnp.asarray([[0.2, -0.4], [0.9, 1.2], [-0.5, 0.0]])
    key = jax.random.PRNGKey(2)
    controls, eps = mppi._sample(key, plan, sampling)
    white = np.asarray(jax.random.normal(key, (6, 3, 2)), np.float64)
    lo, hi = np.asarray([-1.0, -1.0]), np.asarray([1.0, 1.5])
    expected_controls = np.clip(np.asarray(plan) + white * [0.5, 2.0], lo, hi)
    expected_controls[0] = plan
    np.testing.assert_allclose(controls, expected_controls, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(eps, expected_controls - np.asarray(plan), atol=1e-6)

    raw = jnp.asarray([3.0, 1.0, jnp.nan, 2.0, 5.0, 4.0])
    costs, weights, finite = mppi._weights(raw, plan, eps, sampling)
    S = np.asarray(raw) + 0.3 * np.einsum("tm,ntm->n", np.asarray(plan), np.asarray(eps) / np.square([0.5, 2.0]))
    w = np.where(np.isfinite(S), np.exp(-(S - np.nanmin(S)) / 0.7), 0.0)
    np.testing.assert_allclose(costs, S, rtol=1e-5)
    np.testing.assert_allclose(weights, w / np.nansum(w), rtol=1e-5, atol=1e-7)
    assert finite.tolist() == [True, True, False, True, True, True]

    updated = mppi._update(plan, weights, eps, jnp.asarray(False), sampling)
    expected_plan = np.clip(np.asarray(plan) + np.einsum("n,ntm->tm", w / np.nansum(w), np.asarray(eps)), lo, hi)
    np.testing.assert_allclose(updated, expected_plan, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(mppi._update(plan, weights, eps, jnp.asarray(True), sampling), plan)


def test_trajectory_cost_of_the_wrong_shape_is_refused_and_one_sample_call_works():
    from pixelmpc_jax.control.rollout import TrajectoryCost

    config = MPPIConfig(num_samples=16, horizon=4, dt=DT, noise_sigma=(1.0, 1.0))
    per_sample = TrajectoryCost(lambda X, U, steps, goal: jnp.sum(X, axis=0))  # (N, n): one row per sample, not step
    ctrl = compile_controller(make_mppi(config, double_integrator, per_sample))
    state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"shape \(T, N\) = \(4, 16\); it returned shape \(16, 4\)"):
        ctrl.step(state, jnp.zeros(4), jnp.zeros(2))
    squared = TrajectoryCost(lambda X, U, steps, goal: jnp.sum(X**2, axis=-1) + steps[:, None])
    x = jnp.asarray([1.0, 2.0, 0.0, 0.5])
    np.testing.assert_allclose(squared(x, jnp.zeros(2), 3, None), 1.0 + 4.0 + 0.25 + 3.0, rtol=1e-6)


def test_batched_step_is_the_same_with_and_without_jit():
    cfg = MPPIConfig(num_samples=32, horizon=8, dt=DT, noise_sigma=(1.0, 1.0), u_min=(-2.0, -2.0), u_max=(2.0, 2.0))
    pure = make_mppi(cfg, double_integrator, goal_cost)
    state = pure.init(jax.random.PRNGKey(1), jnp.zeros(2))
    x, goal = jnp.asarray([0.1, 0.0, 0.0, 0.2]), jnp.asarray([1.0, -1.0])
    u_jit, s_jit, info_jit = compile_controller(pure).step(state, x, goal)
    with jax.disable_jit():
        u_eager, s_eager, info_eager = pure.step(state, x, goal)
    np.testing.assert_allclose(info_eager.costs, info_jit.costs, rtol=1e-5)
    np.testing.assert_allclose(s_eager.plan, s_jit.plan, atol=1e-5)
    np.testing.assert_allclose(u_eager, u_jit, atol=1e-5)


def test_the_pure_step_vmapped_over_8_robots_in_one_jit_gives_each_robot_its_own_step():
    """The pure pair composes in the caller's program: init and step vmapped over 8 robots (8 keys, 8 warm starts,
    8 states, 8 goals) inside one ``jax.jit`` give each robot what its own jitted step gives: the same keys, counts
    and flags exactly, the same floats up to the rounding of batched reductions (rtol 1e-5, atol 1e-6; 3e-6 seen)."""
    cfg = MPPIConfig(num_samples=64, horizon=10, dt=DT, noise_sigma=(1.0, 1.0), u_min=(-2.0, -2.0), u_max=(2.0, 2.0))
    ctrl = make_mppi(cfg, double_integrator, goal_cost)
    keys = jax.random.split(jax.random.PRNGKey(7), 8)
    plans = 0.5 * jax.random.normal(jax.random.PRNGKey(8), (8, 10, 2))
    x0s = jax.random.normal(jax.random.PRNGKey(9), (8, 4))
    goals = jax.random.normal(jax.random.PRNGKey(10), (8, 2))

    @jax.jit
    def fleet(keys, plans, x0s, goals):
        states = jax.vmap(ctrl.init)(keys, plans)
        return states, jax.vmap(ctrl.step)(states, x0s, goals)

    states, (u, stepped, info) = fleet(keys, plans, x0s, goals)
    single = jax.jit(ctrl.step)
    close = dict(rtol=1e-5, atol=1e-6)
    for i in range(8):
        state = ctrl.init(keys[i], plans[i])
        np.testing.assert_array_equal(states.plan[i], state.plan)
        u_i, stepped_i, info_i = single(state, x0s[i], goals[i])
        np.testing.assert_allclose(u[i], u_i, **close)
        np.testing.assert_allclose(stepped.plan[i], stepped_i.plan, **close)
        np.testing.assert_array_equal(jax.random.key_data(stepped.key[i]), jax.random.key_data(stepped_i.key))
        for name, value in info._asdict().items():
            if jnp.issubdtype(value.dtype, jnp.floating):
                np.testing.assert_allclose(value[i], getattr(info_i, name), **close, err_msg=name)
            else:
                np.testing.assert_array_equal(value[i], getattr(info_i, name), err_msg=name)
    assert len({tuple(np.asarray(row).tolist()) for row in u}) == 8  # 8 robots, 8 different controls
