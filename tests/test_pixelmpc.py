"""PixelMPC: one compiled step over robot + pixel; the t_f prefix equals the full-horizon computation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as PM
from pixelmpc_jax.control.mppi import make_mppi
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.dynamics import quadrotor as Q
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import track as T

SMALL = PM.paper_mppi_config(num_samples=64, horizon=24)


@pytest.fixture(scope="module")
def setup():
    track = T.load_course()
    dof_params = dof.init_dof_params(jax.random.PRNGKey(7))
    return track, dof_params


def make_params(track, dof_params, config, active=True, target=0, speed=14.0):
    racing = costs.racing_params(track, jnp.linspace(0.0, 20.0, config.mppi.horizon), speed, config.racing)
    return PM.PixelMPCParams(racing=racing, dof=dof_params, target_active=jnp.asarray(active),
                             target_centre=track.gates.centre[target],
                             target_normal=track.gates.normal[target], camera=C.default_camera())


def state(track, uv=(0.55, 0.45)):
    x = track.start.at[7:].set(track.path_tangents[0] * 5.0)
    return jnp.concatenate([x, jnp.asarray(uv)])


def test_prefix_equals_full_horizon_computation(setup):
    track, dof_params = setup
    config = PM.PixelMPCConfig(mppi=SMALL, t_f=0.25, c_pixel=9e6)  # n_f = 10 of 24 steps
    assert config.pixel_steps == 10
    fast = PM.make_pixelmpc(config)
    dt = SMALL.dt

    # The reference: the DOF runs over the WHOLE horizon; the pixel cost is masked after n_f steps.
    def full_dynamics(X, u, p):
        x_next = Q.step(X[:10], u, dt, Q.QuadParams())
        uv = X[10:] + dt * dof.pixel_velocity(p.dof, X[3:7], X[10:], u)
        return jnp.concatenate([x_next, uv])

    def full_cost(X, u, t, p):
        racing = costs.racing_cost(X[:10], t, p.racing, config.racing)
        pixel = jnp.where(t < config.pixel_steps, PM.pixel_cost(X[10:], config), 0.0)
        return racing + p.target_active * pixel

    full = make_mppi(SMALL, full_dynamics, full_cost)
    params = make_params(track, dof_params, config)
    key = jax.random.PRNGKey(3)
    u_init = Q.hover_control(Q.QuadParams())
    u_a, s_a, info_a = fast.step(fast.init(key, u_init), state(track), params)
    u_b, s_b, info_b = full.step(full.init(key, u_init), state(track), params)
    np.testing.assert_allclose(info_a.costs, info_b.costs, rtol=2e-5)
    np.testing.assert_allclose(u_a, u_b, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(s_a.plan, s_b.plan, rtol=1e-5, atol=1e-5)
    # the predicted pixel agrees where it is modelled; afterwards the fast version holds it still
    n_f = config.pixel_steps
    np.testing.assert_allclose(info_a.nominal_trajectory[: n_f + 1], info_b.nominal_trajectory[: n_f + 1],
                               atol=1e-5)
    np.testing.assert_allclose(info_a.nominal_trajectory[n_f:, 10:], np.broadcast_to(
        info_a.nominal_trajectory[n_f, 10:], (SMALL.horizon + 1 - n_f, 2)))


def test_pixel_cost_counts_only_while_the_target_is_detected(setup):
    track, dof_params = setup
    config = PM.PixelMPCConfig(mppi=SMALL, t_f=0.5, c_pixel=9e6)
    ctrl = PM.make_pixelmpc(config)
    key = jax.random.PRNGKey(0)
    u_init = Q.hover_control(Q.QuadParams())
    off_centre = state(track, uv=(0.9, 0.1))
    _, _, on = ctrl.step(ctrl.init(key, u_init), off_centre, make_params(track, dof_params, config, active=True))
    _, _, off = ctrl.step(ctrl.init(key, u_init), off_centre, make_params(track, dof_params, config, active=False))
    nominal = PM.make_pixelmpc(PM.PixelMPCConfig(mppi=SMALL, t_f=0.5, c_pixel=0.0))
    _, _, zero = nominal.step(nominal.init(key, u_init), off_centre, make_params(track, dof_params, config))
    np.testing.assert_allclose(off.costs, zero.costs, rtol=1e-6)
    # L1 of (0.9, 0.1) from the centre is 0.8: at least n_f steps of a large pixel cost in every sample
    assert float(jnp.min(on.costs - off.costs)) > 0.5 * 20 * 9e6 * config.pixel_cost_scale * 0.8


def test_projection_model_predicts_the_projected_target(setup):
    track, dof_params = setup
    config = PM.PixelMPCConfig(mppi=SMALL, t_f=0.5, pixel_model="projection")
    ctrl = PM.make_pixelmpc(config)
    params = make_params(track, dof_params, config)
    _, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(0), Q.hover_control(Q.QuadParams())), state(track), params)
    traj = info.nominal_trajectory
    for t in (1, 5, config.pixel_steps):
        uv, _, in_front = C.project(track.gates.centre[0], traj[t, :10], C.default_camera())
        assert bool(in_front)
        np.testing.assert_allclose(traj[t, 10:], uv, atol=1e-6)


def small_controller(track, dof_params, seed=0):
    """A PixelMPC controller at the small size with t_f = 0.25 s: (ctrl, config, its first state, params)."""
    config = PM.PixelMPCConfig(mppi=SMALL, t_f=0.25)
    ctrl = PM.make_pixelmpc(config)
    s = ctrl.init(jax.random.PRNGKey(seed), Q.hover_control(Q.QuadParams()))
    return ctrl, config, s, make_params(track, dof_params, config)


def test_no_recompilation_for_new_pixel_gates_or_weights(setup):
    track, dof_params = setup
    ctrl, config, s, params = small_controller(track, dof_params)
    _, s, _ = ctrl.step(s, state(track), params)  # compiles once
    perturbed = T.perturb_course(track, jax.random.PRNGKey(5))
    other_weights = dof.init_dof_params(jax.random.PRNGKey(99))
    for i in range(6):
        p = make_params(perturbed if i % 2 else track, other_weights if i % 3 else dof_params, config,
                        active=bool(i % 2), target=i % 3, speed=10.0 + i)
        _, s, _ = ctrl.step(s, state(track, uv=(0.3 + 0.05 * i, 0.6)), p)
    assert ctrl.num_compilations() == 1


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="pixel_model"):
        PM.PixelMPCConfig(pixel_model="flow")
    with pytest.raises(ValueError, match="t_f"):
        PM.PixelMPCConfig(t_f=-1.0)
    with pytest.raises(ValueError, match="c_pixel"):
        PM.PixelMPCConfig(c_pixel=-5.0)


def test_batched_racing_cost_equals_each_sample_on_its_own(setup):
    """The racing cost runs with the samples on the last axis; a batch must give every sample the cost it
    gets alone (a reduction over the wrong axis would mix samples), crashes and tilts included."""
    track, _ = setup
    cfg = costs.RacingCostConfig()
    params = costs.racing_params(track, jnp.linspace(0.0, 20.0, 8), 14.0, cfg)
    key_p, key_q, key_v = jax.random.split(jax.random.PRNGKey(11), 3)
    n = 64
    path = track.path_points[jnp.linspace(0, 60, n).astype(jnp.int32)]
    pos = path + 1.5 * jax.random.normal(key_p, (n, 3))
    pos = pos.at[0].set(track.gates.centre[0] + jnp.asarray([0.0, 0.0, 0.5 * float(track.gates.height[0]) + 0.1]))
    pos = pos.at[1, 2].set(-1.0)  # below the floor
    q = Q.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.6 * jax.random.normal(key_q, (n, 4)))
    v = 8.0 * jax.random.normal(key_v, (n, 3))
    X = jnp.concatenate([pos, q, v], axis=1)
    for t in (0, 5):
        batch = costs.racing_cost_batch(X, t, params, cfg)
        alone = jnp.stack([costs.racing_cost(X[i], t, params, cfg) for i in range(n)])
        np.testing.assert_allclose(batch, alone, rtol=1e-5)
        assert bool(costs.crashed(X[:2, :3].T, params, cfg).all())
        assert float(batch[0]) >= cfg.c1 * cfg.crash_value**2  # the gate frame's top bar


def test_pixel_cost_clip_and_dead_zone():
    paper = PM.PixelMPCConfig(pixel_error_clip=None, c_pixel=1.0, pixel_cost_scale=1.0)
    uv = jnp.asarray([0.9, -2.5])  # 0.4 right of the centre, 3 image heights above it
    np.testing.assert_allclose(PM.pixel_cost(uv, paper), 0.4 + 3.0, rtol=1e-6)
    clipped = PM.PixelMPCConfig(c_pixel=1.0, pixel_cost_scale=1.0)  # default clip: 1 image size per axis
    np.testing.assert_allclose(PM.pixel_cost(uv, clipped), 0.4 + 1.0, rtol=1e-6)
    dead = PM.PixelMPCConfig(c_pixel=1.0, pixel_cost_scale=1.0, pixel_deadzone=0.3)
    np.testing.assert_allclose(PM.pixel_cost(uv, dead), 0.1 + 1.0, rtol=1e-6)
    np.testing.assert_allclose(PM.pixel_cost(jnp.asarray([0.6, 0.35]), dead), 0.0, atol=1e-7)
    with pytest.raises(ValueError, match="pixel_deadzone"):
        PM.PixelMPCConfig(pixel_deadzone=0.5)
    with pytest.raises(ValueError, match="pixel_error_clip"):
        PM.PixelMPCConfig(pixel_error_clip=0.0)


def _reference_and_batched(config_of):
    """Controllers built with the former step-by-step costs ("per_step") and with the default ("batched")."""
    return (config_of(dataclasses.replace(SMALL, rollout="per_step")), config_of(SMALL))


@pytest.mark.parametrize("model", ["nominal", "dof", "projection"])
def test_batched_step_gives_the_reference_plan(setup, model):
    """For a fixed key and state, the default step (dynamics scanned, costs over the whole horizon at once) gives
    the reference step's sample costs, plan and control within float rounding, over a few ticks of a closed
    loop, with the shipped DOF weights and the AlphaPilot course."""
    track, _ = setup
    dof_params = dof.load_packaged_dof()
    u_init = Q.hover_control(Q.QuadParams())
    if model == "nominal":
        ctrls = [PM.make_nominal_mppi(c) for c in _reference_and_batched(lambda m: m)]
        params = costs.racing_params(track, jnp.linspace(0.0, 20.0, SMALL.horizon), 14.0, costs.RacingCostConfig())
        x = state(track)[:10]
    else:
        configs = _reference_and_batched(lambda m: PM.PixelMPCConfig(mppi=m, t_f=0.25, pixel_model=model))
        ctrls = [PM.make_pixelmpc(c) for c in configs]
        params = make_params(track, dof_params, configs[1])
        x = state(track)
    assert [c.config.rollout for c in ctrls] == ["per_step", "batched"]
    states = [c.init(jax.random.PRNGKey(5), u_init) for c in ctrls]
    for _ in range(3):
        (u_ref, s_ref, i_ref), (u, s, info) = (c.step(st, x, params) for c, st in zip(ctrls, states, strict=True))
        np.testing.assert_allclose(info.costs, i_ref.costs, rtol=2e-5)
        np.testing.assert_allclose(s.plan, s_ref.plan, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(u, u_ref, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(info.nominal_trajectory, i_ref.nominal_trajectory, rtol=1e-4, atol=1e-4)
        states = [s_ref, s]
        x = x.at[:10].set(Q.step(x[:10], u, SMALL.dt, Q.QuadParams()))
    assert ctrls[1].num_compilations() == 1


@pytest.mark.slow  # ~18 s of op-by-op execution; test_mppi checks jit == no-jit for the generic step
def test_batched_pixelmpc_step_is_the_same_with_and_without_jit(setup):
    ctrl, _, s, params = small_controller(*setup, seed=2)
    track = setup[0]
    u_jit, s_jit, info_jit = ctrl.step(s, state(track), params)
    with jax.disable_jit():
        u_eager, s_eager, info_eager = ctrl.step_pure(s, state(track), params)
    np.testing.assert_allclose(info_eager.costs, info_jit.costs, rtol=1e-4)
    np.testing.assert_allclose(s_eager.plan, s_jit.plan, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(u_eager, u_jit, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("cfg", [costs.RacingCostConfig(),
                                 costs.RacingCostConfig(heading_weight=0.3, progress_weight=0.0, max_tilt_deg=None)])
def test_racing_costs_over_the_horizon_equal_each_step_on_its_own(setup, cfg):
    """racing_costs (all steps and samples at once, short axes unrolled) gives racing_cost_batch's numbers at each
    step: crashes into a gate frame, the floor and a tilt included, with and without the heading and progress terms."""
    track, _ = setup
    steps = 6
    params = costs.racing_params(track, jnp.linspace(0.0, 20.0, steps), 14.0, cfg)
    key_p, key_q, key_v = jax.random.split(jax.random.PRNGKey(12), 3)
    n = 48
    path = track.path_points[jnp.linspace(0, 80, steps * n).astype(jnp.int32)]
    pos = path + 1.5 * jax.random.normal(key_p, (steps * n, 3))
    pos = pos.at[0].set(track.gates.centre[0] + jnp.asarray([0.0, 0.0, 0.5 * float(track.gates.height[0]) + 0.1]))
    pos = pos.at[1, 2].set(-1.0)  # below the floor
    q = Q.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.6 * jax.random.normal(key_q, (steps * n, 4)))
    v = 8.0 * jax.random.normal(key_v, (steps * n, 3))
    X = jnp.concatenate([pos, q, v, jnp.zeros((steps * n, 2))], axis=1).reshape(steps, n, 12)
    got = costs.racing_costs(X, jnp.arange(steps), params, cfg)
    expected = jnp.stack([costs.racing_cost_batch(X[t], t, params, cfg) for t in range(steps)])
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert float(got[0, 0]) >= cfg.c1 * cfg.crash_value**2 and float(got[0, 1]) >= cfg.c1 * cfg.crash_value**2
    # a window of later steps: steps index the params, not the rows
    np.testing.assert_allclose(costs.racing_costs(X[3:], jnp.arange(3, steps), params, cfg), expected[3:], rtol=1e-5)


def test_desired_attitude_is_the_half_yaw_quaternion_of_the_tangent():
    """q_d = [cos(psi / 2), 0, 0, sin(psi / 2)], psi = atan2(ty, tx), up to the quaternion's sign, on every side
    (behind, +-pi, the axes) and for any length; a zero tangent gives the identity."""
    angles = np.concatenate([np.linspace(-np.pi, np.pi, 721), [np.pi - 1e-6, -np.pi + 1e-6, 1e-7, -1e-7]])
    lengths = np.resize([1.0, 0.3, 7.0], angles.size)
    tangent = np.stack([lengths * np.cos(angles), lengths * np.sin(angles), np.zeros_like(angles)])
    got = np.asarray(costs.desired_attitude(jnp.asarray(tangent, jnp.float32)))
    psi = np.arctan2(tangent[1], tangent[0])
    expected = np.stack([np.cos(psi / 2), 0 * psi, 0 * psi, np.sin(psi / 2)])
    sign = np.sign(np.sum(got * expected, axis=0))
    np.testing.assert_allclose(got * sign, expected, atol=3e-7)
    np.testing.assert_allclose(np.sum(got**2, axis=0), 1.0, atol=3e-7)
    np.testing.assert_array_equal(costs.desired_attitude(jnp.zeros((3, 1))).ravel(), [1.0, 0.0, 0.0, 0.0])


def test_racing_constants_computed_once_give_the_same_params(setup):
    track, _ = setup
    cfg = costs.RacingCostConfig()
    constants = jax.jit(costs.racing_constants, static_argnames="config")(track, cfg)
    progress = jnp.linspace(3.0, 30.0, 7)
    built = jax.jit(costs.racing_params, static_argnames="config")
    fresh, reused = built(track, progress, 12.0, cfg), built(track, progress, 12.0, cfg, constants)
    for a, b in zip(jax.tree_util.tree_leaves(fresh), jax.tree_util.tree_leaves(reused), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(constants.attributes[:, 3], costs.speed_cap(track, cfg)[::cfg.path_stride])
    other = costs.racing_constants(track, dataclasses.replace(cfg, path_stride=2))
    with pytest.raises(ValueError, match="racing_constants"):
        costs.racing_params(track, progress, 12.0, cfg, other)
