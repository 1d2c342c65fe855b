"""The racing cost, Eq. (19): ``racing_costs`` (every step and sample at once) against a plain one-state
reference written here, on random states and on hand-built cases (crashes, tilts, a U-turn window, the
desired attitude on every side)."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.control import costs
from pixelmpc_jax.dynamics import quadrotor as Q
from pixelmpc_jax.world import course as course_lib


@pytest.fixture(scope="module")
def track():
    return course_lib.load_course()


# --------------------------------------------------------------------------------------------------
# A one-state reference of Eq. (19): float64, a loop over the window's segments and the gates, arctan2.
# --------------------------------------------------------------------------------------------------


def reference_crashed(p, params, config) -> bool:
    """Inside a gate frame's volume (not its opening), below the floor or outside the hall."""
    r, gates = config.vehicle_radius, params.gates
    for g in range(gates.centre.shape[0]):
        along, lateral, up = gates.rotation[g].T @ (p - gates.centre[g])  # columns [normal, lateral, up]
        half_w, half_h, border = 0.5 * gates.width[g], 0.5 * gates.height[g], gates.border[g]
        in_slab = abs(along) <= max(0.5 * gates.depth[g] + r, config.crash_slab_halfwidth)
        in_frame = abs(lateral) <= half_w + border + r and abs(up) <= half_h + border + r
        in_opening = abs(lateral) < half_w - r and abs(up) < half_h - r
        if in_slab and in_frame and not in_opening:
            return True
    return bool(np.any(p < params.hall_min + r) or np.any(p > params.hall_max - r))


def half_yaw(psi: float) -> np.ndarray:
    """The level attitude with heading psi: [cos(psi / 2), 0, 0, sin(psi / 2)]."""
    return np.array([math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2)])


def reference_racing_cost(x, t: int, params, config) -> float:
    """Eq. (19) for one state x (>= 10,) at horizon step t: c1 h^2 + c2 |q_d - q|^2 + c3 |v_d - v|^2.

    ``params`` as numpy float64 arrays (see :func:`as_numpy`).
    """
    p, q, v = x[0:3], x[3:7], x[7:10]
    path, attributes, arc = params.path_xyz[t].T, params.tangent_xyz[t].T, params.path_s[t]  # (L, 3), (L, 4), (L,)
    # the closest point of the window: the segment minimising d^2 + progress_weight (s - expected_s)^2
    best = None
    for k in range(len(path) - 1):
        a, ab = path[k], path[k + 1] - path[k]
        fraction = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
        d2 = np.sum((p - a - fraction * ab) ** 2)
        s = arc[k] + fraction * (arc[k + 1] - arc[k])
        metric = d2 + config.progress_weight * (s - params.expected_s[t]) ** 2
        if best is None or metric < best[0]:
            best = (metric, d2, attributes[k] + fraction * (attributes[k + 1] - attributes[k]))
    _, d2, attribute = best
    tangent, cap = attribute[:3] / max(np.linalg.norm(attribute[:3]), 1e-6), attribute[3]
    # h: the distance in corridor half-widths (at most 1), or crash_value on a crash or a tilt past max_tilt_deg
    crash = reference_crashed(p, params, config)
    cos_tilt = 1.0 - 2.0 * (q[1] ** 2 + q[2] ** 2)
    if config.max_tilt_deg is not None and cos_tilt < math.cos(math.radians(config.max_tilt_deg)):
        crash = True
    h = config.crash_value if crash else min(math.sqrt(d2) / config.corridor_halfwidth, 1.0)
    # q_d: level, facing along the tangent; q and -q are one attitude
    def distance(q_d):
        return min(np.sum((q_d - q) ** 2), np.sum((q_d + q) ** 2))

    attitude = distance(half_yaw(math.atan2(tangent[1], tangent[0])))
    if config.heading_weight < 1.0:
        own_heading = math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
        attitude = config.heading_weight * attitude + (1 - config.heading_weight) * distance(half_yaw(own_heading))
    velocity = np.sum((min(params.target_speed, cap) * tangent - v) ** 2)
    return config.c1 * h**2 + config.c2 * attitude + config.c3 * velocity


def as_numpy(params):
    return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params)


def reference_costs(X, steps, params, config) -> np.ndarray:
    """(T, N) the reference, state by state."""
    X, ref = np.asarray(X, np.float64), as_numpy(params)
    return np.asarray([[reference_racing_cost(x, int(t), ref, config) for x in row] for row, t in zip(X, steps,
                                                                                                       strict=True)])


def quat_about(axis, angle: float) -> jnp.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return jnp.asarray(np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis]), jnp.float32)


# --------------------------------------------------------------------------------------------------
# racing_costs against the reference.
# --------------------------------------------------------------------------------------------------


