"""Gate detectors: projection of the true gate, colour segmentation of rendered frames, and their agreement."""

from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import devices
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as D
from pixelmpc_jax.world import camera as C
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render as R

PX = np.array([204.0, 153.0])
# the clipped geometric detector against the image detector on a flown lap: measured 239/240 frames agreeing on found,
# the centres 0.27 px apart at the median and 0.69 px at the 95th percentile (0.24 and 0.79 px on the 95 frames with
# the gate partly out of view; AMD EPYC 2-core, jax 0.10.2); bounded at about twice that
FOUND_AGREEMENT = 0.98
CENTRE_MEDIAN_PX, CENTRE_P95_PX = 0.5, 1.5
FLOWN_LAP = Path(__file__).resolve().parent / "data" / "detector_lap.npz"  # :func:`record_flown_lap`
render_batch = devices.compiled(R.render_batch, ("supersample", "chunk"))  # the renderer is pure: its caller compiles
# (gate index, distance, lateral, height, yaw offset, roll): fully visible gates on the AlphaPilot course.
VISIBLE = (
    (0, 8.0, 0.0, 0.0, 0.0, 0.0),
    (2, 6.0, 0.5, 0.3, 0.0, 0.0),
    (5, 10.0, -0.5, 0.0, 0.0, 0.0),
    (8, 7.0, 0.0, 0.0, 0.0, 0.0),
    (3, 12.0, -1.5, 0.5, -0.2, 0.0),
    (4, 4.0, 0.0, 0.0, 0.0, 0.4),
    (6, 5.0, 1.5, -0.3, 0.25, -0.3),
)


@pytest.fixture(scope="module")
def camera():
    return C.default_camera()


@pytest.fixture(scope="module")
def course():
    return course_lib.load_course()


@pytest.fixture(scope="module")
def rendered(course, camera):
    poses = jnp.stack([R.pose_before_gate(course.gate(g), *rest) for g, *rest in VISIBLE])
    partial = R.pose_before_gate(course.gate(1), 5.0, 1.0, -0.4, 0.3)  # gate cut by the right image edge
    frames = render_batch(course, jnp.concatenate([poses, partial[None]]), camera)
    return poses, partial, frames


# --------------------------------------------------------------------------------------------------
# From geometry.
# --------------------------------------------------------------------------------------------------


def test_geometry_straight_ahead(camera):
    course = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=20.0)
    gate = course.gate(0)
    x = quadrotor.hover_state((14.0, 0.0, 3.0))
    det = D.detect_from_geometry(gate, x, camera, gate_id=0)
    assert bool(det.found) and int(det.gate_id) == 0
    np.testing.assert_allclose(det.centre, [camera.cx / camera.width, camera.cy / camera.height], atol=1e-6)
    tl, tr, br, bl = np.asarray(det.corners)
    assert tl[0] < tr[0] and bl[0] < br[0] and tl[1] < bl[1] and tr[1] < br[1]
    assert bool(det.corners_visible.all())
    half_w = 0.5 * float(gate.width + 2 * gate.border) * camera.fx / 6.0 / camera.width
    np.testing.assert_allclose(np.asarray(det.bbox)[[0, 2]], [0.5 - half_w, 0.5 + half_w], atol=1e-5)
    # Behind the camera: not found. Turned away 90 deg: out of view, not found.
    behind = quadrotor.hover_state((26.0, 0.0, 3.0))
    assert not bool(D.detect_from_geometry(gate, behind, camera).found)
    aside = quadrotor.hover_state((14.0, 0.0, 3.0), yaw=np.pi / 2)
    assert not bool(D.detect_from_geometry(gate, aside, camera).found)
    # Turned so the gate is partly in view: found, some corners not visible.
    edge = quadrotor.hover_state((14.0, 0.0, 3.0), yaw=0.75)
    det = D.detect_from_geometry(gate, edge, camera)
    assert bool(det.found) and 0 < int(det.corners_visible.sum()) < 4


