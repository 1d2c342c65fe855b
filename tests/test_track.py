"""Course loading, gate geometry, passage/collision and the desired path."""

import copy
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import track as T


@pytest.fixture(scope="module")
def course_data():
    return json.loads(T.COURSE_FILE.read_text())


@pytest.fixture(scope="module")
def course():
    return T.load_course()


@pytest.fixture(scope="module")
def straight():
    return T.straight_course(num_gates=5, spacing=20.0, height=3.0, first_gate_x=20.0)


# Shared compiled wrappers (each compiles once per module); eager no-jit runs are compared against them.
passed_j = jax.jit(T.gate_passed)
collide_j = jax.jit(T.collision)
query_j = jax.jit(T.path_query)


def _gate(track, name):
    return track.gate(track.names.index(name))


# --------------------------------------------------------------------------------------------------
# Loading.
# --------------------------------------------------------------------------------------------------


def test_gates_in_race_order(course, course_data):
    assert course.names == tuple(course_data["race"]["gate_order"])
    assert course.num_gates == 11
    assert course.gates.centre.shape == (11, 3) and course.gates.rotation.shape == (11, 3, 3)


def test_centres_are_corner_means_and_corners_reproduce_the_file(course, course_data):
    for k, name in enumerate(course.names):
        corners = np.asarray(course_data["gates"][name]["corners"])
        np.testing.assert_allclose(course.gates.centre[k], corners.mean(axis=0), atol=1e-4)
        ours = np.asarray(course.gate(k).corners())  # (4, 3)
        # Every file corner is one of ours (the file's order is inconsistent, ours is fixed).
        dist = np.linalg.norm(corners[:, None, :] - ours[None, :, :], axis=-1)
        assert dist.min(axis=1).max() < 2e-3, name
        assert sorted(dist.argmin(axis=1)) == [0, 1, 2, 3], name


def test_rotation_frames(course):
    R = np.asarray(course.gates.rotation)
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-5)
    normal, lateral, up = R[..., 0], R[..., 1], R[..., 2]
    np.testing.assert_allclose(lateral, np.cross(up, normal), atol=1e-5)
    assert (up[:, 2] > 0.99).all()  # the AlphaPilot gates stand upright


def test_corner_order_top_left_first(course):
    g = _gate(course, "Gate10")  # crossed along +y: lateral (left) is -x
    tl, tr, br, bl = np.asarray(g.corners())
    assert tl[2] > bl[2] and tr[2] > br[2]  # top above bottom
    assert tl[0] < tr[0] and bl[0] < br[0]  # looking along +y, right is +x
    np.testing.assert_allclose(np.asarray(g.outer_corners())[0] - tl, [-0.3, 0.0, 0.3], atol=1e-4)


def test_normals_point_along_the_direction_of_travel(course):
    c = np.asarray(course.gates.centre)
    n = np.asarray(course.gates.normal)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6)
    previous = np.concatenate([np.asarray(course.start[:3])[None], c[:-1]])
    following = np.concatenate([c[1:], c[-1:]])
    assert (np.sum(n * (following - previous), axis=-1) > 0).all()
    np.testing.assert_allclose(n[0], [0.0, 1.0, 0.0], atol=1e-4)  # Gate10 straight ahead of the start (+y)
    np.testing.assert_allclose(n[2], [0.0, -1.0, 0.0], atol=1e-4)  # Gate2 is crossed going back (-y)


def test_gate_sizes(course):
    g = _gate(course, "Gate10")
    assert float(g.width) == pytest.approx(1.8, abs=1e-3)
    assert float(g.height) == pytest.approx(1.846, abs=1e-3)
    assert float(g.border) == pytest.approx(0.3)
    assert float(g.depth) == pytest.approx(T.GATE_DEPTH)
    big = _gate(course, "Gate21")  # the diagonal one: 2.128 * sqrt(2) wide
    assert float(big.width) == pytest.approx(math.hypot(17.81402 - 15.68563, 40.63416 - 38.50578), abs=1e-3)
    assert float(big.height) == pytest.approx(8.376249 - 5.14875, abs=1e-3)
    assert ((course.gates.width > 1.5) & (course.gates.width < 3.5)).all()


def test_start_pose(course):
    np.testing.assert_allclose(course.start[:3], [18.0, -23.0, 5.3], atol=1e-6)
    np.testing.assert_allclose(course.start[3:7], [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)], atol=1e-6)
    heading = quadrotor.rotation_matrix(course.start[3:7])[:, 0]
    np.testing.assert_allclose(heading, [0.0, 1.0, 0.0], atol=1e-5)  # yaw +90 deg: facing +y
    np.testing.assert_allclose(course.start[7:], 0.0)