def random_states(track, steps: int, n: int, seed: int) -> jnp.ndarray:
    """(steps, n, 12) states near the course's path, random attitudes and velocities, and in row 0: a state in
    gate 0's top bar, one below the floor, one beyond a wall, one tilted 80 deg (past max_tilt_deg), one 70 deg."""
    key_p, key_q, key_v = jax.random.split(jax.random.PRNGKey(seed), 3)
    path = track.path_points[jnp.linspace(0, 80, steps * n).astype(jnp.int32)]
    pos = path + 1.5 * jax.random.normal(key_p, (steps * n, 3))
    q = Q.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.6 * jax.random.normal(key_q, (steps * n, 4)))
    v = 8.0 * jax.random.normal(key_v, (steps * n, 3))
    gate = track.gate(0)
    pos = pos.at[0].set(gate.centre + gate.up * (0.5 * gate.height + 0.1))
    pos = pos.at[1, 2].set(-1.0)
    pos = pos.at[2, 1].set(track.hall_max[1] + 0.5)
    q = q.at[3].set(quat_about([1.0, 0.3, 0.0], math.radians(80.0))).at[4].set(quat_about([0.0, 1.0, 0.0],
                                                                                             math.radians(70.0)))
    pos = pos.at[3:5].set(path[3:5])
    return jnp.concatenate([pos, q, v, jnp.zeros((steps * n, 2))], axis=1).reshape(steps, n, 12)


@pytest.mark.parametrize("config", [
    costs.RacingCostConfig(),
    costs.RacingCostConfig(heading_weight=0.3, progress_weight=0.0, max_tilt_deg=None),
    costs.RacingCostConfig(heading_weight=0.0, max_lateral_acc=None, path_stride=2),
])
def test_racing_costs_equal_the_one_state_reference(track, config):
    """Every step's samples against their own window, every sample on its own (a reduction over the wrong axis
    would mix samples): crashes into a gate frame, the floor, a wall and a tilt included."""
    steps, n = 6, 40
    params = costs.racing_params(track, jnp.linspace(0.0, 20.0, steps), 14.0, config)
    X = random_states(track, steps, n, seed=12)
    got = np.asarray(costs.racing_costs(X, jnp.arange(steps), params, config))
    expected = reference_costs(X, range(steps), params, config)
    np.testing.assert_allclose(got, expected, rtol=2e-5, atol=1e-3)
    crash = config.c1 * config.crash_value**2
    assert got.shape == (steps, n) and np.all(got[0, :3] >= crash)  # the frame, the floor, the wall
    if config.max_tilt_deg is not None:
        assert got[0, 3] >= crash and got[0, 4] < crash  # 80 deg is past 75, 70 deg is not
    assert np.sum(got < crash) > n  # most states fly
    # a window of later steps: the steps index the params, not the rows
    later = costs.racing_costs(X[3:], jnp.arange(3, steps), params, config)
    np.testing.assert_allclose(later, got[3:], rtol=1e-6)


def test_racing_costs_by_hand_on_a_straight_course():
    track = course_lib.straight_course(num_gates=3, spacing=15.0, first_gate_x=12.0)
    cfg = costs.RacingCostConfig()
    params = costs.racing_params(track, jnp.asarray([0.0, 12.0]), 10.0, cfg)  # two horizon steps

    def cost(x, t=0):
        return float(costs.racing_costs(x[None, None], jnp.asarray([t]), params, cfg)[0, 0])

    on_path = track.start.at[7].set(10.0)  # at the start, on the path, level, facing +x, at speed
    assert cost(on_path) == pytest.approx(0.0, abs=1e-2)
    assert cost(on_path.at[1].add(1.0)) == pytest.approx(400 * 0.5**2, rel=1e-3)  # 1 m off: h = 0.5
    assert cost(on_path.at[1].add(3.0)) == pytest.approx(400 * 1.0, rel=1e-3)  # beyond the corridor: h = 1
    assert cost(track.start) == pytest.approx(8.0 * 10.0**2, rel=1e-4)  # at rest: c3 |v_d|^2
    gate = track.gate(0)
    assert cost(on_path.at[:3].set(gate.centre + gate.up * (0.5 * gate.height + 0.15)), 1) > 400 * 1000.0**2 * 0.99
    assert cost(on_path.at[:3].set(gate.centre), 1) < 1e3  # the opening is free
    assert cost(on_path.at[2].set(-0.5)) > 400 * 1000.0**2 * 0.99  # below the floor


def u_turn_params(track, config, expected_s: float, target_speed: float = 5.0):
    """Racing params of one step whose window doubles back: 6 m along +x, a half circle of radius 1 m, and 6 m back
    along -x 2 m beside the first leg, 8 m up (clear of the course's gates)."""
    leg = np.linspace(0.0, 6.0, 13)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 9)[1:-1]
    points = np.concatenate([np.stack([leg, 0 * leg, 8 + 0 * leg], 1),
                             np.stack([6 + np.cos(angles), 1 + np.sin(angles), 8 + 0 * angles], 1),
                             np.stack([leg[::-1], 2 + 0 * leg, 8 + 0 * leg], 1)])
    tangents = np.concatenate([np.tile([1.0, 0.0, 0.0], (13, 1)),
                               np.stack([-np.sin(angles), np.cos(angles), 0 * angles], 1),
                               np.tile([-1.0, 0.0, 0.0], (13, 1))])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    attributes = np.concatenate([tangents, np.full((len(points), 1), 100.0)], axis=1)  # no speed cap
    params = costs.racing_params(track, jnp.zeros((1,)), target_speed, config)
    f32 = lambda a: jnp.asarray(a, jnp.float32)[None]  # noqa: E731
    return params.replace(path_xyz=f32(points.T), path_s=f32(arc), tangent_xyz=f32(attributes.T),
                          expected_s=f32([expected_s])[0]), arc