def test_geometry_noise_dropout_and_vmap(camera, course):
    gate = course.gate(2)
    x = R.pose_before_gate(gate, 6.0)
    clean = D.detect_from_geometry(gate, x, camera)
    keys = jax.random.split(jax.random.key(0), 4000)
    detect = jax.jit(jax.vmap(lambda k: D.detect_from_geometry(gate, x, camera, k, 1.5, 0.25)))
    noisy = detect(keys)
    err_px = (np.asarray(noisy.corners) - np.asarray(clean.corners)) * PX
    np.testing.assert_allclose(err_px.std(axis=0), 1.5, rtol=0.08)
    np.testing.assert_allclose(err_px.mean(axis=0), 0.0, atol=0.15)
    centre_px = (np.asarray(noisy.centre) - np.asarray(clean.centre)) * PX
    np.testing.assert_allclose(centre_px.std(axis=0), 1.5, rtol=0.08)
    assert abs(float(noisy.found.mean()) - 0.75) < 0.03
    none = D.detect_from_geometry(gate, x, camera, keys[0], 0.0, 1.0)
    assert not bool(none.found)
    # vmap == one call
    single = D.detect_from_geometry(gate, x, camera, keys[1], 1.5, 0.25)
    np.testing.assert_allclose(single.corners, noisy.corners[1], atol=1e-6)
    assert bool(single.found) == bool(noisy.found[1])


@pytest.mark.parametrize("quad, box, overlaps", [
    ([[-0.5, 0.2], [0.5, 0.2], [0.5, 0.6], [-0.5, 0.6]], [0.0, 0.2, 0.5, 0.6], True),  # cut by the left border
    ([[0.5, -1.0], [2.0, 0.5], [0.5, 2.0], [-1.0, 0.5]], [0.0, 0.0, 1.0, 1.0], True),  # holds the whole image
    ([[0.2, 0.2], [0.4, 0.2], [0.4, 0.3], [0.2, 0.3]], [0.2, 0.2, 0.4, 0.3], True),  # inside
    ([[0.8, -0.4], [1.4, 0.2], [0.8, 0.8], [0.2, 0.2]], [0.2, 0.0, 1.0, 0.8], True),  # a diamond over two borders
    ([[2.0, 2.0], [3.0, 2.0], [3.0, 3.0], [2.0, 3.0]], [0.0, 0.0, 0.0, 0.0], False),  # off the image
])
def test_the_clipped_box_is_the_box_of_the_outline_cut_to_the_image(quad, box, overlaps):
    got, meets = D._clipped_box(jnp.asarray(quad, jnp.float32))
    np.testing.assert_allclose(got, box, atol=1e-6)
    assert bool(meets) == overlaps


def test_a_gate_half_out_of_the_image_is_reported_by_its_visible_part_only(camera):
    """Turned so the gate's left half leaves the image: the clipped detector reports the right corners only, no
    corner outside the image, and a centre inside the visible part (the ideal projection's lies on the border);
    with the whole gate in view the two reports are one."""
    course = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=20.0)
    gate = course.gate(0)
    ahead = quadrotor.hover_state((14.0, 0.0, 3.0))
    whole, ideal_whole = D.detect_in_view(gate, ahead, camera), D.detect_from_geometry(gate, ahead, camera)
    for field in ("found", "centre", "corners", "corners_visible"):
        np.testing.assert_array_equal(getattr(whole, field), getattr(ideal_whole, field))
    # the box holds the frame's depth (its front face, nearer, is seen a little larger)
    box = np.asarray(whole.bbox)
    assert np.all(box[:2] <= np.asarray(ideal_whole.bbox)[:2]) and np.all(box[2:] >= np.asarray(ideal_whole.bbox)[2:])
    np.testing.assert_allclose(box, ideal_whole.bbox, atol=2.0 / 204)
    # turned right by the half field of view: the gate centre's image on the left border
    half_fov = float(np.arctan(camera.cx / camera.fx))
    x = quadrotor.hover_state((14.0, 0.0, 3.0), yaw=-half_fov)
    ideal, seen = D.detect_from_geometry(gate, x, camera), D.detect_in_view(gate, x, camera)
    assert bool(seen.found) and bool(ideal.found)
    assert float(ideal.centre[0]) == pytest.approx(0.0, abs=1e-3)  # the ideal centre: on the border
    np.testing.assert_array_equal(seen.corners_visible, [False, True, True, False])  # TR, BR in view
    corners, ideal_corners = np.asarray(seen.corners), np.asarray(ideal.corners)
    np.testing.assert_array_equal(corners[[0, 3]], 0.0)  # nothing reported of the corners out of view
    np.testing.assert_array_equal(corners[[1, 2]], ideal_corners[[1, 2]])
    box = np.asarray(seen.bbox)
    outer, _, _ = C.project(gate.outer_corners(), x, camera)
    assert box[0] == 0.0 and box[2] == pytest.approx(float(np.max(outer[:, 0])), abs=2.0 / 204)  # cut at the border
    assert 0.0 <= box[1] < box[3] <= 1.0
    # no diagonal whole in view: the centre of the visible outline's box, inside the image
    np.testing.assert_allclose(seen.centre, 0.5 * (box[:2] + box[2:]), atol=1e-6)
    assert float(seen.centre[0]) > 0.05 and float(ideal.centre[0]) < 0.01
    # out of view altogether: nothing of the gate in the report
    away = D.detect_in_view(gate, quadrotor.hover_state((14.0, 0.0, 3.0), yaw=np.pi / 2), camera)
    assert not bool(away.found)
    np.testing.assert_array_equal(away.centre, 0.5)
    np.testing.assert_array_equal(away.bbox, 0.0)
    np.testing.assert_array_equal(away.corners, 0.0)