def test_hall_encloses_the_course_with_margin(course):
    corners = np.asarray(course.gates.outer_corners()).reshape(-1, 3)
    pts = np.concatenate([corners, np.asarray(course.start[:3])[None], np.asarray(course.path_points)])
    lo, hi = np.asarray(course.hall_min), np.asarray(course.hall_max)
    assert lo[2] == 0.0 and 12.0 <= hi[2] <= 20.0
    assert (pts[:, :2] - lo[:2] >= T.HALL_MARGIN - 1e-3).all()
    assert (hi[:2] - pts[:, :2] >= T.HALL_MARGIN - 1e-3).all()


# --------------------------------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------------------------------


def _write(tmp_path, data):
    path = tmp_path / "course.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["gates"]["Gate10"]["corners"].pop(), r"gate 'Gate10' corners: expected 4 corners.*3"),
        (lambda d: d["gates"]["Gate2"]["corners"][1].pop(), r"gate 'Gate2' corners\[1\]: expected 3"),
        (lambda d: d.update(speed_limit=3), r"unknown field\(s\) \['speed_limit'\]"),
        (lambda d: d["race"].update(laps=2), r"race: unknown field\(s\) \['laps'\]"),
        (lambda d: d["gates"]["Gate9"].update(colour=1), r"gate 'Gate9': unknown field\(s\) \['colour'\]"),
        (lambda d: d["gates"].pop("Gate13"), r"gate\(s\) \['Gate13'\] missing from 'gates'"),
        (lambda d: d["gates"]["Gate1"].update(corners=[[1.0, 2.0, 3.0]] * 4), r"'Gate1' corners: degenerate"),
        (
            lambda d: d["race"]["init_pose"].update(quaternion_xyzw=[0, 0, 1]),
            r"race.init_pose.quaternion_xyzw: expected 4",
        ),
    ],
)
def test_bad_course_files_raise(tmp_path, course_data, edit, message):
    data = copy.deepcopy(course_data)
    edit(data)
    with pytest.raises(ValueError, match=message):
        T.load_course(_write(tmp_path, data))


def test_a_copy_of_the_file_loads_the_same(tmp_path, course_data, course):
    other = T.load_course(_write(tmp_path, course_data))
    np.testing.assert_allclose(other.gates.centre, course.gates.centre)
    np.testing.assert_allclose(other.path_points, course.path_points)


# --------------------------------------------------------------------------------------------------
# Passage and collisions.
# --------------------------------------------------------------------------------------------------


def _through(gate, lateral, up, before=1.0, after=1.0):
    """Segment crossing the gate plane along the normal at (lateral, up) offsets from the centre."""
    point = gate.centre + lateral * gate.lateral + up * gate.up
    return point - before * gate.normal, point + after * gate.normal


def test_passage_through_opening(course):
    g = _gate(course, "Gate10")
    p0, p1 = _through(g, 0.3, -0.4)
    assert bool(passed_j(g, p0, p1))
    hit, cause = collide_j(course, p0, p1)
    assert not bool(hit) and int(cause) == T.CRASH_NONE


def test_frame_is_a_crash_not_a_passage(course):
    g = _gate(course, "Gate10")
    for lateral, up in [(0.0, 0.5 * 1.846 + 0.15), (-(0.9 + 0.15), 0.0), (0.9 + 0.2, -(0.923 + 0.2))]:
        p0, p1 = _through(g, lateral, up)
        assert not bool(passed_j(g, p0, p1))
        hit, cause = collide_j(course, p0, p1)
        assert bool(hit) and int(cause) == T.CRASH_GATE
        assert T.CRASH_NAMES[int(cause)] == "gate"


def test_vehicle_radius_grazing_the_inner_edge_crashes(course):
    g = _gate(course, "Gate10")
    p0, p1 = _through(g, 0.9 - 0.05, 0.0)  # centre inside the opening, 5 cm from the edge
    assert bool(passed_j(g, p0, p1))
    assert int(collide_j(course, p0, p1)[1]) == T.CRASH_GATE
    assert int(collide_j(course, p0, p1, radius=0.0)[1]) == T.CRASH_NONE


