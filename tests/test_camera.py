"""Pinhole projection (hand-computed cases, round trip) and gate visibility."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import camera as cam_mod
from pixelmpc_jax.world import track as track_mod

# The AlphaPilot K scaled to 204 x 153: both axes scale by 0.19921875.
FX = 548.4088134765625 * 204 / 1024
CX, CY = 102.0, 76.5


@pytest.fixture(scope="module")
def camera():
    return cam_mod.default_camera()


def _state(position, yaw=0.0):
    return quadrotor.hover_state(position, yaw)


def test_default_camera_intrinsics(camera):
    assert (camera.width, camera.height) == (204, 153)
    np.testing.assert_allclose([camera.fx, camera.fy, camera.cx, camera.cy], [FX, FX, CX, CY], rtol=1e-6)


def test_project_ahead_left_up_identity(camera):
    # 10 m ahead, 1 m left, 1 m up: camera x = -1 (right), y = -1 (down), z = 10.
    uv, depth, in_front = cam_mod.project(jnp.asarray([10.0, 1.0, 1.0]), _state((0.0, 0.0, 0.0)), camera)
    expected = [(CX - FX * 0.1) / 204, (CY - FX * 0.1) / 153]
    np.testing.assert_allclose(uv, expected, rtol=1e-5)
    np.testing.assert_allclose(depth, 10.0, rtol=1e-6)
    assert bool(in_front)


def test_project_with_yaw_90(camera):
    # Facing +y from (1, 2, 3): ahead is +y, left is -x.
    x = _state((1.0, 2.0, 3.0), yaw=math.pi / 2)
    uv, depth, _ = cam_mod.project(jnp.asarray([0.0, 12.0, 4.0]), x, camera)
    np.testing.assert_allclose(uv, [(CX - FX * 0.1) / 204, (CY - FX * 0.1) / 153], rtol=1e-5)
    np.testing.assert_allclose(depth, 10.0, rtol=1e-5)


def test_project_with_tilt():
    tilt = math.radians(30.0)
    camera = cam_mod.default_camera(tilt=tilt)
    x = _state((0.0, 0.0, 0.0))
    # A point on the tilted optical axis lands at the image centre.
    on_axis = jnp.asarray([10 * math.cos(tilt), 0.0, 10 * math.sin(tilt)])
    uv, depth, _ = cam_mod.project(on_axis, x, camera)
    np.testing.assert_allclose(uv, [0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(depth, 10.0, rtol=1e-6)
    # A point straight ahead (horizontal) appears below the centre by fy tan(tilt).
    uv, depth, _ = cam_mod.project(jnp.asarray([10.0, 0.0, 0.0]), x, camera)
    np.testing.assert_allclose(uv, [0.5, (CY + FX * math.tan(tilt)) / 153], rtol=1e-5)
    np.testing.assert_allclose(depth, 10 * math.cos(tilt), rtol=1e-6)


def test_point_behind_is_not_in_front(camera):
    _, depth, in_front = cam_mod.project(jnp.asarray([-5.0, 0.0, 0.0]), _state((0.0, 0.0, 0.0)), camera)
    assert float(depth) == pytest.approx(-5.0)
    assert not bool(in_front)


_round_trip = jax.jit(
    lambda p, x, camera: cam_mod.backproject(
        cam_mod.project(p, x, camera)[0] * jnp.asarray([camera.width, camera.height], jnp.float32),
        cam_mod.project(p, x, camera)[1],
        x,
        camera,
    )
)


@settings(max_examples=30, deadline=None)
@given(
    position=st.tuples(*[st.floats(-20, 20)] * 3),
    euler=st.tuples(st.floats(-0.8, 0.8), st.floats(-0.8, 0.8), st.floats(-math.pi, math.pi)),
    point_cam=st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.5, 30)),
    tilt=st.floats(0.0, 0.5),
)
def test_backproject_inverts_project(position, euler, point_cam, tilt):
    camera = cam_mod.default_camera(tilt=tilt)
    q = quadrotor.quat_from_euler(*[jnp.float32(a) for a in euler])
    x = jnp.concatenate([jnp.asarray(position, jnp.float32), q, jnp.zeros(3)])
    # A point in front of the camera: place it in camera coordinates, then map to the world.
    R, origin = cam_mod.world_to_camera(x, camera)
    p = jnp.asarray(point_cam, jnp.float32) @ R + origin
    np.testing.assert_allclose(_round_trip(p, x, camera), p, atol=2e-4 * (1 + abs(point_cam[2])))


# --------------------------------------------------------------------------------------------------
# Gate outline and visibility.
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def gate():
    """A 2 x 1.5 m gate at (10, 0, 2) crossed along +x."""
    return track_mod.make_gate([10.0, 0.0, 2.0], np.eye(3), 2.0, 1.5)


def test_outline_points_on_the_opening(gate):
    pts = np.asarray(cam_mod.gate_outline_points(gate, n_per_side=8))
    assert pts.shape == (32, 3)
    local = pts - np.array([10.0, 0.0, 2.0])
    np.testing.assert_allclose(local[:, 0], 0.0, atol=1e-6)
    on_side = np.isclose(np.abs(local[:, 1]), 1.0, atol=1e-6) | np.isclose(np.abs(local[:, 2]), 0.75, atol=1e-6)
    assert on_side.all()
    assert (np.abs(local[:, 1]) <= 1.0 + 1e-6).all() and (np.abs(local[:, 2]) <= 0.75 + 1e-6).all()
    np.testing.assert_allclose(pts[::8], np.asarray(gate.corners()), atol=1e-6)  # each side starts at a corner
    assert len({tuple(np.round(p, 5)) for p in pts}) == 32  # no duplicates


def test_corner_order_as_seen_in_the_image(gate, camera):
    uv, _, in_front = cam_mod.project(gate.corners(), _state((0.0, 0.0, 2.0)), camera)
    uv = np.asarray(uv)
    assert bool(jnp.all(in_front))
    tl, tr, br, bl = uv
    assert tl[0] < tr[0] and bl[0] < br[0]  # left corners have smaller u
    assert tl[1] < bl[1] and tr[1] < br[1]  # top corners have smaller v
    np.testing.assert_allclose(uv.mean(axis=0), [0.5, 0.5], atol=1e-6)


def test_visibility_facing_away_and_edge(gate, camera):
    facing = cam_mod.gate_visibility(gate, _state((0.0, 0.0, 2.0)), camera)
    away = cam_mod.gate_visibility(gate, _state((0.0, 0.0, 2.0), yaw=math.pi), camera)
    # Turn left by the half field of view: the gate centre sits on the right image edge.
    half_fov = math.atan(CX / FX)
    edge = cam_mod.gate_visibility(gate, _state((0.0, 0.0, 2.0), yaw=half_fov), camera)
    assert float(facing) == 1.0
    assert float(away) == 0.0
    assert 0.2 < float(edge) < 0.8


def test_visibility_behind_the_camera_is_zero(gate, camera):
    # Just past the gate, still facing +x: the gate is behind, even though it would project "into" the image.
    assert float(cam_mod.gate_visibility(gate, _state((12.0, 0.0, 2.0)), camera)) == 0.0


def test_visibility_batched_gates_and_jit(camera):
    gates = track_mod.make_gate([[10.0, 0.0, 2.0], [-10.0, 0.0, 2.0]], np.broadcast_to(np.eye(3), (2, 3, 3)), 2.0, 1.5)
    x = _state((0.0, 0.0, 2.0))
    vis = cam_mod.gate_visibility(gates, x, camera)
    assert vis.shape == (2,)
    np.testing.assert_allclose(vis, [1.0, 0.0])
    jitted = jax.jit(cam_mod.gate_visibility, static_argnames="n_per_side")(gates, x, camera, n_per_side=16)
    np.testing.assert_allclose(jitted, vis)
