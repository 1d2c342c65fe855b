"""Gates found, not assumed: the course's gates stand off the drone's map, the Kalman filter estimates each gate's
offset from the map as states (its prior what the drone was told: the survey's error or the AlphaPilot bounds), the
next gate is seen before it becomes the target, and the controller follows the gates where the filter places them.
No test here flies a closed loop (the suite's budget of compiled closed-loop programs)."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.apps.racing import presets
from pixelmpc_jax.apps.racing.race import lap_worlds
from pixelmpc_jax.perception import association as association_lib
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import eskf as E
from pixelmpc_jax.perception.estimator import EstimatorParams
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import track as track_lib

CONFIG = E.ESKFConfig(map_sigma_m=0.0)
OFFSET = (1.2, -0.8, 0.0, math.radians(4.0))  # the first gate's offset from the map: within its AlphaPilot bounds


@pytest.fixture(scope="module")
def course():
    return course_lib.load_course(), camera_lib.default_camera()


def _standing_before(track, gate_index: int, distance: float):
    gate = track.gate(gate_index)
    return track.start.at[0:3].set(gate.centre - distance * gate.normal)


def test_offset_gates_moves_the_centre_and_turns_about_z_through_it(course):
    track, _ = course
    offset = jnp.zeros((track.num_gates, 4)).at[0].set(jnp.asarray(OFFSET))
    moved = track_lib.offset_gates(track.gates, offset)
    np.testing.assert_allclose(moved.centre[1:], track.gates.centre[1:])
    np.testing.assert_allclose(moved.centre[0], track.gates.centre[0] + jnp.asarray(OFFSET[:3]), atol=1e-6)
    # every corner keeps its distance to the centre and its height; the normal turns by the yaw
    arms = moved.corners()[0] - moved.centre[0]
    np.testing.assert_allclose(np.linalg.norm(arms, axis=-1),
                               np.linalg.norm(track.gates.corners()[0] - track.gates.centre[0], axis=-1), rtol=1e-5)
    turn = math.atan2(float(moved.normal[0, 1]), float(moved.normal[0, 0])) - math.atan2(
        float(track.gates.normal[0, 1]), float(track.gates.normal[0, 0]))
    assert turn == pytest.approx(OFFSET[3], abs=1e-5)


def test_the_gates_jacobian_matches_jacfwd(course):
    track, camera = course
    x = _standing_before(track, 0, 7.0).at[:3].add(jnp.asarray([0.4, -0.3, 0.2]))
    scale = jnp.asarray([camera.width, camera.height])

    def pixels(offset):
        gate = track_lib.offset_gates(track.gates, jnp.zeros((track.num_gates, 4)).at[0].set(offset))
        return camera_lib.project(gate.corners()[0], x, camera)[0] * scale

    _, H, in_front = jax.jit(E.reproject_corners)(x, track.gates.corners()[0], camera)
    assert bool(jnp.all(in_front))
    expected = jax.jit(jax.jacfwd(pixels))(jnp.zeros(4))
    np.testing.assert_allclose(E.gate_jacobian(H, track.gates.corners()[0], track.gates.centre[0]), expected,
                               rtol=1e-4, atol=1e-3)


def _gate_filter(track, x0, gate_std, per_tick: int = 1, spread=(0.05, 0.01, 0.1)):
    estimator = E.make_eskf(CONFIG, spread, detections_per_tick=per_tick)
    return estimator, jax.jit(estimator.step), estimator.init(None, x0, gate_std)


def test_the_filter_finds_a_moved_gate_and_keeps_its_pose_where_the_map_alone_pulls_it_off(course):
    """A drone sure of its pose to 5 cm, 12 m before the first gate, which stands 1.4 m and 4 degrees off the map:
    with the gates as states (prior: the AlphaPilot bounds) the filter moves the gate's centre onto the detections
    and keeps the pose; told the map is right within a surveyed map's 0.2 m, its gate rejects every corner."""
    track, camera = course
    x0 = _standing_before(track, 0, 12.0)
    true_gates = track_lib.offset_gates(track.gates, jnp.zeros((track.num_gates, 4)).at[0].set(jnp.asarray(OFFSET)))
    detection = detector_lib.detect_from_geometry(jax.tree_util.tree_map(lambda a: a[0], true_gates), x0, camera,
                                                  gate_id=0)
    assert bool(detection.found) and int(np.sum(detection.corners_visible)) == 4
    params = EstimatorParams(gates=track.gates, camera=camera, delay_ticks=0)
    gate_std = course_lib.gate_prior_std(track, perturbed=True)
    estimator, step, state = _gate_filter(track, x0, gate_std)
    for _ in range(20):
        estimate, state, info = step(state, None, detection, params)
    assert bool(np.all(info.accepted))
    np.testing.assert_allclose(estimate.gates.centre[0], true_gates.centre[0], atol=0.1)
    # seen head on, 4 degrees of yaw shorten the opening by 0.2 %: the yaw stays about where its prior put it
    assert abs(float(state.latest.gate_offset[0, 3])) < OFFSET[3]
    assert float(jnp.linalg.norm(estimate.mean[:3] - x0[:3])) < 0.05
    np.testing.assert_allclose(estimate.gates.centre[1:], track.gates.centre[1:], atol=1e-6)  # unseen: as mapped
    placed, std = estimator.place_gates(state, track.gates)
    np.testing.assert_allclose(placed.centre, estimate.gates.centre)
    assert float(std[0]) < 0.3 < float(np.max(gate_std[0, :2]))  # the seen gate is found; the others keep their prior
    assert np.all(np.asarray(std[1:]) >= np.max(np.asarray(gate_std)[1:, :2], axis=-1) - 1e-6)

    surveyed = E.make_eskf(E.ESKFConfig(), (0.05, 0.01, 0.1))
    state = surveyed.init(None, x0)
    surveyed_step = jax.jit(surveyed.step)
    for _ in range(20):
        estimate, state, info = surveyed_step(state, None, detection, params)
    assert estimate.gates is None
    assert not np.any(info.accepted)  # the moved gate's corners fail the filter's gate: it cannot see the gate