def test_segment_inside_the_frame_material_without_crossing_the_plane(course):
    g = _gate(course, "Gate10")
    top = g.centre + (0.5 * g.height + 0.15) * g.up
    p0, p1 = top - 0.02 * g.normal, top + 0.01 * g.normal  # stays within the slab
    assert int(collide_j(course, p0, p1)[1]) == T.CRASH_GATE


def test_beside_the_gate_is_neither(course):
    g = _gate(course, "Gate10")
    p0, p1 = _through(g, 0.9 + 0.3 + 1.0, 0.0)
    assert not bool(passed_j(g, p0, p1))
    assert not bool(collide_j(course, p0, p1)[0])


def test_backwards_is_not_a_passage(course):
    g = _gate(course, "Gate10")
    p0, p1 = _through(g, 0.0, 0.0)
    assert not bool(passed_j(g, p1, p0))
    assert not bool(passed_j(g, p0, p0 - g.normal))  # approaching only
    assert not bool(collide_j(course, p1, p0)[0])


def test_ground_wall_ceiling(course):
    free = jnp.asarray([10.0, 0.0, 3.0])
    assert int(collide_j(course, free, free + 0.1)[1]) == T.CRASH_NONE
    assert int(collide_j(course, free, free.at[2].set(0.05))[1]) == T.CRASH_GROUND
    beyond_x = free.at[0].set(course.hall_max[0] + 0.5)
    assert int(collide_j(course, free, beyond_x)[1]) == T.CRASH_WALL
    beyond_y = free.at[1].set(course.hall_min[1] - 0.5)
    assert int(collide_j(course, free, beyond_y)[1]) == T.CRASH_WALL
    above = free.at[2].set(course.hall_max[2] + 1.0)
    assert int(collide_j(course, free, above)[1]) == T.CRASH_WALL
    assert int(collide_j(course, course.start[:3], course.start[:3])[1]) == T.CRASH_NONE


def test_passage_and_collision_jit_and_vmap(course):
    g = course.gates
    rng = np.random.default_rng(0)
    # Segments around Gate10: through the opening, the frame and beside it, forwards and backwards.
    g10 = course.gate(0)
    offsets = rng.uniform(-2.0, 2.0, size=(64, 2))
    sign = np.where(rng.uniform(size=64) < 0.5, 1.0, -1.0)[:, None]
    lateral, up = np.asarray(g10.lateral), np.asarray(g10.up)
    mid = np.asarray(g10.centre) + offsets[:, :1] * lateral + offsets[:, 1:] * up
    p0 = jnp.asarray(mid - sign * np.asarray(g10.normal), jnp.float32)
    p1 = jnp.asarray(mid + sign * np.asarray(g10.normal), jnp.float32)
    passed_v = jax.jit(jax.vmap(T.gate_passed, in_axes=(None, 0, 0)))(g, p0, p1)  # (64, G)
    coll_v = jax.jit(jax.vmap(T.collision, in_axes=(None, 0, 0)))(course, p0, p1)
    for k in range(0, 64, 8):  # vmap == loop, jit == no-jit
        np.testing.assert_array_equal(T.gate_passed(g, p0[k], p1[k]), passed_v[k])
        assert int(T.collision(course, p0[k], p1[k])[1]) == int(coll_v[1][k])
    # Each outcome is present and consistent with the geometry.
    inside = (np.abs(offsets[:, 0]) <= 0.9) & (np.abs(offsets[:, 1]) <= 0.923)
    np.testing.assert_array_equal(np.asarray(passed_v[:, 0]), inside & (sign[:, 0] > 0))
    assert np.asarray(passed_v[:, 1:]).sum() == 0
    on_frame = (~inside) & (np.abs(offsets[:, 0]) < 1.1) & (np.abs(offsets[:, 1]) < 1.1)
    assert (np.asarray(coll_v[1])[on_frame] == T.CRASH_GATE).all() and on_frame.any()
    assert (np.asarray(coll_v[1]) == T.CRASH_NONE).any() and np.asarray(passed_v).any()


# --------------------------------------------------------------------------------------------------
# The desired path.
# --------------------------------------------------------------------------------------------------


