"""The closed loop from Python (apps/racing/race.py): ``race`` flies a RaceSpec as ``run_laps`` and ``pixelmpc race``
fly it, ``fly`` one's own controller or course, both returning a RaceResult of laps, metrics and per-tick arrays; and
a course of one's own from its gates' centres (world/course.py)."""

import jax.numpy as jnp
import numpy as np
import pytest
import standard_race
from standard_race import BATCH, TICKS

from pixelmpc_jax import (
    EpisodeConfig,
    Policy,
    RaceResult,
    course_from_gates,
    fly,
    load_course,
    make_world,
    quadrotor,
    race,
)
from pixelmpc_jax.apps.racing import race as race_lib

SMALL_NOMINAL = standard_race.NOMINAL.config


def test_a_course_from_gates_faces_each_gate_the_way_it_is_flown():
    track = course_from_gates([[10.0, 0.0, 3.0], [20.0, 10.0, 4.0], [20.0, 20.0, 4.0]], start=(0.0, 0.0, 3.0))
    normals = np.asarray(track.gates.rotation[:, :, 0])  # (G, 3): [normal, lateral, up] columns
    expected = np.asarray([[20.0, 10.0], [10.0, 20.0], [0.0, 10.0]])  # from the point before to the point after
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(normals[:, :2], expected, atol=1e-6)
    np.testing.assert_allclose(normals[:, 2], 0.0, atol=1e-7)
    np.testing.assert_allclose(track.start, quadrotor.hover_state((0.0, 0.0, 3.0)), atol=1e-7)  # heading gate 1
    assert track.names == ("Gate1", "Gate2", "Gate3") and np.all(np.diff(np.asarray(track.path_gate_s)) > 0)
    assert float(track.gates.width[0]) == pytest.approx(1.8) and float(track.gates.height[0]) == pytest.approx(1.85)


@pytest.mark.parametrize("centres, start, match", [
    ([10.0, 0.0, 3.0], (0.0, 0.0, 3.0), r"\(G, 3\)"),
    ([[10.0, 0.0, np.nan]], (0.0, 0.0, 3.0), r"\(G, 3\)"),
    ([[10.0, 0.0, 3.0]], (0.0, 0.0), "start"),
    ([[10.0, 0.0, 0.5]], (0.0, 0.0, 3.0), "below the floor"),
    ([[0.0, 0.0, 4.0]], (0.0, 0.0, 3.0), "one place"),
])
def test_a_course_from_gates_refuses_what_cannot_be_flown(centres, start, match):
    with pytest.raises(ValueError, match=match):
        course_from_gates(centres, start=start)


def test_race_flies_a_spec_as_run_laps_does_and_fly_the_same_laps_from_its_world():
    """One implementation: ``race`` gives ``run_laps``' laps; ``fly`` with the spec's controller, world and loop gives
    them too; the per-tick arrays are each lap's, states (S, 10) and controls (S - 1, 4)."""
    spec = standard_race.NOMINAL.replace(laps=2, seed=3)
    result = race(spec, batch_size=BATCH)
    assert isinstance(result, RaceResult) and result.controller == "mppi"
    assert result.laps == race_lib.run_laps(spec, batch_size=BATCH, progress=False)["laps"]
    assert [lap["seed"] for lap in result.laps] == [3, 4] and result.aggregate["num_laps"] == 2
    assert result.ticks[0]["states"].shape == (TICKS + 1, 10) and result.ticks[0]["controls"].shape == (TICKS, 4)
    assert np.isnan(result.lap_times).all() and [lap["crash"] for lap in result.laps] == ["timeout", "timeout"]
    flown = fly("mppi", make_world(load_course(), target_speed=10.0), config=spec.config, laps=2, seed=3,
                episode=spec.episode_config(), batch_size=BATCH)
    assert flown.laps == result.laps
    for mine, theirs in zip(flown.ticks, result.ticks):
        np.testing.assert_array_equal(mine["states"], theirs["states"])
        np.testing.assert_array_equal(mine["controls"], theirs["controls"])


def test_fly_flies_a_policy_of_ones_own_on_a_course_of_ones_own():
    """A hand-written Policy on a two-gate course: hover, and the lap times out where it started; cut the thrust
    (the same policy, its thrust read from the world's target speed: one program), and the vehicle falls from 3 m to
    the ground (less its 0.1 m radius) in about 0.77 s, where the lap ends."""
    hover = quadrotor.hover_control(quadrotor.QuadParams())

    def act(state, obs, world):  # full hover thrust at a target speed above 1 m/s, none below
        return hover * jnp.asarray([1.0, 1.0, 1.0, world.target_speed > 1.0]), state, jnp.zeros((2, 10))

    mine = Policy(init=lambda key, world: jnp.zeros(()), act=act, name="hover")
    course = course_from_gates([[15.0, 0.0, 3.0], [30.0, 8.0, 3.0]])
    episode = EpisodeConfig(max_time_s=1.5)
    result = fly(mine, make_world(course, target_speed=6.0), episode=episode, seed=5)
    lap, ticks = result.laps[0], result.ticks[0]
    assert result.controller == "hover" and lap["seed"] == 5 and lap["crash"] == "timeout"
    assert ticks["states"].shape == (61, 10) and lap["gates_passed"] == 0
    np.testing.assert_allclose(ticks["controls"], np.broadcast_to(hover, (60, 4)))
    assert np.max(np.abs(ticks["states"][:, :3] - ticks["states"][0, :3])) < 0.2
    fallen = fly(mine, make_world(course, target_speed=0.5), episode=episode, seed=5)
    lap = fallen.laps[0]
    assert lap["crash"] == "ground" and not lap["success"] and 0.7 <= lap["flight_time_s"] <= 0.9
    assert np.all(fallen.ticks[0]["controls"][:, 3] == 0.0) and fallen.ticks[0]["states"][-1, 2] < 0.2


@pytest.mark.parametrize("kwargs, match", [
    ({"laps": 0}, "laps and batch_size"),
    ({"batch_size": 1.5}, "laps and batch_size"),
    ({"seed": "0"}, "seed"),
    ({"world": load_course()}, "World"),
    ({"controller": "lqr"}, "controller must be one of"),
    ({"controller": Policy(init=None, act=None, name="mine"), "config": SMALL_NOMINAL}, "brings its own"),
])
def test_fly_refuses_bad_settings_before_it_compiles(kwargs, match):
    with pytest.raises(ValueError, match=match):
        fly(**kwargs)