def test_the_clipped_detector_takes_a_diagonals_midpoint_when_only_its_two_ends_are_in_view(camera):
    """1.5 m before a gate taller than the image, rolled: one diagonal's corners in view, the other's out (the image
    detector's rule: the diagonal's midpoint is the centre)."""
    gate = course_lib.straight_course(num_gates=1, height=3.0, first_gate_x=20.0).gate(0)
    for roll, diagonal in ((0.6, [0, 2]), (-0.6, [1, 3])):
        q = quadrotor.quat_from_euler(jnp.asarray(roll), jnp.asarray(0.0), jnp.asarray(0.0))
        x = quadrotor.hover_state((18.5, 0.0, 3.0)).at[3:7].set(q)
        seen = D.detect_in_view(gate, x, camera)
        visible = np.zeros(4, bool)
        visible[diagonal] = True
        assert bool(seen.found)
        np.testing.assert_array_equal(seen.corners_visible, visible)
        np.testing.assert_allclose(np.asarray(seen.corners)[diagonal].mean(0), seen.centre, atol=1e-6)


def record_flown_lap() -> None:
    """Fly the lap :data:`FLOWN_LAP` holds and write it (``python tests/test_detector.py``): nominal MPPI, 128 samples
    over 40 steps, on the AlphaPilot course at 8.5 m/s, seed 0, for 6 s (240 ticks). The test reads the lap instead of
    flying it: what it checks is the two detectors on the frames of a flown lap, not the controller, and flying it cost
    the suite an episode's compilation (7 s on a 2-core AMD EPYC)."""
    from pixelmpc_jax.control.pixelmpc import paper_mppi_config
    from pixelmpc_jax.sim import env as env_lib
    from pixelmpc_jax.sim import episode as episode_lib
    from pixelmpc_jax.sim import policies

    policy = policies.nominal_mppi_policy(paper_mppi_config(num_samples=128, horizon=40))
    world = env_lib.make_world(course_lib.load_course(), target_speed=8.5)
    log = episode_lib.make_runner(policy, episode_lib.EpisodeConfig(max_time_s=6.0)).single(
        world, jax.random.PRNGKey(0))
    n = int(log.num_ticks)
    FLOWN_LAP.parent.mkdir(exist_ok=True)
    np.savez_compressed(FLOWN_LAP, states=np.asarray(log.states)[:n], target=np.asarray(log.target)[:n])


