"""PixelMPC: one compiled step over robot + pixel; the t_f prefix equals the full-horizon computation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as PM
from pixelmpc_jax.control.mppi import make_mppi
from pixelmpc_jax.control.rollout import rollout_states
from pixelmpc_jax.devices import compile_controller
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.dynamics import quadrotor as Q
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import course as course_lib

SMALL = PM.paper_mppi_config(num_samples=64, horizon=24)


@pytest.fixture(scope="module")
def setup():
    track = course_lib.load_course()
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


def one_state_racing(X, t, racing_params, config):
    """Eq. (19) of one state at horizon step t: the racing cost of a batch of one."""
    return costs.racing_costs(X[None, None, :10], jnp.reshape(t, (1,)), racing_params, config)[0, 0]


@pytest.mark.parametrize("model", ["dof", "projection"])
def test_prefix_equals_full_horizon_computation(setup, model):
    """The step (pixel model over the first n_f steps only, the costs over all (T, N) states at once) equals a
    generic MPPI with one-sample costs whose pixel model runs over the whole horizon and whose pixel cost is masked
    after n_f steps, while the target is detected and ahead."""
    track, dof_params = setup
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.25, c_pixel=9e6, pixel_model=model)  # n_f = 10 of 24 steps
    assert config.pixel_steps == 10
    fast = compile_controller(PM.make_pixelmpc(config))
    dt = SMALL.dt

    def full_dynamics(X, u, p):
        x_next = Q.step(X[:10], u, dt, Q.QuadParams())
        if model == "dof":
            uv = X[10:] + dt * dof.pixel_velocity(p.dof, X[3:7], X[10:], u)
        else:
            uv, _, in_front = C.project(p.target_centre, x_next, p.camera)
            uv = jnp.where(in_front, uv, PM.behind_camera_pixel(uv.dtype))
        return jnp.concatenate([x_next, uv])

    def full_cost(X, u, t, p):
        racing = one_state_racing(X, t, p.racing, config.racing)
        ahead = jnp.dot(X[:3] - p.target_centre, p.target_normal) < 0.0
        pixel = jnp.where((t < config.pixel_steps) & ahead, PM.pixel_cost(X[10:], config), 0.0)
        return racing + p.target_active * pixel

    full = compile_controller(make_mppi(SMALL, full_dynamics, full_cost))
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
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.5, c_pixel=9e6)
    ctrl = compile_controller(PM.make_pixelmpc(config))
    key = jax.random.PRNGKey(0)
    u_init = Q.hover_control(Q.QuadParams())
    off_centre = state(track, uv=(0.9, 0.1))
    _, _, on = ctrl.step(ctrl.init(key, u_init), off_centre, make_params(track, dof_params, config, active=True))
    _, _, off = ctrl.step(ctrl.init(key, u_init), off_centre, make_params(track, dof_params, config, active=False))
    nominal = compile_controller(PM.make_pixelmpc(PM.ControllerConfig(mppi=SMALL, t_f=0.5, c_pixel=0.0)))
    _, _, zero = nominal.step(nominal.init(key, u_init), off_centre, make_params(track, dof_params, config))
    np.testing.assert_allclose(off.costs, zero.costs, rtol=1e-6)
    # L1 of (0.9, 0.1) from the centre is 0.8: at least n_f steps of a large pixel cost in every sample
    assert float(jnp.min(on.costs - off.costs)) > 0.5 * 20 * 9e6 * config.pixel_cost_scale * 0.8


def test_projection_model_predicts_the_projected_target(setup):
    track, dof_params = setup
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.5, pixel_model="projection")
    ctrl = compile_controller(PM.make_pixelmpc(config))
    params = make_params(track, dof_params, config)
    _, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(0), Q.hover_control(Q.QuadParams())), state(track), params)
    traj = info.nominal_trajectory
    for t in (1, 5, config.pixel_steps):
        uv, _, in_front = C.project(track.gates.centre[0], traj[t, :10], C.default_camera())
        assert bool(in_front)
        np.testing.assert_allclose(traj[t, 10:], uv, atol=1e-6)


def small_controller(track, dof_params, seed=0):
    """A PixelMPC controller at the small size with t_f = 0.25 s: (ctrl, config, its first state, params)."""
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.25)
    ctrl = compile_controller(PM.make_pixelmpc(config))
    s = ctrl.init(jax.random.PRNGKey(seed), Q.hover_control(Q.QuadParams()))
    return ctrl, config, s, make_params(track, dof_params, config)


def test_no_recompilation_for_new_pixel_gates_or_weights(setup):
    track, dof_params = setup
    ctrl, config, s, params = small_controller(track, dof_params)
    _, s, _ = ctrl.step(s, state(track), params)  # compiles once
    perturbed = course_lib.perturb_course(track, jax.random.PRNGKey(5))
    other_weights = dof.init_dof_params(jax.random.PRNGKey(99))
    for i in range(6):
        p = make_params(perturbed if i % 2 else track, other_weights if i % 3 else dof_params, config,
                        active=bool(i % 2), target=i % 3, speed=10.0 + i)
        _, s, _ = ctrl.step(s, state(track, uv=(0.3 + 0.05 * i, 0.6)), p)
    assert ctrl.num_compilations() == 1


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="pixel_model"):
        PM.ControllerConfig(pixel_model="flow")
    with pytest.raises(ValueError, match="t_f"):
        PM.ControllerConfig(t_f=-1.0)
    with pytest.raises(ValueError, match="c_pixel"):
        PM.ControllerConfig(c_pixel=-5.0)


def test_pixel_cost_clip_and_dead_zone():
    paper = PM.ControllerConfig(pixel_error_clip=None, c_pixel=1.0, pixel_cost_scale=1.0)
    uv = jnp.asarray([0.9, -2.5])  # 0.4 right of the centre, 3 image heights above it
    np.testing.assert_allclose(PM.pixel_cost(uv, paper), 0.4 + 3.0, rtol=1e-6)
    clipped = PM.ControllerConfig(c_pixel=1.0, pixel_cost_scale=1.0)  # default clip: 1 image size per axis
    np.testing.assert_allclose(PM.pixel_cost(uv, clipped), 0.4 + 1.0, rtol=1e-6)
    dead = PM.ControllerConfig(c_pixel=1.0, pixel_cost_scale=1.0, pixel_deadzone=0.3)
    np.testing.assert_allclose(PM.pixel_cost(uv, dead), 0.1 + 1.0, rtol=1e-6)
    np.testing.assert_allclose(PM.pixel_cost(jnp.asarray([0.6, 0.35]), dead), 0.0, atol=1e-7)
    with pytest.raises(ValueError, match="pixel_deadzone"):
        PM.ControllerConfig(pixel_deadzone=0.5)
    with pytest.raises(ValueError, match="pixel_error_clip"):
        PM.ControllerConfig(pixel_error_clip=0.0)


def test_nominal_step_equals_a_one_sample_racing_cost(setup):
    """Nominal MPPI (the racing cost over all (T, N) predicted states at once) takes the steps of a generic MPPI
    whose running cost is the racing cost of one state: the same sample costs, plan and control within float
    rounding over a few ticks of a closed loop on the AlphaPilot course, compiled once."""
    track, _ = setup
    cfg = costs.RacingCostConfig()
    nominal = compile_controller(PM.make_nominal_mppi(SMALL, cfg))
    reference = compile_controller(make_mppi(SMALL, lambda x, u, p: Q.step(x, u, SMALL.dt, Q.QuadParams()),
                                             lambda x, u, t, p: one_state_racing(x, t, p, cfg)))
    params = costs.racing_params(track, jnp.linspace(0.0, 20.0, SMALL.horizon), 14.0, cfg)
    x = state(track)[:10]
    u_init = Q.hover_control(Q.QuadParams())
    s_ref, s = reference.init(jax.random.PRNGKey(5), u_init), nominal.init(jax.random.PRNGKey(5), u_init)
    for _ in range(3):
        u_ref, s_ref, i_ref = reference.step(s_ref, x, params)
        u, s, info = nominal.step(s, x, params)
        np.testing.assert_allclose(info.costs, i_ref.costs, rtol=2e-5)
        np.testing.assert_allclose(s.plan, s_ref.plan, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(u, u_ref, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(info.nominal_trajectory, i_ref.nominal_trajectory, rtol=1e-4, atol=1e-4)
        x = Q.step(x, u, SMALL.dt, Q.QuadParams())
    assert nominal.num_compilations() == 1


@pytest.mark.slow  # ~18 s of op-by-op execution; test_mppi checks jit == no-jit for the generic step
def test_batched_pixelmpc_step_is_the_same_with_and_without_jit(setup):
    ctrl, config, s, params = small_controller(*setup, seed=2)
    track = setup[0]
    u_jit, s_jit, info_jit = ctrl.step(s, state(track), params)
    with jax.disable_jit():
        u_eager, s_eager, info_eager = PM.make_pixelmpc(config).step(s, state(track), params)
    np.testing.assert_allclose(info_eager.costs, info_jit.costs, rtol=1e-4)
    np.testing.assert_allclose(s_eager.plan, s_jit.plan, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(u_eager, u_jit, rtol=1e-4, atol=1e-4)


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


def test_the_vdof_model_carries_the_box_size_and_its_limit_stops_the_pixel_cost(setup):
    """PixelMPC over [x; u, v, s]: the step is finite and predicts the 13-state; with the box size past
    ``box_size_limit`` (a hovering drone: s stays put) the pixel cost adds nothing to any sample."""
    from pixelmpc_jax.dynamics import vdof

    track, _ = setup
    params_vdof = vdof.load_packaged_vdof()
    x = track.start
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.25, c_pixel=3e7, pixel_cost="border", pixel_model="vdof",
                               box_size_limit=0.5)
    costs_of = {}
    controllers = {c_pixel: compile_controller(PM.make_pixelmpc(dataclasses.replace(config, c_pixel=c_pixel)))
                   for c_pixel in (3e7, 0.0)}
    params = make_params(track, params_vdof, config)
    for name, c_pixel, s in (("near", 3e7, 5.0), ("near_free", 0.0, 5.0), ("far", 3e7, 0.2), ("far_free", 0.0, 0.2)):
        ctrl = controllers[c_pixel]
        X0 = jnp.concatenate([x, jnp.asarray([0.95, 0.05, s])])  # the gate at the image's corner: costly
        u, _, info = ctrl.step(ctrl.init(jax.random.PRNGKey(0), Q.hover_control(Q.QuadParams())), X0, params)
        assert np.all(np.isfinite(np.asarray(u))) and info.nominal_trajectory.shape == (SMALL.horizon + 1, 13)
        costs_of[name] = np.asarray(info.costs)
    np.testing.assert_allclose(costs_of["near"], costs_of["near_free"], rtol=1e-6)  # past the limit: no pixel cost
    assert np.all(costs_of["far"] > costs_of["far_free"])  # below it the corner pixel costs every sample
    assert PM.ControllerConfig(box_size_limit=0.5) == PM.ControllerConfig()  # no box size: the limit flies nothing


def _before_gate_0(track):
    """1 m before gate 0, facing it at 8 m/s."""
    centre, normal = track.gates.centre[0], track.gates.normal[0]
    x0 = Q.hover_state(tuple(np.asarray(centre - 1.0 * normal)), yaw=float(jnp.arctan2(normal[1], normal[0])))
    return x0.at[7:].set(8.0 * normal)


def _project(centre, x):
    """The pixel of ``centre`` seen from ``x``, far off the image behind the camera (as the projection model)."""
    uv, _, in_front = C.project(centre, x, C.default_camera())
    return jnp.where(in_front, uv, PM.behind_camera_pixel(uv.dtype))


def _look_ahead_reference(config, plan_passes=None):
    """A generic MPPI with one-sample costs over the projection look-ahead's state [x; target uv; next uv]: the racing
    cost, the target's pixel cost before its plane and ``look_ahead`` times the next gate's past it, or from horizon
    step ``plan_passes`` on (None: never) where the sample has not passed yet."""
    dt = config.mppi.dt

    def full_dynamics(X, u, p):
        x_next = Q.step(X[:10], u, dt, Q.QuadParams())
        return jnp.concatenate([x_next, _project(p.target_centre, x_next), _project(p.next_centre, x_next)])

    def full_cost(X, u, t, p):
        racing = one_state_racing(X, t, p.racing, config.racing)
        in_prefix = t < config.pixel_steps
        ahead = jnp.dot(X[:3] - p.target_centre, p.target_normal) < 0.0
        before_next = jnp.dot(X[:3] - p.next_centre, p.next_normal) < 0.0
        charged = ~ahead if plan_passes is None else ~ahead | (t >= plan_passes)
        target = jnp.where(in_prefix & ahead & p.target_active, PM.pixel_cost(X[10:12], config), 0.0)
        following = jnp.where(in_prefix & charged & before_next & p.next_active, PM.pixel_cost(X[12:14], config), 0.0)
        return racing + target + config.look_ahead * following

    return compile_controller(make_mppi(config.mppi, full_dynamics, full_cost))


def test_the_look_ahead_charges_the_next_gate_past_the_target_as_a_full_horizon_reference_does(setup):
    """With ``look_ahead`` the state carries the next gate's pixel too, and each predicted state past the target's
    plane (and before the next gate's) is charged ``look_ahead`` times the next gate's pixel cost: the step equals a
    generic MPPI with one-sample costs doing exactly that, from 1 m before gate 0 at 8 m/s (the samples pass it
    within the 0.25 s the pixel is costed)."""
    track, dof_params = setup
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.25, c_pixel=9e6, pixel_model="projection", look_ahead=0.5)
    fast = compile_controller(PM.make_pixelmpc(config))
    centre, x0 = track.gates.centre[0], _before_gate_0(track)
    full = _look_ahead_reference(config)
    params = make_params(track, dof_params, config).replace(
        next_active=jnp.asarray(True), next_centre=track.gates.centre[1], next_normal=track.gates.normal[1])
    X0 = jnp.concatenate([x0, _project(centre, x0), _project(track.gates.centre[1], x0)])
    key = jax.random.PRNGKey(3)
    u_init = Q.hover_control(Q.QuadParams())
    _, _, info_a = fast.step(fast.init(key, u_init), X0, params)
    _, _, info_b = full.step(full.init(key, u_init), X0, params)
    np.testing.assert_allclose(info_a.costs, info_b.costs, rtol=2e-5)
    traj = info_a.nominal_trajectory
    assert traj.shape[-1] == 14
    np.testing.assert_allclose(traj[5, 12:], _project(track.gates.centre[1], traj[5, :10]), atol=1e-6)
    # the term charges something: without the next gate (none after the target) the costs are lower
    _, _, alone = fast.step(fast.init(key, u_init), X0, params.replace(next_active=jnp.asarray(False)))
    assert float(jnp.max(info_a.costs - alone.costs)) > 0.0
    assert float(jnp.min(info_a.costs - alone.costs)) >= 0.0
    with pytest.raises(ValueError, match=r"look_ahead must be a finite number in \[0, 1000\]"):
        PM.ControllerConfig(look_ahead=-1.0)


def test_the_look_ahead_from_the_plan_charges_a_sample_that_passes_later_from_the_plans_passage(setup):
    """``look_ahead_from="plan"``: a predicted state is charged the next gate's pixel cost once its sample has passed
    the target's plane or once the plan (the zero-noise sample) has, so a sample that passes later than the plan, or
    not at all, is charged from the plan's passage: the step equals a generic MPPI with one-sample costs that charge
    from the step the plan's own rollout passes, the plan itself costs what it costs charged from its own passage, and
    no sample costs less than charged from its own passage only."""
    track, dof_params = setup
    wide = dataclasses.replace(SMALL, noise_sigma=(1.5, 1.5, 1.5, 8.0))  # samples that part from the plan's passage
    plane = PM.ControllerConfig(mppi=wide, t_f=0.5, c_pixel=9e6, pixel_model="projection", look_ahead=0.5)
    config = dataclasses.replace(plane, look_ahead_from="plan")
    dt = SMALL.dt
    centre, normal = track.gates.centre[0], track.gates.normal[0]
    x0 = Q.hover_state(tuple(np.asarray(centre - 0.8 * normal)), yaw=float(jnp.arctan2(normal[1], normal[0])))
    x0 = x0.at[7:].set(2.0 * normal)  # the plan passes the plane about 0.4 s on, inside the 0.5 s pixel horizon
    u_init = Q.hover_control(Q.QuadParams())
    plan = jnp.tile(u_init, (wide.horizon, 1))  # the warm start: the hover command held
    plan_states = rollout_states(lambda x, u, p: Q.step(x, u, dt, Q.QuadParams()), x0, plan, None)[1:]  # x_1 .. x_T
    plan_past = np.asarray(jnp.dot(plan_states[:, :3] - centre, normal) >= 0.0)
    plan_passes = int(np.argmax(plan_past))
    assert plan_past.any() and 0 < plan_passes < config.pixel_steps

    full = _look_ahead_reference(config, plan_passes)
    following = track.gates.centre[1] + jnp.asarray([0.0, 4.0, 1.0])  # off the image's centre: its L1 cost is not 0
    params = make_params(track, dof_params, config).replace(
        next_active=jnp.asarray(True), next_centre=following, next_normal=track.gates.normal[1])
    X0 = jnp.concatenate([x0, _project(centre, x0), _project(following, x0)])
    key = jax.random.PRNGKey(3)
    runs = {}
    for name, controller in (("plan", compile_controller(PM.make_pixelmpc(config))),
                             ("plane", compile_controller(PM.make_pixelmpc(plane))), ("reference", full)):
        runs[name] = controller.step(controller.init(key, u_init), X0, params)[2].costs
    np.testing.assert_allclose(runs["plan"], runs["reference"], rtol=2e-5)
    np.testing.assert_allclose(runs["plan"][0], runs["plane"][0], rtol=1e-6)  # the plan: charged from its passage
    extra = np.asarray(runs["plan"] - runs["plane"])
    assert extra.min() >= -1e-3 * float(jnp.max(runs["plane"])) and extra.max() > 0.0
    with pytest.raises(ValueError, match="look_ahead_from must be one of"):
        PM.ControllerConfig(look_ahead_from="target")
    with pytest.raises(ValueError, match="nominal_sample"):
        PM.ControllerConfig(mppi=dataclasses.replace(wide, nominal_sample=False), look_ahead_from="plan")


def test_the_projection_look_ahead_predicts_the_next_gate_from_the_map_and_the_target_by_the_pixel_model(setup):
    """``look_ahead_model="projection"`` with a learned pixel model: the target's pixel follows the DOF, the next
    gate's is its centre projected through each predicted pose; the step equals a generic MPPI with one-sample costs
    doing exactly that, from 1 m before gate 0 at 8 m/s."""
    track, dof_params = setup
    config = PM.ControllerConfig(mppi=SMALL, t_f=0.25, c_pixel=9e6, pixel_model="dof", look_ahead=0.5,
                                 look_ahead_model="projection")
    assert config.next_pixel_dim == 2
    fast = compile_controller(PM.make_pixelmpc(config))
    dt = SMALL.dt
    x0 = _before_gate_0(track)

    def full_dynamics(X, u, p):
        x_next = Q.step(X[:10], u, dt, Q.QuadParams())
        uv = X[10:12] + dt * dof.pixel_velocity(p.dof, X[3:7], X[10:12], u)
        return jnp.concatenate([x_next, uv, _project(p.next_centre, x_next)])

    prefix_steps = config.pixel_steps
    params = make_params(track, dof_params, config).replace(
        next_active=jnp.asarray(True), next_centre=track.gates.centre[1], next_normal=track.gates.normal[1])
    X0 = jnp.concatenate([x0, jnp.asarray([0.52, 0.47]), _project(track.gates.centre[1], x0)])
    key = jax.random.PRNGKey(3)
    u_init = Q.hover_control(Q.QuadParams())
    u0, stepped, info_a = fast.step(fast.init(key, u_init), X0, params)
    controls = jnp.concatenate([u0[None], stepped.plan[:-1]])  # the updated plan (the state holds it shifted)
    traj = np.asarray(info_a.nominal_trajectory)
    assert traj.shape[-1] == 14
    for t in range(prefix_steps):  # the nominal prediction under the plan, state by state, as the reference makes it
        np.testing.assert_allclose(traj[t + 1, 10:], full_dynamics(traj[t], controls[t], params)[10:],
                                   atol=1e-5)
    np.testing.assert_allclose(traj[prefix_steps + 3, 10:], traj[prefix_steps, 10:])  # carried after n_f
    # the same config with the DOF predicting the next gate too moves it otherwise
    own = compile_controller(PM.make_pixelmpc(dataclasses.replace(config, look_ahead_model="own")))
    _, _, info_own = own.step(own.init(key, u_init), X0, params)
    assert np.abs(np.asarray(info_own.nominal_trajectory)[prefix_steps, 12:] - traj[prefix_steps, 12:]).max() > 1e-3
    with pytest.raises(ValueError, match="look_ahead_model must be one of"):
        PM.ControllerConfig(look_ahead_model="map")
