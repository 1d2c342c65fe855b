"""Gate geometry, passage and collisions, and the desired path (building courses: test_course.py)."""

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.world import course as C
from pixelmpc_jax.world import track as T


@pytest.fixture(scope="module")
def course():
    return C.load_course()


@pytest.fixture(scope="module")
def straight():
    return C.straight_course(num_gates=5, spacing=20.0, height=3.0, first_gate_x=20.0)


# Shared compiled wrappers (each compiles once per module); eager no-jit runs are compared against them.
passed_j = jax.jit(T.gate_passed)
collide_j = jax.jit(T.collision)
query_j = jax.jit(T.path_query)


def _gate(track, name):
    return track.gate(track.names.index(name))


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
        chex.assert_trees_all_close(full(course, near), windowed(course, near, k), atol=1e-5)
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
    chex.assert_trees_all_close(T.path_query(course, p), jax.jit(T.path_query)(course, p), atol=1e-6)
