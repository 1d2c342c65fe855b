"""The ray-caster: gates where the camera puts them, at the right depth; the exact flow's equations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import devices
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render as R

GATE_X = 20.0
DISTANCE = 6.0
# the renderer is pure; its callers compile it (pixelmpc_jax.devices.compiled), as these tests do
render = devices.compiled(R.render, ("supersample",))
render_batch = devices.compiled(R.render_batch, ("supersample", "chunk"))
exact_flow = devices.compiled(R.exact_flow)


@pytest.fixture(scope="module")
def camera():
    return C.default_camera()


@pytest.fixture(scope="module")
def single_gate():
    return course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=GATE_X)


@pytest.fixture(scope="module")
def ahead(single_gate, camera):
    """A frame from DISTANCE m straight before the gate, level, heading +x."""
    x = quadrotor.hover_state((GATE_X - DISTANCE, 0.0, 3.0), yaw=0.0)
    return x, render(single_gate, x, camera)


def test_frame_shapes_and_dtypes(ahead, camera):
    _, frame = ahead
    H, W = camera.height, camera.width
    assert frame.rgb.shape == (H, W, 3) and frame.rgb.dtype == jnp.uint8
    assert frame.grey.shape == (H, W) and frame.grey.dtype == jnp.uint8
    assert frame.depth.shape == (H, W) and frame.depth.dtype == jnp.float32
    assert frame.gate_id.shape == (H, W) and frame.gate_id.dtype == jnp.int32
    assert np.all(np.isfinite(frame.depth)) and float(frame.depth.min()) > 0
    assert set(np.unique(frame.gate_id)) == {-1, 0}


def test_grey_is_the_luma_of_rgb(ahead):
    _, frame = ahead
    rgb = np.asarray(frame.rgb, np.float64)
    luma = rgb @ np.array([0.299, 0.587, 0.114])
    assert np.abs(luma - np.asarray(frame.grey, np.float64)).max() <= 1.5  # rounding of rgb and grey


def _pixel(uv, camera):
    u, v = np.asarray(uv) * [camera.width, camera.height]
    return int(np.floor(v)), int(np.floor(u))


def test_gate_renders_where_the_camera_projects_it(ahead, single_gate, camera):
    x, frame = ahead
    gate = single_gate.gate(0)
    gate_id = np.asarray(frame.gate_id)
    # The opening's centre shows the hall through the gate.
    centre_uv, _, _ = C.project(gate.centre, x, camera)
    assert gate_id[_pixel(centre_uv, camera)] == -1
    # Mid-border points just outside every inner corner and along every side are frame.
    inner, outer = np.asarray(gate.corners()), np.asarray(gate.outer_corners())
    ring = 0.5 * (inner + outer)  # (4, 3) diagonally in the frame's corner squares
    sides = 0.5 * (ring + np.roll(ring, -1, axis=0))  # middles of the four bars
    for point in np.concatenate([ring, sides]):
        uv, _, _ = C.project(jnp.asarray(point), x, camera)
        assert gate_id[_pixel(uv, camera)] == 0, point
    # Just inside the opening and just outside the frame: not the gate.
    for point, expected in (
        (0.9 * inner + 0.1 * np.asarray(gate.centre), -1),
        (np.asarray(gate.centre) + 1.15 * (outer - np.asarray(gate.centre)), -1),
    ):
        for p in point:
            uv, _, _ = C.project(jnp.asarray(p), x, camera)
            assert gate_id[_pixel(uv, camera)] == expected, p
    # Depth at frame pixels: the distance to the frame's near face along the optical axis.
    depth = np.asarray(frame.depth)[gate_id == 0]
    near_face = DISTANCE - 0.5 * float(gate.depth)
    np.testing.assert_allclose(depth.min(), near_face, atol=1e-3)
    assert depth.max() < DISTANCE + 0.5 * float(gate.depth) + 1e-3  # inner walls lie within the slab


def test_hall_depth_straight_ahead(ahead, single_gate, camera):
    """Through the opening the optical axis meets the far +x wall."""
    x, frame = ahead
    H, W = camera.height, camera.width
    depth = float(np.asarray(frame.depth)[H // 2, W // 2])
    ray_z = 1.0  # the centre pixel's ray is almost the optical axis; depth is measured along it
    expected = float(single_gate.hall_max[0]) - float(x[0])
    assert abs(depth * ray_z - expected) / expected < 1e-3


def test_render_batch_matches_single_renders(single_gate, camera):
    x0 = quadrotor.hover_state((GATE_X - 8.0, 0.3, 2.8), yaw=0.1)
    x1 = R.advance_pose(x0, 1 / 40, speed=10.0, body_rates=(0.5, -0.3, 1.0))
    batch = render_batch(single_gate, jnp.stack([x0, x1]), camera)
    for k, x in enumerate((x0, x1)):
        single = render(single_gate, x, camera)
        np.testing.assert_array_equal(batch.gate_id[k], single.gate_id)
        np.testing.assert_allclose(batch.depth[k], single.depth, rtol=1e-5)
        assert np.abs(np.asarray(batch.rgb[k], int) - np.asarray(single.rgb, int)).max() <= 1


def test_a_compiled_render_compiles_once_for_new_poses(single_gate, camera):
    assert devices.compiled(R.render, ("supersample",)) is render  # asked again: the same compiled function
    x = quadrotor.hover_state((GATE_X - 8.0, 0.3, 2.8), yaw=0.1)
    render(single_gate, x, camera, supersample=1)
    compiled = render._cache_size()
    render(single_gate, x.at[0].add(0.5), camera, supersample=1)
    assert render._cache_size() == compiled


def test_bad_supersample_and_batch_shape(single_gate, camera):
    with pytest.raises(ValueError, match="odd"):
        render(single_gate, single_gate.start, camera, supersample=2)
    with pytest.raises(ValueError, match=r"\(B, 10\)"):
        render_batch(single_gate, single_gate.start, camera)


# --------------------------------------------------------------------------------------------------
# Exact flow (no rendering needed: any depth map will do).
# --------------------------------------------------------------------------------------------------


def _depth_map(camera, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform(1.0, 30.0, (camera.height, camera.width)), jnp.float32)


def test_zero_motion_gives_zero_flow(camera):
    x = quadrotor.hover_state((1.0, -2.0, 3.0), yaw=0.7)
    flow, valid = exact_flow(x, x, _depth_map(camera), camera)
    assert bool(valid.all())
    assert float(jnp.abs(flow).max()) < 1e-3


@pytest.mark.parametrize("yaw_step", [0.05, -0.05, 0.2])
def test_pure_yaw_gives_the_rotational_flow(camera, yaw_step):
    """Turning left by psi moves a normalised image point to x' = (x cos + sin) / (cos - x sin),
    y' = y / (cos - x sin), whatever the depth."""
    x0 = quadrotor.hover_state((1.0, -2.0, 3.0), yaw=0.7)
    x1 = x0.at[quadrotor.QUAT].set(quadrotor.quat_from_yaw(0.7 + yaw_step))
    flow, valid = exact_flow(x0, x1, _depth_map(camera), camera)
    uu, vv = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    xn, yn = (uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy
    c, s = np.cos(yaw_step), np.sin(yaw_step)
    den = c - xn * s
    expected = np.stack([camera.fx * ((xn * c + s) / den - xn), camera.fy * (yn / den - yn)], axis=-1)
    u1, v1 = uu + expected[..., 0], vv + expected[..., 1]
    inside = (u1 >= 0) & (u1 <= camera.width) & (v1 >= 0) & (v1 <= camera.height)
    edge = np.minimum.reduce([u1, camera.width - u1, v1, camera.height - v1]) < 1e-2  # rounding at the rim
    np.testing.assert_array_equal(np.asarray(valid)[~edge], inside[~edge])
    np.testing.assert_allclose(np.asarray(flow)[inside], expected[inside], atol=2e-3)
    assert np.sign(np.asarray(flow)[inside][:, 0]).mean() == np.sign(yaw_step)  # left turn: scene moves right


def test_forward_translation_expands_from_the_centre(camera):
    """Moving dz along the optical axis: flow = (p - c) * dz / (Z - dz)."""
    x0 = quadrotor.hover_state((0.0, 0.0, 3.0), yaw=0.0)
    dz = 0.25
    x1 = x0.at[0].add(dz)
    depth = _depth_map(camera, seed=1)
    flow, valid = exact_flow(x0, x1, depth, camera)
    uu, vv = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    gain = dz / (np.asarray(depth) - dz)
    expected = np.stack([(uu - camera.cx) * gain, (vv - camera.cy) * gain], axis=-1)
    v = np.asarray(valid)
    assert v.mean() > 0.9
    np.testing.assert_allclose(np.asarray(flow)[v], expected[v], atol=2e-3)


def test_texture_is_deterministic_and_band_limited():
    a = jnp.linspace(-3.0, 3.0, 2001)
    b = jnp.full_like(a, 0.37)
    fine = R.surface_texture(a, b, jnp.full_like(a, 0.001), jnp.int32(3))
    np.testing.assert_array_equal(fine, R.surface_texture(a, b, jnp.full_like(a, 0.001), jnp.int32(3)))
    assert float(fine.std()) > 0.1  # rich
    # A footprint wider than every wavelength leaves the mean grey only.
    flat = R.surface_texture(a, b, jnp.full_like(a, 10.0), jnp.int32(3))
    np.testing.assert_allclose(flat, 0.5, atol=1e-6)
    other = R.surface_texture(a, b, jnp.full_like(a, 0.001), jnp.int32(4))
    assert float(jnp.abs(other - fine).mean()) > 0.05  # each material its own texture


def test_gate_colours_are_distinct():
    hues = np.array([R.gate_hue(g) for g in range(12)])
    gaps = np.abs(hues[:, None] - hues[None, :])
    gaps = np.minimum(gaps, 1 - gaps) + np.eye(12)
    assert gaps.min() >= 29.9 / 360


def test_advance_pose_is_jittable_and_exact(camera):
    x0 = quadrotor.hover_state((0.0, 0.0, 1.0), yaw=0.3)
    x1 = jax.jit(R.advance_pose, static_argnums=(1,))(x0, 0.5, 4.0, jnp.asarray([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(x1[:3], [2.0 * np.cos(0.3), 2.0 * np.sin(0.3), 1.0], atol=1e-5)
    np.testing.assert_allclose(quadrotor.euler_angles(x1[3:7]), [0.0, 0.0, 0.8], atol=1e-5)


def test_render_figure_writes_a_png(tmp_path, single_gate, camera):
    from pixelmpc_jax.perception import figures

    x0 = quadrotor.hover_state((GATE_X - 8.0, 0.2, 3.1), yaw=0.05)
    x1 = R.advance_pose(x0, 1 / 40, speed=10.0, body_rates=(0.0, 0.0, -2.0))
    out = figures.render_figure(single_gate, x0, x1, camera, tmp_path / "fig" / "render.png")
    assert out["path"].is_file() and out["path"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert 0.0 < out["aee_px"] < 2.45 and out["max_flow_px"] > 5.0
