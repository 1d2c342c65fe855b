"""Farneback on rendered pairs against the exact flow, the polar DOF units, and input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import devices
from pixelmpc_jax.perception import flow as F
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render as R

PAPER_DOF_AEE_PX = 2.45  # the paper's DOF flow error; Farneback's own error must stay below it
DT = 1.0 / 40.0

# (name, speed m/s along body x, body rates rad/s)
MOTIONS = (
    ("forward 6 m/s", 6.0, (0.0, 0.0, 0.0)),
    ("forward 10 m/s", 10.0, (0.0, 0.0, 0.0)),
    ("forward 14 m/s", 14.0, (0.0, 0.0, 0.0)),
    ("yaw +2 rad/s", 0.0, (0.0, 0.0, 2.0)),
    ("yaw -2 rad/s + forward 10 m/s", 10.0, (0.0, 0.0, -2.0)),
    ("roll 2 rad/s", 0.0, (2.0, 0.0, 0.0)),
    ("roll -2 rad/s + forward 14 m/s", 14.0, (-2.0, 0.0, 0.0)),
)
# (gate index, distance m, lateral m, height m, yaw offset rad, roll rad): poses on the AlphaPilot course.
POSES = ((0, 8.0, 0.0, 0.0, 0.0, 0.0), (2, 6.0, 0.5, 0.3, 0.15, 0.0), (5, 10.0, -0.5, 0.0, -0.1, 0.2))


@pytest.fixture(scope="module")
def camera():
    return C.default_camera()


@pytest.fixture(scope="module")
def aee_table(camera):
    """AEE (px) of Farneback against the exact flow over the valid pixels, per motion and pose."""
    course = course_lib.load_course()
    starts = [R.pose_before_gate(course.gate(g), d, lat, h, yaw, roll) for g, d, lat, h, yaw, roll in POSES]
    render_batch = devices.compiled(R.render_batch, ("supersample", "chunk"))
    firsts = render_batch(course, jnp.stack(starts), camera)
    nexts_x = jnp.stack([R.advance_pose(x, DT, v, w) for _, v, w in MOTIONS for x in starts])
    nexts = render_batch(course, nexts_x, camera)
    table = {}
    for m, (name, _, _) in enumerate(MOTIONS):
        row = []
        for p, x0 in enumerate(starts):
            k = m * len(starts) + p
            exact, valid = devices.compiled(R.exact_flow)(x0, nexts_x[k], firsts.depth[p], camera)
            measured = F.farneback(np.asarray(firsts.grey[p]), np.asarray(nexts.grey[k]))
            row.append((F.average_endpoint_error(measured, exact, valid), float(np.abs(exact).max())))
        table[name] = row
    print("\nFarneback vs exact flow, AEE px (max |flow| px) per pose:")
    for name, row in table.items():
        print(f"  {name:32s} " + "  ".join(f"{a:.2f} ({mx:.1f})" for a, mx in row))
    return table


@pytest.mark.parametrize("motion", [m[0] for m in MOTIONS])
def test_farneback_matches_exact_flow_below_paper_dof_error(aee_table, motion):
    """Whole image (valid = the point stays in front and in the image at t+1), no border excluded."""
    for aee, max_flow in aee_table[motion]:
        assert aee < PAPER_DOF_AEE_PX, (motion, aee)
        assert max_flow > 1.5  # the motion is not trivially small


def test_farneback_recovers_a_pure_shift():
    rng = np.random.default_rng(0)
    big = np.kron(rng.integers(0, 256, (60, 80)), np.ones((4, 4))).astype(np.float32)
    import cv2

    big = cv2.GaussianBlur(big, (0, 0), 2.0)
    grey0 = np.clip(big[20:173, 20:224], 0, 255).astype(np.uint8)
    grey1 = np.clip(big[17:170, 22:226], 0, 255).astype(np.uint8)  # content moves by (-2, +3)
    flow = F.farneback(grey0, grey1)
    inner = F.border_mask(153, 204, 10)
    np.testing.assert_allclose(np.median(flow[inner], axis=0), [-2.0, 3.0], atol=0.05)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((153, 204), np.float32), "uint8"),
        (np.zeros((153, 204, 3), np.uint8), r"\(H, W\)"),
        (np.zeros((100, 204), np.uint8), r"\(153, 204\)"),
    ],
)
def test_farneback_rejects_bad_images(bad, match):
    good = np.zeros((153, 204), np.uint8)
    with pytest.raises(ValueError, match=match):
        F.farneback(bad, good)
    with pytest.raises(ValueError, match=match):
        F.farneback(good, bad)


def test_farneback_other_size_when_asked():
    img = np.zeros((60, 80), np.uint8)
    assert F.farneback(img, img, shape=None).shape == (60, 80, 2)
    with pytest.raises(ValueError, match="shape"):
        F.farneback(img, np.zeros((61, 80), np.uint8), shape=None)


def test_farneback_parameters_are_the_papers():
    assert F.FARNEBACK_PARAMS == dict(
        pyr_scale=0.5, levels=10, winsize=51, iterations=15, poly_n=5, poly_sigma=1.1, flags=0
    )


def test_polar_units_hand_cases():
    W, H = 204, 153
    flow = np.array([[W * DT * 1.0, 0.0], [0.0, H * DT * 2.0], [-W * DT * 3.0, 0.0]])
    l, theta = F.flow_to_polar(flow, W, H, DT)
    np.testing.assert_allclose(l, [1.0, 2.0, 3.0], rtol=1e-12)
    np.testing.assert_allclose(theta, [0.0, np.pi / 2, np.pi], atol=1e-12)


def test_polar_round_trip_numpy_and_jit():
    rng = np.random.default_rng(1)
    flow = rng.normal(0.0, 5.0, (50, 2))
    l, theta = F.flow_to_polar(flow)
    np.testing.assert_allclose(F.polar_to_flow(l, theta), flow, atol=1e-10)
    to_polar = jax.jit(F.flow_to_polar, static_argnums=(1, 2, 3))
    lj, tj = to_polar(jnp.asarray(flow, jnp.float32), 204, 153, DT)
    np.testing.assert_allclose(lj, l, rtol=1e-5)
    np.testing.assert_allclose(jax.jit(F.polar_to_flow)(lj, tj), flow, atol=1e-4)


def test_half_precision_flow_is_converted_in_float32():
    """DOF training keeps its flow in float16 on the device; the polar units come out in float32."""
    flow = np.random.default_rng(2).normal(0.0, 5.0, (50, 2))
    l16, theta16 = F.flow_to_polar(jnp.asarray(flow, jnp.float16))
    l32, theta32 = F.flow_to_polar(jnp.asarray(jnp.asarray(flow, jnp.float16), jnp.float32))
    assert l16.dtype == theta16.dtype == jnp.float32
    np.testing.assert_array_equal(l16, l32)
    np.testing.assert_array_equal(theta16, theta32)


def test_average_endpoint_error():
    a = np.zeros((2, 2, 2))
    b = np.zeros((2, 2, 2))
    b[0, 0] = [3.0, 4.0]
    assert F.average_endpoint_error(a, b) == pytest.approx(1.25)
    mask = np.array([[True, False], [False, False]])
    assert F.average_endpoint_error(a, b, mask) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="no pixels"):
        F.average_endpoint_error(a, b, np.zeros((2, 2), bool))
    with pytest.raises(ValueError, match="shape"):
        F.average_endpoint_error(a, b, np.ones((3, 2), bool))


def test_flow_colours():
    flow = np.zeros((4, 4, 2), np.float32)
    flow[0, 0] = [1.0, 0.0]  # right: red
    flow[0, 1] = [0.0, 0.0]  # still: black
    rgb = F.flow_to_rgb(flow, max_magnitude=1.0)
    assert rgb.shape == (4, 4, 3) and rgb.dtype == np.uint8
    assert tuple(rgb[0, 0]) == (255, 0, 0)
    assert tuple(rgb[0, 1]) == (0, 0, 0)
    wheel = F.colour_wheel(41)
    assert wheel.shape == (41, 41, 3) and tuple(wheel[0, 0]) == (0, 0, 0)