def test_path_samples(course):
    P = course.num_path_points
    assert course.path_points.shape == (P, 3) and course.path_tangents.shape == (P, 3)
    np.testing.assert_allclose(np.diff(course.path_s), T.PATH_SPACING, rtol=1e-2)
    np.testing.assert_allclose(np.linalg.norm(course.path_tangents, axis=-1), 1.0, atol=1e-5)
    steps = np.linalg.norm(np.diff(np.asarray(course.path_points), axis=0), axis=-1)
    np.testing.assert_allclose(steps, np.diff(course.path_s), rtol=2e-2)
    tangents = np.asarray(course.path_tangents)
    assert (np.sum(tangents[1:] * tangents[:-1], axis=-1) > 0.99).all()  # C1: no kinks
    assert (np.diff(course.path_gate_s) > 0).all()
    np.testing.assert_allclose(course.path_points[0], course.start[:3], atol=1e-5)
    assert float(course.path_s[-1] - course.path_gate_s[-1]) == pytest.approx(T.PATH_RUNOUT, rel=1e-2)


def test_path_crosses_every_gate_centre_along_its_normal(course):
    query = query_j
    for k in range(course.num_gates):
        q = query(course, course.gates.centre[k])
        assert float(q.distance) < 0.01, course.names[k]
        assert float(jnp.dot(q.tangent, course.gates.normal[k])) > 0.99, course.names[k]
        assert float(q.progress_s) == pytest.approx(float(course.path_gate_s[k]), abs=0.02)


def test_flying_the_path_passes_every_gate_in_order_without_crashing(course):
    p0, p1 = course.path_points[:-1], course.path_points[1:]
    passed = np.asarray(jax.jit(jax.vmap(T.gate_passed, in_axes=(None, 0, 0)))(course.gates, p0, p1))  # (P-1, G)
    _, cause = jax.jit(jax.vmap(T.collision, in_axes=(None, 0, 0)))(course, p0, p1)
    assert (np.asarray(cause) == T.CRASH_NONE).all()
    assert (passed.sum(axis=0) == 1).all()
    assert (np.diff(passed.argmax(axis=0)) > 0).all()


def test_path_query_hand_case(straight):
    q = query_j(straight, jnp.asarray([5.1, 2.0, 4.0]))
    np.testing.assert_allclose(q.distance, math.sqrt(5.0), rtol=1e-5)
    np.testing.assert_allclose(q.progress_s, 5.1, atol=1e-4)  # continuous, not snapped to a 0.25 m vertex
    np.testing.assert_allclose(q.closest_point, [5.1, 0.0, 3.0], atol=1e-4)
    np.testing.assert_allclose(q.tangent, [1.0, 0.0, 0.0], atol=1e-5)


def test_windowed_query_equals_full_query_near_the_gate(course):
    full = jax.jit(jax.vmap(T.path_query, in_axes=(None, 0)))

    @jax.jit
    def windowed(track, positions, gate_index):
        window = T.gate_window(track, gate_index, before_m=6.0, after_m=4.0)
        return jax.vmap(lambda p: T.path_query(track, p, window))(positions)

    rng = np.random.default_rng(1)
    for k in range(course.num_gates):
        s_gate = float(course.path_gate_s[k])
        idx = np.searchsorted(np.asarray(course.path_s), s_gate + rng.uniform(-5.0, 3.0, size=16))
        near = np.asarray(course.path_points)[idx] + rng.normal(scale=0.3, size=(16, 3))
        near = jnp.asarray(near, jnp.float32)
        a, b = full(course, near), windowed(course, near, k)
        for field in ("distance", "progress_s", "tangent", "closest_point"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-5, err_msg=f"{k}{field}")
    window = T.gate_window(course, 3, before_m=6.0, after_m=4.0)
    assert isinstance(window.length, int) and window.length < course.num_path_points // 10
    s0 = float(course.path_s[int(window.start)])
    s1 = float(course.path_s[int(window.start) + window.length - 1])
    gate_s = float(course.path_gate_s[3])
    assert s0 <= gate_s - 6.0 and s1 >= gate_s + 4.0


def test_windowed_query_costs_the_window_not_the_path(course):
    window = T.gate_window(course, 2, before_m=5.0, after_m=5.0)
    jaxpr = jax.make_jaxpr(lambda tr, p, w: T.path_query(tr, p, w))(course, course.start[:3], window)
    num_points = course.num_path_points
    biggest = max(
        (v.aval.shape[0] for eqn in jaxpr.eqns for v in eqn.outvars if getattr(v.aval, "shape", ())),
        default=0,
    )
    assert biggest <= window.length < num_points


def test_window_clamps_at_the_ends(course):
    last = T.gate_window(course, course.num_gates + 3, before_m=2.0, after_m=50.0)
    assert int(last.start) == course.num_path_points - last.length
    first = T.gate_window(course, 0, before_m=100.0, after_m=1.0)
    assert int(first.start) == 0
    q = query_j(course, course.start[:3], first)
    assert float(q.distance) < 1e-4 and float(q.progress_s) < 1e-3


