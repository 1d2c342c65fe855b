"""The closed loop: a policy at 40 Hz flying the racing environment, logged tick by tick.

Each 1/40 s tick the driver asks the environment for an observation (:mod:`pixelmpc_jax.sim.env`: detection
and estimate), the policy for a command (:mod:`pixelmpc_jax.sim.policies`; it is given the observation and the
world as the drone knows it, :class:`~pixelmpc_jax.sim.env.PolicyWorld`, no truth), and the environment for the
tick flown (plant, gate passage, collisions, the episode's end), then writes the tick into preallocated logs, the
truth the metrics need (the target's visibility from the true pose) among them. An episode is one
``lax.while_loop`` over ticks, so a finished lap stops computing; a batch of episodes (seeds, speeds, course
perturbations) is a ``vmap`` of it, split over the devices (:mod:`pixelmpc_jax.devices`), and runs until its last
member ends.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.devices import gather_batch, shard_batch
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import association as association_lib
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim.env import Observation, SimState, World
from pixelmpc_jax.sim.policies import Policy


@dataclasses.dataclass(frozen=True)
class EpisodeConfig(env_lib.EnvConfig):
    """Static settings of a closed-loop episode: the environment's (:class:`~pixelmpc_jax.sim.env.EnvConfig`:
    time limit, detector, estimator, ...) and the driver's.

    Attributes:
        logged_prediction_steps: how many steps of the controller's predicted target pixel to log per
            tick (for the onboard video); controllers without a pixel state log zeros.
    """

    logged_prediction_steps: int = 41


class EpisodeLog(NamedTuple):
    """One episode (leading batch axes under vmap). M = max ticks; entries past ``num_ticks`` are zero.

    Attributes:
        states: (M+1, 10) true state at each tick, the start included.
        controls: (M, 4) commands sent.
        body_rates: (M+1, 3) true body rates.
        visibility: (M+1,) target-gate visibility at each tick, from the true pose (the metric's; no policy sees it).
        target: (M+1,) target gate index at each tick.
        detected: (M,) the detector reported the target at each tick.
        detection_uv: (M, 2) the detected target pixel (normalised).
        predicted_uv: (M, P, 2) the controller's predicted target pixel for the next P-1 steps.
        estimates: (M, 10) the state the controller acted on (the truth, or the filter's mean).
        position_cov_trace: (M,) trace of the estimator's position covariance (0 for the truth), m^2.
        num_ticks: () ticks flown.
        gates_passed: () gates passed in order.
        end_cause: () int32, 0 finished or still flying, else a key of END_NAMES.
        finished: () bool, all gates passed.
        association: (M,) int8, with gates painted alike what became of each tick's candidates (an index of
            :data:`~pixelmpc_jax.perception.association.OUTCOMES`: none in view, accepted, rejected, ambiguous); -1
            (:data:`~pixelmpc_jax.perception.association.NOT_ASSOCIATING`) where each gate has its own hue. None in a
            log built by hand.
        gate_centre_error: (G,) m, for each gate passed, how far the centre the drone held for it (the map's, or
            where the estimator placed it) stood from the gate's true centre at the tick the vehicle passed it; NaN
            for a gate not passed. None in a log built by hand.
        target_centre_est: (M, 3) m, at each tick the centre the drone held for the world's target gate (the map's, or
            where the estimator placed it). None in a log built by hand.
    """

    states: jax.Array
    controls: jax.Array
    body_rates: jax.Array
    visibility: jax.Array
    target: jax.Array
    detected: jax.Array
    detection_uv: jax.Array
    predicted_uv: jax.Array
    estimates: jax.Array
    position_cov_trace: jax.Array
    num_ticks: jax.Array
    gates_passed: jax.Array
    end_cause: jax.Array
    finished: jax.Array
    association: jax.Array | None = None
    gate_centre_error: jax.Array | None = None
    target_centre_est: jax.Array | None = None


class _Carry(NamedTuple):
    sim: SimState
    policy_state: Any
    key: jax.Array
    log: EpisodeLog


def _varying_with(key: jax.Array, tree):
    """``tree`` unchanged, each leaf selected on a flag computed from ``key``.

    Under ``vmap`` every leaf is then batched before the episode's ``while_loop``. The laps end at different ticks,
    so the loop's predicate is batched and vmap batches the whole carry anyway. It finds which carry leaves are
    batched by batching the loop body again until nothing changes, then batches it once more for the batched
    predicate: four passes over the body from the carry as it is built, two from a carry already batched. A batched
    episode traces about 0.5 s faster (1.6 s against 1.1 s on a 2-core AMD EPYC); what it computes is the same (XLA
    drops a select between equal values, and the golden laps hold bit for bit)."""
    flag = jax.random.key_data(key).reshape(-1)[0] == 0
    return jax.tree_util.tree_map(lambda leaf: jnp.where(flag, leaf, leaf), tree)


def episode_fn(policy: Policy, config: EpisodeConfig = EpisodeConfig()) -> Callable:
    """The pure episode ``closed_loop_episode(world, key) -> EpisodeLog`` (jit and vmap it; see :func:`make_runner`).
    Its compiled programs are named for it (``jit_closed_loop_episode``), so a compilation cache or log tells them
    apart from the rest."""
    env = env_lib.make_env(config)
    M = config.max_ticks
    P = config.logged_prediction_steps

    def predicted_pixels(prediction: jax.Array) -> jax.Array:
        if prediction.shape[-1] < quadrotor.STATE_DIM + 2:
            return jnp.zeros((P, 2), jnp.float32)
        uv = prediction[:P, quadrotor.STATE_DIM:quadrotor.STATE_DIM + 2].astype(jnp.float32)
        return jnp.pad(uv, ((0, P - uv.shape[0]), (0, 0)), mode="edge")

    def empty_log(world: World, sim: SimState) -> EpisodeLog:
        x0 = sim.plant.x
        return EpisodeLog(
            states=jnp.zeros((M + 1, quadrotor.STATE_DIM), x0.dtype).at[0].set(x0),
            controls=jnp.zeros((M, quadrotor.CONTROL_DIM), x0.dtype),
            body_rates=jnp.zeros((M + 1, 3), x0.dtype),
            visibility=jnp.zeros((M + 1,), jnp.float32).at[0].set(env_lib.target_visibility(world, sim)),
            target=jnp.zeros((M + 1,), jnp.int32),
            detected=jnp.zeros((M,), jnp.bool_),
            detection_uv=jnp.zeros((M, 2), jnp.float32),
            predicted_uv=jnp.zeros((M, P, 2), jnp.float32),
            estimates=jnp.zeros((M, quadrotor.STATE_DIM), x0.dtype),
            position_cov_trace=jnp.zeros((M,), jnp.float32),
            num_ticks=jnp.asarray(0, jnp.int32),
            gates_passed=jnp.asarray(0, jnp.int32),
            end_cause=jnp.asarray(0, jnp.int32),
            finished=jnp.asarray(False),
            association=jnp.full((M,), association_lib.NOT_ASSOCIATING, jnp.int8),
            gate_centre_error=jnp.full((world.track.num_gates,), jnp.nan, jnp.float32),
            target_centre_est=jnp.zeros((M, 3), jnp.float32),
        )

    def record(log: EpisodeLog, world: World, obs: Observation, u: jax.Array, prediction: jax.Array,
               sim: SimState, passing: jax.Array) -> EpisodeLog:
        """Write tick ``sim.tick - 1``: what was observed and commanded, the state it led to, and the error of the
        drone's centre of the gate ``passing`` (the world's target before the tick) where the tick passed it."""
        tick, num_gates = sim.tick, world.track.num_gates
        known = world.track if obs.track is None else obs.track
        gate = jnp.minimum(passing, num_gates - 1)
        error = jnp.linalg.norm(known.gates.centre[gate] - env_lib.flown_track(world, sim.faults).gates.centre[gate])
        passed = sim.target > passing
        return log._replace(
            target_centre_est=log.target_centre_est.at[tick - 1].set(known.gates.centre[gate].astype(jnp.float32)),
            gate_centre_error=log.gate_centre_error.at[gate].set(
                jnp.where(passed, error.astype(jnp.float32), log.gate_centre_error[gate])),
            states=log.states.at[tick].set(sim.plant.x),
            controls=log.controls.at[tick - 1].set(u),
            body_rates=log.body_rates.at[tick].set(sim.plant.rates),
            visibility=log.visibility.at[tick].set(env_lib.target_visibility(world, sim)),
            target=log.target.at[tick].set(jnp.minimum(sim.target, num_gates - 1)),
            detected=log.detected.at[tick - 1].set(obs.detection.found),
            detection_uv=log.detection_uv.at[tick - 1].set(obs.detection.centre.astype(jnp.float32)),
            predicted_uv=log.predicted_uv.at[tick - 1].set(predicted_pixels(prediction)),
            estimates=log.estimates.at[tick - 1].set(obs.x_est),
            position_cov_trace=log.position_cov_trace.at[tick - 1].set(obs.position_cov_trace),
            association=log.association.at[tick - 1].set(jnp.asarray(obs.association, jnp.int8)),
        )

    def closed_loop_episode(world: World, key: jax.Array) -> EpisodeLog:
        key, key_policy, key_reset = jax.random.split(key, 3)
        sim = env.reset(world, key_reset)
        known = env_lib.policy_world(world)  # the policy reads the map, never the course flown or the true vehicle
        carry = _Carry(sim=sim, policy_state=policy.init(key_policy, known), key=key, log=empty_log(world, sim))

        def body(c: _Carry) -> _Carry:
            key, key_step, key_observe = jax.random.split(c.key, 3)
            sim, obs = env.observe(world, c.sim, key_observe)
            now = known if obs.track is None else known._replace(track=obs.track)  # the gates as estimated
            u, policy_state, prediction = policy.act(c.policy_state, obs, now)
            sim = env.step(world, sim, u, key_step)
            return _Carry(sim=sim, policy_state=policy_state, key=key,
                          log=record(c.log, world, obs, u, prediction, sim, c.sim.target))

        final = jax.lax.while_loop(lambda c: ~c.sim.done, body, _varying_with(key, carry))
        sim = final.sim
        return final.log._replace(num_ticks=sim.tick, gates_passed=jnp.minimum(sim.target, world.track.num_gates),
                                  end_cause=sim.end_cause, finished=env_lib.lap_finished(world, sim))

    return closed_loop_episode


class Runner(NamedTuple):
    """Compiled episode runners. ``single(world, key)``; ``batch(worlds, keys)`` with worlds batched on
    their leading axis (use :func:`~pixelmpc_jax.sim.env.stack_worlds`)."""

    single: Callable[[World, jax.Array], EpisodeLog]
    batch: Callable[[World, jax.Array], EpisodeLog]


def make_runner(policy: Policy, config: EpisodeConfig = EpisodeConfig()) -> Runner:
    """Compiled runners; ``batch`` splits its episodes over every device present, across processes too
    (see :func:`~pixelmpc_jax.devices.shard_batch`), and returns them whole.

    ``single`` compiles with the policy's XLA options (``Policy.compiler_options``: chosen for one controller
    step, e.g. YNNPACK's products for a step on one CPU device, which split each product over the cores).
    ``batch`` compiles with XLA's own kernels: its laps are spread over the devices, one core each, where
    kernels that take every core would contend with the other devices' laps."""
    run = episode_fn(policy, config)
    batch_jit = jax.jit(jax.vmap(run))

    def batch(worlds: World, keys: jax.Array) -> EpisodeLog:
        (worlds, keys), size = shard_batch((worlds, keys))
        logs = gather_batch(batch_jit(worlds, keys))
        return jax.tree_util.tree_map(lambda a: a[:size], logs)

    return Runner(single=jax.jit(run, compiler_options=policy.compiler_options), batch=batch)
