"""No ground truth in what a policy is handed (issue #74): on the onboard loop (the rendered frame through the image
detector, the Kalman filter, the gate switch from its estimate, the nominal map of a perturbed course) a policy's
``init`` and ``act`` get what the drone knows, and reading a true quantity fails when the episode is traced.

The episode driver (:func:`~pixelmpc_jax.sim.episode.episode_fn`) is traced with ``jax.eval_shape`` (nothing is
compiled: no closed-loop program of its own) to read the types it hands over; the world it hands over holds the map's
gates, not the ones the world flies.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from standard_race import NOMINAL

from pixelmpc_jax.apps.racing.presets import LOOPS, with_loop
from pixelmpc_jax.apps.racing.race import lap_worlds
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception.detector import Detection
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.sim.policies import Policy
from pixelmpc_jax.world.course import load_course

# What a policy may read. A field added to what the driver hands over must be added here on purpose: if it is true
# (the course flown, the vehicle as it flies, the metric's visibility), it does not belong to a policy.
OBSERVATION_FIELDS = ("x_est", "target_gate", "progress_s", "detection", "position_cov_trace",
                      "association",  # what the estimator made of the candidates of gates painted alike
                      "track")  # the map with its gates where the estimator places them (None: the map as it is)
DETECTION_FIELDS = ("found", "centre", "bbox", "corners", "corners_visible", "gate_id")
POLICY_WORLD_FIELDS = ("track", "target_speed", "camera", "dof")

HOVER = quadrotor.hover_control(quadrotor.QuadParams())


def onboard_config(max_time_s: float = 1.0) -> episode_lib.EpisodeConfig:
    """The onboard loop as a race flies it (:data:`~pixelmpc_jax.apps.racing.presets.LOOPS`)."""
    return with_loop(NOMINAL.replace(perturb=True), "onboard").replace(max_time_s=max_time_s).episode_config()


@pytest.fixture(scope="module")
def perturbed_world() -> env_lib.World:
    """A lap's world on the onboard loop: the nominal AlphaPilot course as the map, its gates perturbed where the
    world flies them."""
    assert LOOPS["onboard"]["map"] == "surveyed"
    stacked = lap_worlds(env_lib.make_world(load_course(), target_speed=10.0), [0], perturb=True, map="surveyed")
    return jax.tree_util.tree_map(lambda leaf: leaf[0], stacked)


def hovering(read=None) -> Policy:
    """A policy that hovers and, with ``read(obs, world)``, reads something of what ``act`` is handed."""

    def act(state, obs, world):
        if read is not None:
            read(obs, world)
        return HOVER, state, jnp.zeros((2, quadrotor.STATE_DIM))

    return Policy(init=lambda key, world: jnp.zeros(()), act=act, name="hover")


def trace_episode(policy: Policy, config: episode_lib.EpisodeConfig, world: env_lib.World):
    return jax.eval_shape(episode_lib.episode_fn(policy, config), world, jax.random.key(0))


def test_the_onboard_world_differs_from_its_map(perturbed_world):
    """The checks below mean something only where the truth differs from what the drone knows: most gates stand
    away from where the map has them (the AlphaPilot bounds hold some in place, turning them only)."""
    flown, mapped = perturbed_world.course.gates.centre, perturbed_world.track.gates.centre
    moved = np.linalg.norm(np.asarray(flown[:, :2] - mapped[:, :2]), axis=-1)
    assert np.sum(moved > 0.3) >= 6 and np.max(moved) > 2.0


@pytest.mark.parametrize("loop", ["truth", "onboard"])
def test_a_policy_is_handed_the_allow_listed_fields_only(perturbed_world, loop):
    """On every loop ``init`` and ``act`` get exactly the allow-listed fields: the observation without the metric's
    visibility, the world without the course flown, the true vehicle and the detector's noise."""
    handed = {}

    def init(key, world):
        handed["init"] = world
        return jnp.zeros(())

    def act(state, obs, world):
        handed["obs"], handed["world"] = obs, world
        return HOVER, state, jnp.zeros((2, quadrotor.STATE_DIM))

    config = with_loop(NOMINAL.replace(perturb=True), loop).episode_config()
    trace_episode(Policy(init=init, act=act, name="recorder"), config, perturbed_world)
    assert type(handed["obs"])._fields == OBSERVATION_FIELDS
    assert tuple(f.name for f in dataclasses.fields(type(handed["obs"].detection))) == DETECTION_FIELDS
    assert type(handed["obs"].detection) is Detection
    for world in (handed["init"], handed["world"]):
        assert type(world) is env_lib.PolicyWorld and type(world)._fields == POLICY_WORLD_FIELDS


@pytest.mark.parametrize("where, name", [
    ("obs", "target_visibility"),  # the metric's visibility of the target, from the true pose
    ("world", "course"),  # the gates as they stand, not as the map has them
    ("world", "plant_params"),  # the vehicle as it flies
    ("world", "detector_noise_px"),
    ("world", "detector_dropout"),
])
def test_a_policy_reading_a_true_quantity_fails_on_the_onboard_loop(perturbed_world, where, name):
    def read(obs, world):
        getattr({"obs": obs, "world": world}[where], name)

    with pytest.raises(AttributeError, match=name):
        trace_episode(hovering(read), onboard_config(), perturbed_world)


def test_a_policy_reading_the_course_in_init_fails_on_the_onboard_loop(perturbed_world):
    policy = hovering()._replace(init=lambda key, world: world.course.gates.centre)
    with pytest.raises(AttributeError, match="course"):
        trace_episode(policy, onboard_config(), perturbed_world)


def test_on_a_perturbed_onboard_lap_a_policy_is_given_the_map(perturbed_world):
    """The world a policy is handed (:func:`~pixelmpc_jax.sim.env.policy_world`, which the traced episode hands to
    ``init`` and ``act``) holds the map's gates, not the perturbed ones the world flies."""
    handed = {}

    def init(key, world):
        handed["init"] = world
        return jnp.zeros(())

    def act(state, obs, world):
        handed["act"] = world
        return HOVER, state, jnp.zeros((2, quadrotor.STATE_DIM))

    trace_episode(Policy(init=init, act=act, name="recorder"), onboard_config(), perturbed_world)
    known = env_lib.policy_world(perturbed_world)
    for world in (handed["init"], handed["act"]):  # the traced episode's: the same arrays' shapes
        assert jax.tree_util.tree_structure(world) == jax.tree_util.tree_structure(known)
    mapped = np.asarray(perturbed_world.track.gates.centre)
    flown = np.asarray(perturbed_world.course.gates.centre)
    np.testing.assert_array_equal(np.asarray(known.track.gates.centre), mapped)
    assert np.max(np.linalg.norm(np.asarray(known.track.gates.centre) - flown, axis=-1)) > 2.0
