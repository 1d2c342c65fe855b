"""Building a course: the course file (gate geometry, start, hall, bad input), the perturbation and the
straight course."""

import copy
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import course as C
from pixelmpc_jax.world import track as T


@pytest.fixture(scope="module")
def course_data():
    return json.loads(C.COURSE_FILE.read_text())


@pytest.fixture(scope="module")
def course():
    return C.load_course()


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
    g = course.gate(course.names.index("Gate10"))  # crossed along +y: lateral (left) is -x
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
    g = course.gate(course.names.index("Gate10"))
    assert float(g.width) == pytest.approx(1.8, abs=1e-3)
    assert float(g.height) == pytest.approx(1.846, abs=1e-3)
    assert float(g.border) == pytest.approx(0.3)
    assert float(g.depth) == pytest.approx(T.GATE_DEPTH)
    big = course.gate(course.names.index("Gate21"))  # the diagonal one: 2.128 * sqrt(2) wide
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
        C.load_course(_write(tmp_path, data))


def test_a_copy_of_the_file_loads_the_same(tmp_path, course_data, course):
    other = C.load_course(_write(tmp_path, course_data))
    np.testing.assert_allclose(other.gates.centre, course.gates.centre)
    np.testing.assert_allclose(other.path_points, course.path_points)


# --------------------------------------------------------------------------------------------------
# Perturbation and the straight course.
# --------------------------------------------------------------------------------------------------


def _yaw(normals):
    return np.arctan2(normals[..., 1], normals[..., 0])