def test_path_query_jit_matches_no_jit(course):
    p = course.gates.centre[4] + jnp.asarray([0.4, -0.3, 0.2])
    a = T.path_query(course, p)
    b = jax.jit(T.path_query)(course, p)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, atol=1e-6)


# --------------------------------------------------------------------------------------------------
# Perturbation and the straight course.
# --------------------------------------------------------------------------------------------------


def _yaw(normals):
    return np.arctan2(normals[..., 1], normals[..., 0])


def test_perturbation_is_deterministic_and_bounded(course):
    perturb_batch = jax.jit(jax.vmap(T.perturb_course, in_axes=(None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    batch = perturb_batch(course, keys)
    again = perturb_batch(course, keys)
    np.testing.assert_array_equal(batch.gates.centre, again.gates.centre)
    np.testing.assert_array_equal(batch.path_points, again.path_points)
    assert not np.allclose(batch.gates.centre[0], batch.gates.centre[1])
    eager = T.perturb_course(course, keys[5])  # no-jit, no-vmap
    np.testing.assert_allclose(eager.gates.centre, batch.gates.centre[5], atol=1e-5)
    np.testing.assert_allclose(eager.path_points, batch.path_points[5], atol=1e-3)
    bounds = np.asarray(course.perturbation_bounds)
    d = np.asarray(batch.gates.centre) - np.asarray(course.gates.centre)  # (16, G, 3)
    assert (np.abs(d[..., :2]) <= bounds[:, :2] + 1e-4).all()
    np.testing.assert_allclose(d[..., 2], 0.0, atol=1e-5)
    turn = _yaw(np.asarray(batch.gates.normal)) - _yaw(np.asarray(course.gates.normal))
    dyaw = np.rad2deg(np.angle(np.exp(1j * turn)))
    assert (np.abs(dyaw) <= bounds[:, 2] + 1e-3).all()
    assert np.abs(dyaw).max() > 1.0 and np.abs(d[..., :2]).max() > 1.0  # it does move them
    fixed = (bounds[:, 0] == 0) & (bounds[:, 1] == 0)  # Gate21, Gate9, Gate6: no xy freedom
    assert fixed.sum() == 3
    np.testing.assert_allclose(d[:, fixed, :2], 0.0, atol=1e-5)
    np.testing.assert_allclose(batch.gates.width, np.broadcast_to(course.gates.width, (16, 11)))


def test_perturbed_path_is_rebuilt_with_the_same_shape(course):
    t = T.perturb_course(course, jax.random.PRNGKey(3))
    assert t.path_points.shape == course.path_points.shape and t.names == course.names
    np.testing.assert_array_equal(t.hall_min, course.hall_min)
    query = query_j
    for k in range(t.num_gates):
        q = query(t, t.gates.centre[k])
        assert float(q.distance) < 0.01
        assert float(jnp.dot(q.tangent, t.gates.normal[k])) > 0.99
    tight = T.perturb_course(course, jax.random.PRNGKey(3), bounds=jnp.zeros(3))
    np.testing.assert_allclose(tight.path_points, course.path_points, atol=1e-4)


def test_straight_course(straight):
    t = straight
    assert t.num_gates == 5 and t.names[0] == "Gate1"
    np.testing.assert_allclose(t.gates.centre[:, 0], [20.0, 40.0, 60.0, 80.0, 100.0])
    np.testing.assert_allclose(t.gates.normal, np.broadcast_to([1.0, 0.0, 0.0], (5, 3)), atol=1e-6)
    np.testing.assert_allclose(t.start[:3], [0.0, 0.0, 3.0])
    np.testing.assert_allclose(t.path_points[:, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(t.path_points[:, 2], 3.0, atol=1e-4)
    np.testing.assert_allclose(t.path_gate_s, [20.0, 40.0, 60.0, 80.0, 100.0], atol=1e-3)
    assert float(t.hall_min[0]) <= -T.HALL_MARGIN and float(t.hall_max[0]) >= 100.0 + T.HALL_MARGIN
    p0, p1 = jnp.asarray([19.0, 0.0, 3.0]), jnp.asarray([21.0, 0.0, 3.0])
    np.testing.assert_array_equal(passed_j(t.gates, p0, p1), [True, False, False, False, False])
    with pytest.raises(ValueError, match="num_gates"):
        T.straight_course(num_gates=0)