def test_the_geometric_detector_agrees_with_the_image_detector_on_a_flown_lap(camera, course):
    """Frames rendered along a short nominal MPPI lap on the AlphaPilot course, recorded in :data:`FLOWN_LAP` (the
    gates in view, partly in view, out of view), each looking for the lap's target gate: the clipped geometric
    detector finds the gate where the image detector does, with the centre near the image detector's, the gates
    partly out of view included.

    Tolerances measured on this lap (seed 0, 8.5 m/s, 240 ticks): :data:`FOUND_AGREEMENT`, :data:`CENTRE_MEDIAN_PX`,
    :data:`CENTRE_P95_PX`."""
    with np.load(FLOWN_LAP) as lap:
        states, targets = lap["states"], lap["target"]
    n = len(states)
    agreement = D.image_agreement(course, states, targets, camera)
    found_geometry, found_image = agreement["found_geometry"], agreement["found_image"]
    error, partial = agreement["centre_error_px"], agreement["partial"]
    both = np.isfinite(error)
    print(f"\n{n} frames, {int(partial.sum())} partly out of view; found agree on "
          f"{np.mean(found_geometry == found_image):.3f}; centre error median {np.median(error[both]):.2f} px, "
          f"p95 {np.percentile(error[both], 95):.2f} px; partly out of view: median "
          f"{np.median(error[both & partial]):.2f} px, p95 {np.percentile(error[both & partial], 95):.2f} px")
    assert n == 240 and partial.sum() >= 60
    assert np.mean(found_geometry == found_image) >= FOUND_AGREEMENT
    for frames in (both, both & partial):
        assert np.median(error[frames]) <= CENTRE_MEDIAN_PX and np.percentile(error[frames], 95) <= CENTRE_P95_PX


# --------------------------------------------------------------------------------------------------
# From an image.
# --------------------------------------------------------------------------------------------------


def test_image_and_geometry_centres_agree(rendered, course, camera):
    poses, _, frames = rendered
    errors = []
    for k, (g, *_) in enumerate(VISIBLE):
        geometric = D.detect_from_geometry(course.gate(g), poses[k], camera, gate_id=g)
        assert bool(geometric.found) and bool(geometric.corners_visible.all())
        seen = D.detect_from_image(np.asarray(frames.rgb[k]), g, camera)
        assert bool(seen.found) and int(seen.gate_id) == g
        assert bool(np.all(seen.corners_visible)), g
        errors.append(np.hypot(*((seen.centre - np.asarray(geometric.centre)) * PX)))
        corner_err = np.hypot(*((seen.corners - np.asarray(geometric.corners)) * PX).T)
        assert corner_err.max() < 2.0, (g, corner_err)
        box_err = np.abs((seen.bbox - np.asarray(geometric.bbox)) * np.tile(PX, 2))
        assert box_err.max() < 2.0, (g, box_err)
    print("\ncentre disagreement image vs geometry (px):", np.round(errors, 2))
    assert max(errors) < 2.0


def test_partly_visible_gate(rendered, course, camera):
    _, partial, frames = rendered
    geometric = D.detect_from_geometry(course.gate(1), partial, camera, gate_id=1)
    seen = D.detect_from_image(np.asarray(frames.rgb[-1]), 1, camera)
    assert bool(seen.found) and bool(geometric.found)
    assert not seen.corners_visible.all()
    # Every corner the image detector reports is a real corner, seen by the geometry too.
    vis = np.asarray(seen.corners_visible)
    assert vis.any() and np.all(np.asarray(geometric.corners_visible)[vis])
    err = np.hypot(*((seen.corners[vis] - np.asarray(geometric.corners)[vis]) * PX).T)
    assert err.max() < 2.0


def test_a_sliver_of_opening_at_the_image_border_gives_no_false_corner(course, camera):
    """A frame of a flown lap (the `paper` preset on the onboard loop, 2.6 s in): gate 0 at the top of the image, its
    opening a sliver between the frame's bottom bar and the image's top border. The opening's 4-gon has a vertex in
    the middle of that bar, where the outline runs straight; the image detector once reported it as the bottom-right
    corner, 10 px from that corner's projection, and the Kalman filter followed it 1.8 m. Every corner reported is the
    geometry's, within 1 px; the bottom-right one, 0.4 px inside the border, is not."""
    state = jnp.asarray([17.370054, -8.827042, 6.0462513, 0.5428202, -0.17202003, 0.25113127, 0.7827441,
                         -0.24827197, 8.98472, 0.4692008], jnp.float32)
    frame = render_batch(course, state[None], camera, supersample=1)
    seen = D.detect_from_image(np.asarray(frame.rgb[0]), 0, camera)
    ideal = D.detect_from_geometry(course.gate(0), state, camera, gate_id=0)
    visible = np.asarray(seen.corners_visible)
    assert bool(seen.found) and visible.tolist() == [False, False, False, True]
    error = np.hypot(*((np.asarray(seen.corners)[visible] - np.asarray(ideal.corners)[visible]) * PX).T)
    assert error.max() < 1.0
    # the vertex on the bar: its two sides meet at nearly 180 degrees
    sliver = np.array([[131.5, 0.5], [150.5, 0.5], [142.5, 2.5], [131.5, 4.5]])
    assert D._interior_angles_deg(sliver)[2] > 170.0
    np.testing.assert_allclose(D._interior_angles_deg(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])),
                               90.0)