def test_perturbation_is_deterministic_and_bounded(course):
    perturb_batch = jax.jit(jax.vmap(C.perturb_course, in_axes=(None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    batch = perturb_batch(course, keys)
    again = perturb_batch(course, keys)
    np.testing.assert_array_equal(batch.gates.centre, again.gates.centre)
    np.testing.assert_array_equal(batch.path_points, again.path_points)
    assert not np.allclose(batch.gates.centre[0], batch.gates.centre[1])
    eager = C.perturb_course(course, keys[5])  # no-jit, no-vmap
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
    t = C.perturb_course(course, jax.random.PRNGKey(3))
    assert t.path_points.shape == course.path_points.shape and t.names == course.names
    np.testing.assert_array_equal(t.hall_min, course.hall_min)
    query = jax.jit(T.path_query)
    for k in range(t.num_gates):
        q = query(t, t.gates.centre[k])
        assert float(q.distance) < 0.01
        assert float(jnp.dot(q.tangent, t.gates.normal[k])) > 0.99
    tight = C.perturb_course(course, jax.random.PRNGKey(3), bounds=jnp.zeros(3))
    np.testing.assert_allclose(tight.path_points, course.path_points, atol=1e-4)


def test_a_perturbed_course_built_on_the_host_is_the_pure_one(course):
    """``move_gates(track, perturb_gates(track, key))`` (the path's halves compiled, a race's perturbed laps) against
    :func:`perturb_course` run op by op: the same gates, the same path within float rounding (3e-5 m measured)."""
    key = jax.random.PRNGKey(3)
    pure = C.perturb_course(course, key)
    host = C.move_gates(course, C.perturb_gates(course, key))
    np.testing.assert_array_equal(host.gates.centre, pure.gates.centre)
    np.testing.assert_array_equal(host.hall_max, course.hall_max)
    assert host.path_points.shape == course.path_points.shape
    np.testing.assert_allclose(host.path_points, pure.path_points, atol=1e-3)
    np.testing.assert_allclose(host.path_gate_s, pure.path_gate_s, atol=1e-3)


def test_straight_course():
    t = C.straight_course(num_gates=5, spacing=20.0, height=3.0, first_gate_x=20.0)
    assert t.num_gates == 5 and t.names[0] == "Gate1"
    np.testing.assert_allclose(t.gates.centre[:, 0], [20.0, 40.0, 60.0, 80.0, 100.0])
    np.testing.assert_allclose(t.gates.normal, np.broadcast_to([1.0, 0.0, 0.0], (5, 3)), atol=1e-6)
    np.testing.assert_allclose(t.start[:3], [0.0, 0.0, 3.0])
    np.testing.assert_allclose(t.path_points[:, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(t.path_points[:, 2], 3.0, atol=1e-4)
    np.testing.assert_allclose(t.path_gate_s, [20.0, 40.0, 60.0, 80.0, 100.0], atol=1e-3)
    assert float(t.hall_min[0]) <= -T.HALL_MARGIN and float(t.hall_max[0]) >= 100.0 + T.HALL_MARGIN
    p0, p1 = jnp.asarray([19.0, 0.0, 3.0]), jnp.asarray([21.0, 0.0, 3.0])
    np.testing.assert_array_equal(jax.jit(T.gate_passed)(t.gates, p0, p1), [True, False, False, False, False])
    with pytest.raises(ValueError, match="num_gates"):
        C.straight_course(num_gates=0)


def test_courses_by_name_or_file(tmp_path, course_data):
    assert C.make_course("alphapilot").num_gates == 11
    straight = C.make_course("straight")
    assert straight.num_gates == 5
    np.testing.assert_allclose(np.diff(np.asarray(straight.gates.centre)[:, 0]), 20.0)
    path = tmp_path / "course.json"
    path.write_text(json.dumps(course_data))
    np.testing.assert_array_equal(C.make_course(str(path)).gates.centre, C.make_course("alphapilot").gates.centre)
    with pytest.raises(ValueError, match="unknown course 'monza'; choose one of alphapilot, straight or a course file"):
        C.make_course("monza")
    assert C.course_title("straight") == "the straight lane" and C.course_title(str(path)) == str(path)


# --------------------------------------------------------------------------------------------------
# The seeded course generator.
# --------------------------------------------------------------------------------------------------

SEEDS = range(20)


@pytest.fixture(scope="module")
def generated():
    return {seed: C.generate_course(seed) for seed in SEEDS}


def _layout(data):
    """start (3,), start quaternion xyzw (4,), corners (G, 4, 3) of a course dict, in race order."""
    pose = data["race"]["init_pose"]
    corners = np.array([data["gates"][name]["corners"] for name in data["race"]["gate_order"]])
    return np.array(pose["position"]), np.array(pose["quaternion_xyzw"]), corners


def _yaw_of(v):
    return np.arctan2(v[..., 1], v[..., 0])


def _wrap_deg(angle):
    return np.rad2deg(np.angle(np.exp(1j * angle)))


def test_generated_course_is_deterministic_in_its_seed(generated):
    assert C.generate_course(3) == generated[3]
    assert generated[3] != generated[4]
    _, _, a = _layout(generated[3])
    _, _, b = _layout(generated[4])
    assert np.abs(a - b).max() > 1.0
    assert len(C.generate_course(3, num_gates=5)["gates"]) == 5
    assert "seed 3" in generated[3]["about"] and f"version {C.GENERATOR_VERSION}" in generated[3]["about"]
    with pytest.raises(ValueError, match="num_gates"):
        C.generate_course(0, num_gates=0)


@pytest.mark.parametrize("seed", SEEDS)
def test_generated_course_keeps_its_bounds(generated, seed):
    data = generated[seed]
    start, q_xyzw, corners = _layout(data)
    assert data["race"]["gate_order"] == [f"Gate{k + 1}" for k in range(8)]
    tl, tr, br, bl = corners.transpose(1, 0, 2)  # (G, 3) each
    np.testing.assert_allclose(np.linalg.norm(tl - tr, axis=-1), 1.8, atol=2e-4)  # AlphaPilot size
    np.testing.assert_allclose(np.linalg.norm(tl - bl, axis=-1), 1.85, atol=2e-4)
    np.testing.assert_allclose((tl - bl)[:, :2], 0.0, atol=2e-4)  # upright
    np.testing.assert_allclose(tl - bl, tr - br, atol=2e-4)  # a rectangle
    centres = corners.mean(axis=1)
    assert ((centres[:, 2] >= 3.0) & (centres[:, 2] <= 7.0)).all()
    leg_lengths = np.linalg.norm(np.diff(centres, axis=0), axis=-1)
    assert ((leg_lengths >= 10.0 - 1e-3) & (leg_lengths <= 22.0 + 1e-3)).all()
    gaps = np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=-1)[np.triu_indices(8, 1)]
    assert gaps.min() >= 6.0 - 1e-3
    route = np.concatenate([start[None], centres])[:, :2]
    legs = np.diff(route, axis=0)
    legs /= np.linalg.norm(legs, axis=-1, keepdims=True)  # (G, 2) unit leg into each gate
    turns = _wrap_deg(np.diff(_yaw_of(legs)))
    assert np.abs(turns).max() <= 70.0 + 1e-3
    # Facing the direction of travel: the normal (lateral x up, TL -> TR being -lateral) is within half
    # the turn of both legs.
    lateral, up = tl - tr, tl - bl
    normal = np.cross(lateral, up)[:, :2]
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    leaving = np.concatenate([legs[1:], legs[-1:]])
    assert (np.sum(normal * legs, -1) >= math.cos(math.radians(35.0)) - 1e-4).all()
    assert (np.sum(normal * leaving, -1) >= math.cos(math.radians(35.0)) - 1e-4).all()
    # The start: level with the first gate, 15-20 m before it, facing it.
    assert start[2] == pytest.approx(centres[0, 2], abs=1e-3)
    assert 15.0 - 1e-3 <= np.linalg.norm(centres[0] - start) <= 20.0 + 1e-3
    heading = np.asarray(quadrotor.rotation_matrix(jnp.asarray(q_xyzw[[3, 0, 1, 2]], jnp.float32))[:, 0])
    np.testing.assert_allclose(heading[:2], legs[0], atol=1e-5)
    assert np.abs(start[:2]).max() <= 35.0  # in the footprint (the frames and path: the next test)


def test_generated_courses_stay_in_the_footprint(generated):
    """The gate frames and the desired path (start -> gates -> run-out) of every seed stay inside the 70 m
    square centred on the origin."""

    @jax.jit
    def frames_and_path(start, corners):
        normal = jnp.cross(corners[:, 0] - corners[:, 1], corners[:, 0] - corners[:, 3])  # lateral x up
        gates = T.make_gate(corners.mean(axis=1), T.gate_rotation(normal), 1.8, 1.85)
        points, _, _, _ = T.build_path(start, gates, 600)
        return gates.outer_corners(), points  # (G, 4, 3), (600, 3)

    for seed in SEEDS:
        start, _, corners = _layout(generated[seed])
        frames, points = frames_and_path(jnp.asarray(start, jnp.float32), jnp.asarray(corners, jnp.float32))
        assert np.abs(np.asarray(frames)[..., :2]).max() <= 35.0, seed
        assert np.abs(np.asarray(points)[:, :2]).max() <= 35.0, seed


def test_generated_course_copies_the_alphapilot_camera_and_vehicle(generated, course_data):
    for data in generated.values():
        assert data["camera"] == course_data["camera"] and data["vehicle"] == course_data["vehicle"]
        assert set(data) == set(course_data) and set(data["race"]) == set(course_data["race"])
    assert generated[0]["vehicle"] is not generated[1]["vehicle"]  # copies, not one shared block


def test_generated_course_round_trip(tmp_path, generated):
    data = generated[7]
    path = tmp_path / "generated.json"
    C.write_course(data, path)
    assert json.loads(path.read_text()) == data
    track = C.load_course(path)
    start, _, corners = _layout(data)
    assert track.names == tuple(data["race"]["gate_order"])
    np.testing.assert_allclose(track.start[:3], start, atol=1e-5)
    np.testing.assert_allclose(track.gates.centre, corners.mean(axis=1), atol=1e-4)
    np.testing.assert_allclose(track.gates.corners(), corners, atol=1e-3)  # the same corner order
    np.testing.assert_allclose(track.gates.width, 1.8, atol=1e-3)
    np.testing.assert_allclose(track.gates.height, 1.85, atol=1e-3)
    # The path is built and goes through the gates in order, along their normals.
    assert track.path_points.shape[0] >= 100 and np.isfinite(np.asarray(track.path_points)).all()
    assert (np.diff(np.asarray(track.path_gate_s)) > 5.0).all()
    query = jax.jit(T.path_query)
    for k in range(track.num_gates):
        q = query(track, track.gates.centre[k])
        assert float(q.distance) < 0.05
        assert float(q.progress_s) == pytest.approx(float(track.path_gate_s[k]), abs=0.5)
        assert float(jnp.dot(q.tangent, track.gates.normal[k])) > 0.99
    extent = np.asarray(track.hall_max - track.hall_min)[:2]
    assert (extent <= 70.0 + 2 * T.HALL_MARGIN).all()