def test_two_detections_a_tick_update_both_gates_and_refuse_one(course):
    track, camera = course
    x0 = _standing_before(track, 0, 12.0)
    params = EstimatorParams(gates=track.gates, camera=camera, delay_ticks=0)
    first = detector_lib.detect_from_geometry(track.gate(0), x0, camera, gate_id=0)
    gate_std = course_lib.gate_prior_std(track, perturbed=True)
    estimator, step, state = _gate_filter(track, x0, gate_std, per_tick=2)
    nothing = first.replace(found=jnp.asarray(False), corners_visible=jnp.zeros(4, bool), gate_id=jnp.asarray(1))
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), first, nothing)
    estimate, state, _ = step(state, None, both, params)
    assert estimate.detection.corners.shape == (4, 2)  # the target's, first
    with pytest.raises(ValueError, match="2 detector.Detections stacked"):
        estimator.check(state, None, first, params)
    cov = np.asarray(state.latest.cov)
    assert cov.shape == (15 + 4 * track.num_gates,) * 2
    assert cov[15, 15] < float(gate_std[0, 0]) ** 2 and cov[19, 19] == pytest.approx(float(gate_std[1, 0]) ** 2)


def test_gate_prior_std_is_the_survey_and_the_bounds_as_uniform_draws(course):
    track, _ = course
    survey = np.asarray(course_lib.gate_prior_std(track, perturbed=False))
    np.testing.assert_allclose(survey, np.broadcast_to(course_lib.SURVEY_SIGMA, survey.shape), rtol=1e-6)
    bounds = np.abs(np.asarray(track.perturbation_bounds))
    perturbed = np.asarray(course_lib.gate_prior_std(track, perturbed=True))
    np.testing.assert_allclose(perturbed[:, 0], np.hypot(course_lib.SURVEY_SIGMA[0], bounds[:, 0] / math.sqrt(3)),
                               rtol=1e-5)
    np.testing.assert_allclose(perturbed[:, 3], np.hypot(course_lib.SURVEY_SIGMA[3],
                                                         np.deg2rad(bounds[:, 2]) / math.sqrt(3)), rtol=1e-5)
    assert np.max(bounds[:, 0]) >= 2.5  # the AlphaPilot course's bounds reach 2.5 m and more