def test_u_turn_window_charges_the_leg_of_the_expected_progress(track):
    """Where the window holds both legs of a U-turn, the state is compared with the leg the previous plan expects
    it on (the progress term), not merely the nearer one; with progress_weight 0 the nearer leg wins."""
    config = costs.RacingCostConfig()
    level = jnp.asarray([1.0, 0.0, 0.0, 0.0])
    x = jnp.concatenate([jnp.asarray([3.0, 0.9, 8.0]), level, jnp.asarray([5.0, 0.0, 0.0])])  # 0.9 m from leg 1
    out_params, arc = u_turn_params(track, config, expected_s=3.0)
    back_s = float(arc[-1] - 3.0)  # the back leg at x = 3
    back_params, _ = u_turn_params(track, config, expected_s=back_s)

    def cost(params, cfg):
        return float(costs.racing_costs(x[None, None], jnp.zeros((1,), jnp.int32), params, cfg)[0, 0])

    h_out, h_back = 0.9 / 2.0, 1.1 / 2.0
    assert cost(out_params, config) == pytest.approx(400 * h_out**2, rel=1e-4)  # along leg 1 at the target speed
    # on the way back: facing and flying the wrong way, c2 |q_d - q|^2 = 250 * 2 and c3 |v_d - v|^2 = 8 * 10^2
    assert cost(back_params, config) == pytest.approx(400 * h_back**2 + 250 * 2 + 8 * 100, rel=1e-4)
    nearest = dataclasses.replace(config, progress_weight=0.0)
    assert cost(back_params, nearest) == pytest.approx(400 * h_out**2, rel=1e-4)
    for params, cfg in ((out_params, config), (back_params, config), (back_params, nearest)):
        expected = reference_racing_cost(np.asarray(x, np.float64), 0, as_numpy(params), cfg)
        assert cost(params, cfg) == pytest.approx(expected, rel=1e-5)


def test_desired_attitude_faces_along_the_tangent_on_every_side(track):
    """q_d = [cos(psi / 2), 0, 0, sin(psi / 2)], psi = atan2(ty, tx), up to the quaternion's sign: a level vehicle
    yawed to psi pays no attitude cost and one yawed to psi + pi the most (c2 * 2), for any heading (behind, +-pi,
    the axes) and tangent length; a zero tangent asks for the identity."""
    config = costs.RacingCostConfig(c1=0.0, c2=1.0, c3=0.0, max_tilt_deg=None)
    angles = np.concatenate([np.linspace(-np.pi, np.pi, 361), [np.pi - 1e-6, -np.pi + 1e-6, 1e-7, -1e-7]])
    lengths = np.resize([1.0, 0.3, 7.0], angles.size)
    direction = np.stack([np.cos(angles), np.sin(angles), 0 * angles], 1)  # (T, 3)
    centre = np.asarray([0.0, 0.0, 8.0])
    path = np.stack([centre - direction, centre + direction], axis=2)  # (T, 3, 2): one segment through the centre
    tangent = np.concatenate([direction * lengths[:, None], np.full((angles.size, 1), 10.0)], axis=1)  # (T, 4)
    tangent = np.concatenate([tangent, np.zeros((1, 4))])  # and a zero tangent
    path = np.concatenate([path, path[:1]])
    steps = angles.size + 1
    params = costs.racing_params(track, jnp.zeros((steps,)), 0.0, config).replace(
        path_xyz=jnp.asarray(path, jnp.float32), tangent_xyz=jnp.asarray(np.repeat(tangent[:, :, None], 2, 2),
                                                                         jnp.float32),
        path_s=jnp.tile(jnp.asarray([0.0, 2.0]), (steps, 1)), expected_s=jnp.ones((steps,)))
    yaw = np.concatenate([angles, [0.0]])
    q_along = np.stack([half_yaw(psi) for psi in yaw])
    q_against = np.stack([half_yaw(psi + np.pi) for psi in yaw])
    rest = np.zeros((steps, 3))
    X = np.stack([np.concatenate([np.tile(centre, (steps, 1)), q, rest], 1) for q in (q_along, q_against)], 1)
    got = np.asarray(costs.racing_costs(jnp.asarray(X, jnp.float32), jnp.arange(steps), params, config))
    np.testing.assert_allclose(got[:, 0], 0.0, atol=1e-6)
    np.testing.assert_allclose(got[:, 1], 2.0, atol=1e-6)
