"""The rollout: N control sequences flown through a one-sample model from one state, and what they cost.

A running cost comes in one of three layouts: written for one sample (``running_cost(x, u, t, params) ->
scalar``, vmapped here), for every sample at a step (:class:`BatchCost`), or for every step and sample at once
(:class:`TrajectoryCost`); the last two let the compiler vectorise costs with inner reductions better. A
:class:`Prefix` gives the first steps of the horizon their own model and cost.

* :func:`rollout_costs`: (N,) total costs of N control sequences, what an MPPI iteration weighs.
* :func:`rollout_cost`, :func:`rollout_states`: one sequence's total cost, and the states it visits.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp

from pixelmpc_jax.control.mppi_checks import checked_costs, checked_trajectory_costs


class Prefix(NamedTuple):
    """The first ``steps`` steps of the horizon with their own one-sample model and cost.

    The rest of the horizon uses the controller's main ``dynamics`` and ``running_cost``. Both parts see
    the same state shape. Use it to confine a costly part of the model (a network that only feeds a cost
    counted early in the horizon) to where it matters; each part is its own ``lax.scan``.
    """

    steps: int
    dynamics: Callable
    running_cost: Callable


@dataclasses.dataclass(frozen=True)
class BatchCost:
    """A running cost written for every sample at once: ``fn(X (N, n), U (N, m), t, params) -> (N,)``.

    MPPI calls ``fn`` on each horizon step's batch of predicted states (``vmap``-ed over the steps) instead of
    vmapping a one-sample cost; the cost can then lay its work out with the samples on the last (contiguous)
    axis. Called with one sample, ``BatchCost(fn)(x, u, t, params)`` runs ``fn`` on a batch of one.
    """

    fn: Callable

    def __call__(self, x, u, t, params):
        return checked_costs(self.fn(x[None], u[None], t, params), 1, self.fn, batch=True)[0]


@dataclasses.dataclass(frozen=True)
class TrajectoryCost:
    """A running cost written for every step and sample at once: ``fn(X (T, N, n), U (T, N, m), steps (T,), params)
    -> (T, N)``, where ``X[t]`` is the state reached by ``U[t]`` at horizon step ``steps[t]``.

    MPPI calls ``fn`` once on all the predicted states of a run of steps charged by this cost, so the cost can
    lay its work out over the whole (T, N) batch (XLA then runs it as a few large kernels instead of many
    small ones at every step). Called with one sample, ``TrajectoryCost(fn)(x, u, t, params)`` runs ``fn`` on a
    batch of one.
    """

    fn: Callable

    def __call__(self, x, u, t, params):
        costs = self.fn(x[None, None], u[None, None], jnp.asarray(t)[None], params)
        return checked_trajectory_costs(costs, (1, 1), self.fn)[0, 0]


def _stage_costs(cost: Callable, X: jax.Array, U: jax.Array, t, params) -> jax.Array:
    """(N,) running costs of a batch of states at one step (samples on axis 0)."""
    N = X.shape[0]
    if isinstance(cost, BatchCost):
        return checked_costs(cost.fn(X, U, t, params), N, cost.fn, batch=True)
    return checked_costs(jax.vmap(cost, in_axes=(0, 0, None, None))(X, U, t, params), N, cost, batch=False)


def _trajectory_costs(cost: Callable, X: jax.Array, U: jax.Array, ts: jax.Array, params) -> jax.Array:
    """(T, N) running costs of the states X (T, N, n) reached by U (T, N, m) at horizon steps ts (T,)."""
    if isinstance(cost, TrajectoryCost):
        return checked_trajectory_costs(cost.fn(X, U, ts, params), X.shape[:2], cost.fn)
    return jax.vmap(lambda X, U, t: _stage_costs(cost, X, U, t, params))(X, U, ts)


def _segments(dynamics, running_cost, prefix: Prefix | None, horizon: int):
    """[(first step, number of steps, dynamics, running_cost)] covering the horizon."""
    if prefix is None or prefix.steps <= 0:
        return [(0, horizon, dynamics, running_cost)]
    steps = min(int(prefix.steps), horizon)
    parts = [(0, steps, prefix.dynamics, prefix.running_cost)]
    if steps < horizon:
        parts.append((steps, horizon - steps, dynamics, running_cost))
    return parts


def rollout_cost(dynamics: Callable, running_cost: Callable, terminal_cost: Callable | None, x0: jax.Array,
                 controls: jax.Array, params: Any, prefix: Prefix | None = None) -> jax.Array:
    """Total cost of one control sequence from x0. controls: (T, m) -> scalar (:func:`rollout_costs` of a
    batch of one)."""
    return rollout_costs(dynamics, running_cost, terminal_cost, x0, controls[None], params, prefix)[0]


def rollout_costs(dynamics: Callable, running_cost: Callable, terminal_cost: Callable | None, x0: jax.Array,
                  controls: jax.Array, params: Any, prefix: Prefix | None = None) -> jax.Array:
    """Total cost of N control sequences from one x0. controls: (N, T, m) -> (N,).

    Scans the dynamics (vmapped over the samples) over the horizon, carrying the batch of states (N, n), then
    evaluates the running costs once over all (T, N) predicted states: a one-sample cost vmapped, a
    :class:`BatchCost` called on each step's batch, a :class:`TrajectoryCost` on all the steps at once.
    """
    chex.assert_rank(controls, 3)
    chex.assert_rank(x0, 1)
    N = controls.shape[0]
    X = jnp.broadcast_to(x0, (N,) + x0.shape)
    total = jnp.zeros((N,), controls.dtype)
    per_step = jnp.swapaxes(controls, 0, 1)  # (T, N, m)
    segments = _segments(dynamics, running_cost, prefix, controls.shape[1])
    trajectory = []
    for first, steps, dyn, _ in segments:

        def body(X, U, dyn=dyn):
            X_next = jax.vmap(dyn, in_axes=(0, 0, None))(X, U, params)
            return X_next, X_next

        X, states = jax.lax.scan(body, X, per_step[first:first + steps])
        trajectory.append(states)
    states = trajectory[0] if len(trajectory) == 1 else jnp.concatenate(trajectory)  # (T, N, n): x_1 .. x_T
    for first, stop, cost in _cost_runs(segments):
        stage_costs = _trajectory_costs(cost, states[first:stop], per_step[first:stop],
                                        jnp.arange(first, stop), params)  # (steps, N)
        # summed over the steps as a product with ones: XLA on a CPU fuses a reduction with the cost
        # before it into one kernel that runs ~3x slower than the cost and a separate product (HIGHEST:
        # full float32 on accelerators too, where a default product may round its inputs)
        ones = jnp.ones((stop - first,), stage_costs.dtype)
        total = total + jnp.matmul(ones, stage_costs, precision=jax.lax.Precision.HIGHEST)
    if terminal_cost is not None:
        total = total + checked_costs(jax.vmap(terminal_cost, in_axes=(0, None))(X, params), N, terminal_cost,
                                      batch=False)
    return total


def _cost_runs(segments) -> list:
    """[(first step, stop step, cost)]: consecutive segments charged by the same cost merged into one run."""
    runs = []
    for first, steps, _, cost in segments:
        if runs and runs[-1][2] is cost:
            runs[-1] = (runs[-1][0], first + steps, cost)
        else:
            runs.append((first, first + steps, cost))
    return runs


def rollout_states(dynamics: Callable, x0: jax.Array, controls: jax.Array, params: Any,
                   prefix: Prefix | None = None) -> jax.Array:
    """States visited by one control sequence, x0 included. controls: (T, m) -> (T+1, n)."""
    x = x0
    trajectory = [x0[None]]
    for first, steps, dyn, _ in _segments(dynamics, None, prefix, controls.shape[0]):

        def body(x, u, dyn=dyn):
            x_next = dyn(x, u, params)
            return x_next, x_next

        x, states = jax.lax.scan(body, x, controls[first:first + steps])
        trajectory.append(states)
    return jnp.concatenate(trajectory, axis=0)