def test_image_detector_takes_a_frame_and_misses_absent_gates(rendered, camera):
    _, _, frames = rendered
    frame = jax.tree_util.tree_map(lambda a: a[0], frames)
    seen = D.detect_from_image(frame, VISIBLE[0][0], camera)
    assert bool(seen.found)
    blank = np.full((153, 204, 3), 128, np.uint8)
    assert not bool(D.detect_from_image(blank, 0, camera).found)


def test_a_triangular_opening_gives_no_corners_not_an_error(camera):
    """A frame whose opening is a triangle (a convex hull of 3 vertices, which ``cv2.approxPolyN`` refuses):
    found, no corner, the centre of the frame's box."""
    gate_id = 3
    hsv = np.zeros((153, 204, 3), np.uint8)
    hsv[40:110, 60:140] = (round(R.gate_hue(gate_id) * 180), 255, 200)  # the frame's paint
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    cv2.fillPoly(rgb, [np.array([[90, 60], [110, 60], [90, 80]], np.int32)], (0, 0, 0))  # the opening
    seen = D.detect_from_image(rgb, gate_id, camera)
    assert bool(seen.found) and not np.any(seen.corners_visible)
    np.testing.assert_allclose(seen.centre * PX, [100.0, 75.0], atol=1e-4)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((153, 204, 3), np.float32), "uint8"),
        (np.zeros((153, 204), np.uint8), r"\(153, 204, 3\)"),
        (np.zeros((204, 153, 3), np.uint8), r"\(153, 204, 3\)"),
    ],
)
def test_image_detector_rejects_bad_images(bad, match, camera):
    with pytest.raises(ValueError, match=match):
        D.detect_from_image(bad, 0, camera)


def test_the_agreement_summary_counts_frames_and_takes_centres_where_both_found():
    """:func:`detector_agreement.summarise` on frames built by hand: agreement over every frame, the centre's
    median and 95th percentile over the frames both detectors found, and over those partly out of view."""
    from pixelmpc_jax.apps.experiments import detector_agreement as A

    error = np.array([0.5, 1.0, np.nan, 3.0, 10.0, np.nan])
    frames = {"found_geometry": np.array([True, True, False, True, True, False]),
              "found_image": np.array([True, True, True, True, True, False]),
              "partial": np.array([False, True, False, True, True, False]), "centre_error_px": error}
    s = A.summarise(frames)
    assert (s["frames"], s["partial_frames"], s["found_image_only"], s["found_geometry_only"]) == (6, 3, 1, 0)
    assert s["found_agree"] == pytest.approx(5 / 6)
    assert s["centre"]["frames"] == 4 and s["centre"]["median_px"] == pytest.approx(2.0)
    assert s["centre_partial"]["frames"] == 3 and s["centre_partial"]["median_px"] == pytest.approx(3.0)
    assert s["centre"]["p95_px"] == pytest.approx(np.percentile([0.5, 1.0, 3.0, 10.0], 95))
    record = {"num_ticks": np.array([2, 3]), "states": np.arange(2 * 4 * 10).reshape(2, 4, 10),
              "target": np.array([[0, 1, 1, 1], [2, 2, 3, 3]])}
    states, targets = A.lap_frames(record, 1)
    assert states.shape == (3, 10) and targets.tolist() == [2, 2, 3]


def test_the_agreement_command_refuses_a_file_that_is_no_per_tick_record(tmp_path, capsys):
    from pixelmpc_jax import cli

    np.savez(tmp_path / "other.npz", states=np.zeros((1, 2, 10)))
    with pytest.raises(SystemExit) as exc:
        cli.main(["experiment", "detector-agreement", str(tmp_path / "other.npz"), "--out", str(tmp_path / "out")])
    assert exc.value.code == 2 and "is not a per-tick record: it lacks target" in capsys.readouterr().err


if __name__ == "__main__":
    record_flown_lap()
