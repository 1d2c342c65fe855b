"""Rotation augmentation: the turned row is the row a camera turned that much more would have produced."""

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import devices
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.learn import rotation_augment as ra
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render as render_lib

DT = 0.025


def test_zero_turn_is_identity():
    camera = camera_lib.default_camera()
    w = jnp.asarray([0.3, -0.2, 0.9])
    w2, f2 = ra.augment_row(w, jnp.asarray([40.5, 100.5]), jnp.asarray([1.5, -2.0]), jnp.zeros(3), camera, DT)
    np.testing.assert_allclose(w2, w, atol=1e-5)
    np.testing.assert_allclose(f2, [1.5, -2.0], atol=1e-4)


def test_parallel_rates_add_and_yaw_moves_the_centre_right_by_fx_per_radian():
    camera = camera_lib.default_camera()
    centre = jnp.asarray([camera.cx, camera.cy])
    w2, f2 = ra.augment_row(jnp.asarray([0.0, 0.0, 0.5]), centre, jnp.zeros(2), jnp.asarray([0.0, 0.0, 0.7]),
                            camera, DT)
    np.testing.assert_allclose(w2, [0.0, 0.0, 1.2], atol=1e-5)
    # a left yaw of 0.7 rad/s for one frame: the scene at the centre moves right by fx * tan(0.7 dt)
    np.testing.assert_allclose(f2, [float(camera.fx) * np.tan(0.7 * DT), 0.0], atol=1e-3)


def test_turned_exact_flow_equals_exact_flow_of_the_turned_pose():
    """Augmenting the exact flow of a real (translating and turning) frame pair gives the exact flow of the
    same pair with the second pose turned by delta dt more, at every pixel both see; and w' is its rate."""
    track = course_lib.load_course()
    camera = camera_lib.default_camera()
    x0 = track.start
    w = jnp.asarray([0.4, -0.3, 0.8])
    x1 = x0.at[quadrotor.POS].add(jnp.asarray([0.25, 0.05, 0.02]))
    x1 = x1.at[quadrotor.QUAT].set(quadrotor.quat_multiply(x0[quadrotor.QUAT], quadrotor.quat_exp(w, DT)))
    delta = jnp.asarray([-0.9, 1.3, 0.6])
    x1_turned = x1.at[quadrotor.QUAT].set(quadrotor.quat_multiply(x1[quadrotor.QUAT], quadrotor.quat_exp(delta, DT)))
    depth = devices.compiled(render_lib.render, ("supersample",))(track, x0, camera, supersample=1).depth
    exact_flow = devices.compiled(render_lib.exact_flow)
    flow, valid = exact_flow(x0, x1, depth, camera)
    flow_turned, valid_turned = exact_flow(x0, x1_turned, depth, camera)
    H, W = depth.shape
    uu, vv = jnp.meshgrid(jnp.arange(W) + 0.5, jnp.arange(H) + 0.5)
    pixels = jnp.stack([uu, vv], -1).reshape(-1, 2)
    rows = pixels.shape[0]
    w2, f2 = jax.vmap(ra.augment_row, in_axes=(None, 0, 0, None, None, None))(
        w, pixels, flow.reshape(-1, 2), delta, camera, DT)
    both = np.asarray(valid & valid_turned).reshape(-1)
    assert both.sum() > 0.5 * rows
    np.testing.assert_allclose(np.asarray(f2)[both], np.asarray(flow_turned).reshape(-1, 2)[both], atol=2e-2)
    # the flow did change: the check is not trivially true
    assert np.abs(np.asarray(f2)[both] - np.asarray(flow).reshape(-1, 2)[both]).mean() > 1.0
    relative = quadrotor.quat_multiply(quadrotor.quat_conjugate(x0[quadrotor.QUAT]), x1_turned[quadrotor.QUAT])
    np.testing.assert_allclose(w2[0], ra.rate_of_rotation(relative, DT), atol=1e-3)


def test_batch_turns_only_the_drawn_rows():
    camera = camera_lib.default_camera()
    key = jax.random.key(3)
    w = jax.random.normal(key, (256, 3))
    pixels = jnp.tile(jnp.asarray([[50.5, 60.5]]), (256, 1))
    flow = jnp.ones((256, 2))
    w0, f0 = ra.augment_batch(key, w, pixels, flow, 1.0, 0.0, camera, DT)
    np.testing.assert_array_equal(w0, w)
    np.testing.assert_array_equal(f0, flow)
    w_half, f_half = ra.augment_batch(key, w, pixels, flow, 1.0, 0.5, camera, DT)
    changed = np.any(np.asarray(w_half) != np.asarray(w), axis=1)
    assert 0.3 < changed.mean() < 0.7
    assert np.all(np.any(np.asarray(f_half)[changed] != 1.0, axis=1))