@pytest.mark.parametrize("perturb, survey_error", [(True, False), (False, True)])
def test_the_worlds_gates_differ_from_the_drones_map(course, perturb, survey_error):
    """A perturbed lap or a lap with the survey's error flies gates that are not where the map the drone (the
    estimator and the policy) reads puts them; each lap its own."""
    track, _ = course
    base = env_lib.make_world(track=track)
    worlds = lap_worlds(base, [300, 301], perturb, "surveyed", survey_error, "estimated")
    assert worlds.course is not None
    moved = np.linalg.norm(np.asarray(worlds.course.gates.centre - worlds.track.gates.centre), axis=-1)  # (2, G)
    assert np.all(np.max(moved, axis=-1) > 0.1) and not np.allclose(moved[0], moved[1])
    np.testing.assert_array_equal(np.asarray(worlds.track.gates.centre[0]), np.asarray(track.gates.centre))
    policy_world = env_lib.policy_world(jax.tree_util.tree_map(lambda a: a[0], worlds))
    np.testing.assert_array_equal(np.asarray(policy_world.track.gates.centre), np.asarray(track.gates.centre))
    assert worlds.gate_std.shape == (2, track.num_gates, 4)
    if survey_error:
        assert np.max(moved) < 6 * max(course_lib.SURVEY_SIGMA[:3])


def test_estimated_gates_need_the_kalman_filter_and_the_maps_accuracy(course):
    with pytest.raises(ValueError, match="need estimator='eskf'"):
        env_lib.EnvConfig(estimator="pf", gates="estimated")
    track, _ = course
    with pytest.raises(ValueError, match="gate_std must be"):
        env_lib.make_world(track=track, gate_std=np.zeros((3, 4)))
    env = env_lib.make_env(env_lib.EnvConfig(estimator="eskf", gates="estimated"))
    with pytest.raises(ValueError, match="World.gate_std"):
        env.reset(env_lib.make_world(track=track), jax.random.PRNGKey(0))
    spec = presets.with_loop(presets.preset("best"), "onboard").replace(gates="estimated")
    assert spec.episode_config().gates == "estimated"
    assert presets.preset("best").replace(gates="estimated").gates == "map"  # nothing estimates on the true state
    assert spec.key() != presets.with_loop(presets.preset("best"), "onboard").key()


def test_the_association_widens_its_gate_by_the_gates_uncertainty(course):
    """The last gate (no other gate near it in the image) 2 m beside where the estimate places it, 8 m ahead: its
    candidate lies beyond the 20 px gate, so the association rejects it from a map taken as exact and names it when
    told the gate's centre is 2 m uncertain."""
    track, camera = course
    last = track.num_gates - 1
    x0 = _standing_before(track, last, 8.0)
    gate = track.gate(last)
    seen = detector_lib.detect_in_view(gate.replace(centre=gate.centre + 2.0 * gate.lateral), x0, camera)
    candidates = detector_lib.Candidates(
        found=jnp.asarray([True, False]), centre=jnp.stack([seen.centre, jnp.zeros(2)]),
        bbox=jnp.stack([seen.bbox, jnp.zeros(4)]), corners=jnp.stack([seen.corners, jnp.zeros((4, 2))]),
        corners_visible=jnp.stack([seen.corners_visible, jnp.zeros(4, bool)]), target=jnp.asarray(last))
    associate = jax.jit(functools.partial(association_lib.associate, config=association_lib.AssociationConfig()))
    _, exact = associate(candidates, x0, track.gates, camera)
    std = jnp.full((track.num_gates,), 2.0)
    detection, uncertain = associate(candidates, x0, track.gates, camera, gate_std=std)
    assert int(exact) == association_lib.REJECTED and int(uncertain) == association_lib.ACCEPTED
    assert bool(detection.found) and int(detection.gate_id) == last


def test_the_race_command_refuses_gate_settings_that_fly_nothing():
    from pixelmpc_jax import cli
    from pixelmpc_jax.commands import race as race_command

    parser = cli.build_parser()
    with pytest.raises(ValueError, match="--gates estimated are the Kalman filter's states"):
        race_command._check_race(parser.parse_args(["race", "--gates", "estimated"]))
    with pytest.raises(ValueError, match="--survey-error draws the gates about the map"):
        race_command._check_race(parser.parse_args(["race", "--survey-error", "--perturb"]))
    spec, _ = race_command.race_spec(parser.parse_args(["race", "--loop", "onboard", "--perturb", "--gates",
                                                         "estimated"]))
    assert spec.gates == "estimated" and spec.episode_config().gates == "estimated"
