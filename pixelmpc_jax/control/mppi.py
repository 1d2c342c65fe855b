"""Model Predictive Path Integral control (Williams et al. 2017), generic and compiled.

This module knows nothing of quadrotors or pixels. A problem is three functions written for ONE sample:

    dynamics(x, u, params) -> x_next            # discrete-time model
    running_cost(x, u, t, params) -> scalar     # charged on the state x = x_{t+1} reached by u_t
    terminal_cost(x, params) -> scalar          # optional, on x_T

and ``params`` is any pytree (network weights, targets, gate geometry) passed to all of them: new params
never recompile. A running cost may instead be written for the whole batch of samples at a step and
wrapped in :class:`BatchCost`, or for every step and sample at once and wrapped in :class:`TrajectoryCost`
(layouts the compiler vectorises better for costs with inner reductions).
One optimisation iteration samples ``N`` noise sequences (:func:`_sample`), rolls all of them out with
``lax.scan`` over the horizon (the dynamics ``vmap``-ed over samples at each step; the running costs are then
evaluated over all (T, N) predicted states at once, :func:`rollout_costs`), weighs them (:func:`_weights`)
and updates the plan (:func:`_update`):

    S_k = sum_t running_cost + terminal_cost + gamma * sum_t U_t^T Sigma^-1 eps_{k,t}
    w_k = softmax(-(S_k - min_j S_j) / lambda)           (non-finite S_k get w_k = 0)
    U  <- clip(U + sum_k w_k eps_k, u_min, u_max)

where ``eps_k`` is the noise after clipping the sampled controls to the bounds. A step runs ``K`` such
iterations (``lax.scan``), returns ``U[0]`` and keeps the plan shifted by one step as the warm start.

Numerics: non-finite sample costs get zero weight; an iteration whose every sample is non-finite keeps the
plan (``info.all_nonfinite``); a plan holding a non-finite value (carried in, or after the update) is
replaced by the last finite one, or by the middle of the bounds (``info.plan_reset``), so ``U[0]`` is always
finite. Settings float32 cannot carry and costs of the wrong shape are refused with a ValueError before
anything runs.

Usage::

    ctrl = make_mppi(config, dynamics, running_cost)
    state = ctrl.init(key, u_init)
    u0, state, info = ctrl.step(state, x0, params)     # jitted, validated
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.control.sampling import (
    CPU_MATMULS,
    coloured_noise_filter,
    compiler_options,
    importance_weights,
    sample_shardings,
)

FLOAT32_MAX = float(np.finfo(np.float32).max)  # 3.4e38: larger numbers (and inf) do not survive float32
TEMPERATURE_MIN = 1e-30  # a smaller lambda flushes to zero in float32 arithmetic: 0 / 0 = NaN weights
SIGMA_MIN, SIGMA_MAX = 1e-18, 1e18  # sigma^2 and 1 / sigma^2 (the control cost) stay normal float32 numbers


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class MPPIConfig:
    """Static MPPI settings; hashable, so a new config compiles once on purpose.

    Attributes:
        num_samples: N, sampled control sequences per iteration.
        horizon: T, steps per rollout.
        dt: step length (s); informational for the dynamics the user passes (the paper: 0.025).
        noise_sigma: per-channel standard deviation of the control noise, length m; each 0 or in
            [1e-18, 1e18] (its square and inverse square must be float32 numbers).
        temperature: lambda of the softmax weights, in [1e-30, 3.4e38] (what float32 carries).
        iterations: K optimisation iterations per step.
        u_min, u_max: per-channel control bounds (length m, finite float32 numbers), or None for unbounded.
        control_cost_weight: gamma of the ``gamma * U^T Sigma^-1 eps`` term (0 disables it).
        nominal_sample: sample 0 uses zero noise, so the current plan is always among the candidates.
        noise_exponent: beta of time-correlated ("coloured") sampling noise with power spectrum 1/f^beta
            along the horizon, as in iCEM and MPPI-Generic's coloured sampler: 0 (the paper's) samples white
            noise, 1 pink, 2 red (smooth, slowly varying). Every step's marginal std stays ``noise_sigma``;
            see :func:`coloured_noise_filter`.
        sample_devices: split the N samples over this many local devices (1: one device, the default). The
            samples are the same (drawn whole from the same key) and so is the plan, up to float rounding;
            each device rolls out N / sample_devices of them. N must split evenly. On a CPU the cores become
            devices only if asked before JAX starts (:func:`~pixelmpc_jax.host.split_host_cpu`).
        cpu_matmul: whose kernels run the step's products on a CPU: "auto", "xla" or "ynnpack"
            (:func:`~pixelmpc_jax.control.sampling.compiler_options`); the same products either way.
    """

    num_samples: int = 512
    horizon: int = 80
    dt: float = timing.CONTROL_DT
    noise_sigma: tuple[float, ...] = (0.2, 0.2, 0.3, 2.2)
    temperature: float = 1.0
    iterations: int = 1
    u_min: tuple[float, ...] | None = None
    u_max: tuple[float, ...] | None = None
    control_cost_weight: float = 0.0
    nominal_sample: bool = True
    noise_exponent: float = 0.0
    sample_devices: int = 1
    cpu_matmul: str = "auto"

    def __post_init__(self):
        if self.cpu_matmul not in CPU_MATMULS:
            raise ValueError(f"MPPIConfig.cpu_matmul must be one of {CPU_MATMULS}, got {self.cpu_matmul!r}")
        for name in ("num_samples", "horizon", "iterations", "sample_devices"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"MPPIConfig.{name} must be a positive integer, got {value!r}")
        if self.num_samples % self.sample_devices:
            raise ValueError(f"MPPIConfig.num_samples={self.num_samples} does not split evenly over "
                             f"sample_devices={self.sample_devices}")
        if not (_is_number(self.dt) and 0 < self.dt <= FLOAT32_MAX):
            raise ValueError(f"MPPIConfig.dt must be a positive finite number, got {self.dt!r}")
        if not (_is_number(self.temperature) and TEMPERATURE_MIN <= self.temperature <= FLOAT32_MAX):
            raise ValueError(f"MPPIConfig.temperature (lambda) must be a number in [{TEMPERATURE_MIN:g}, "
                             f"{FLOAT32_MAX:.4g}] (what float32 carries), got {self.temperature!r}")
        try:
            sigma = np.asarray(self.noise_sigma, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"MPPIConfig.noise_sigma must be numbers, got {self.noise_sigma!r}") from err
        if sigma.ndim != 1 or sigma.size == 0:
            raise ValueError(f"MPPIConfig.noise_sigma must be a 1-D sequence (m,), one std per control channel; "
                             f"got shape {sigma.shape}")
        if not np.all((sigma == 0) | ((sigma >= SIGMA_MIN) & (sigma <= SIGMA_MAX))):
            raise ValueError(f"MPPIConfig.noise_sigma: each std must be 0 or a number in [{SIGMA_MIN:g}, "
                             f"{SIGMA_MAX:g}] (its square and inverse square must be float32 numbers), "
                             f"got {self.noise_sigma!r}")
        object.__setattr__(self, "noise_sigma", tuple(float(s) for s in sigma))
        m = sigma.size
        for name in ("u_min", "u_max"):
            bound = getattr(self, name)
            if bound is None:
                continue
            try:
                arr = np.asarray(bound, dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"MPPIConfig.{name} must be numbers, got {bound!r}") from err
            if arr.shape != (m,):
                raise ValueError(
                    f"MPPIConfig.{name} must have shape ({m},) to match noise_sigma, got shape {arr.shape}")
            if not np.all(np.abs(arr) <= FLOAT32_MAX):  # also rejects NaN and inf
                raise ValueError(f"MPPIConfig.{name} must be finite numbers in [-{FLOAT32_MAX:.4g}, "
                                 f"{FLOAT32_MAX:.4g}] (float32), got {bound!r}; None leaves the controls unbounded")
            object.__setattr__(self, name, tuple(float(b) for b in arr))
        if self.u_min is not None and self.u_max is not None:
            lo, hi = np.asarray(self.u_min), np.asarray(self.u_max)
            if np.any(lo > hi):
                raise ValueError(f"MPPIConfig: u_min > u_max in channels {np.nonzero(lo > hi)[0].tolist()} "
                                 f"(u_min={self.u_min}, u_max={self.u_max})")
        if not (isinstance(self.noise_exponent, (int, float)) and 0.0 <= self.noise_exponent <= 4.0):
            raise ValueError(f"MPPIConfig.noise_exponent (beta) must lie in [0, 4], got {self.noise_exponent!r}")
        if not (_is_number(self.control_cost_weight) and 0 <= self.control_cost_weight <= FLOAT32_MAX):
            raise ValueError(f"MPPIConfig.control_cost_weight must be a finite number >= 0, "
                             f"got {self.control_cost_weight!r}")

    @property
    def control_dim(self) -> int:
        return len(self.noise_sigma)


class MPPIState(NamedTuple):
    """What MPPI carries between steps.

    Attributes:
        plan: (T, m) nominal control sequence (the warm start).
        key: PRNG key, split with purpose names at every step.
    """

    plan: jax.Array
    key: jax.Array


class MPPIInfo(NamedTuple):
    """Diagnostics of one step (the last iteration's figures).

    Attributes:
        min_cost, mean_cost: over the finite sample costs.
        effective_sample_size: 1 / sum w_k^2, in [1, N].
        num_nonfinite: samples whose cost was NaN or inf (excluded from the weights).
        all_nonfinite: True when every sample was non-finite in some iteration (the plan was kept).
        plan_reset: True when the carried plan or the updated one held a non-finite value: the step then
            went on from the last finite plan (the carried one if finite, else the reset plan: the middle of
            the bounds, zero where a channel is unbounded), so ``u0`` is always finite.
        nominal_trajectory: (T+1, n) states predicted under the updated plan, starting at x0.
        costs: (N,) total cost per sample.
    """

    min_cost: jax.Array
    mean_cost: jax.Array
    effective_sample_size: jax.Array
    num_nonfinite: jax.Array
    all_nonfinite: jax.Array
    nominal_trajectory: jax.Array
    costs: jax.Array
    plan_reset: jax.Array


class Controller(NamedTuple):
    """An init/step pair.

    Attributes:
        init: ``init(key, u_init) -> MPPIState``; u_init is (T, m) or (m,) (repeated over the horizon).
        step: ``step(state, x0, params) -> (u0, state, info)``, jitted, inputs validated before tracing.
        step_pure: the same step, unjitted and unvalidated, to compose inside a larger jitted function
            (a closed-loop episode scanned over time).
        config: the MPPIConfig it was built with.
        num_compilations: ``() -> int``, how many times the jitted step has been traced: JAX traces it once
            per new input signature (shapes, dtypes, static structure), right before compiling that version;
            a control loop must keep it at 1.
        shardings: with ``sample_devices`` > 1, where the step's samples and its other inputs live
            (:class:`~pixelmpc_jax.control.sampling.SampleShardings`; put params there once with
            ``jax.device_put(params, ctrl.shardings.replicated)`` to save a copy per call); else None.
        compiler_options: the XLA options the step compiles with (``MPPIConfig.cpu_matmul``); a larger jitted
            function that composes ``step_pure`` passes them to its own ``jax.jit``.
    """

    init: Callable[..., MPPIState]
    step: Callable[..., tuple[jax.Array, MPPIState, MPPIInfo]]
    step_pure: Callable[..., tuple[jax.Array, MPPIState, MPPIInfo]]
    config: MPPIConfig
    num_compilations: Callable[[], int]
    shardings: Any = None
    compiler_options: Any = None


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
        return _checked_costs(self.fn(x[None], u[None], t, params), 1, self.fn, batch=True)[0]


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
        return _checked_trajectory_costs(costs, (1, 1), self.fn)[0, 0]


def _checked_costs(costs, N: int, fn: Callable, batch: bool) -> jax.Array:
    """``costs`` if it holds one cost per sample, (N,); a ValueError naming ``fn`` otherwise (shapes are known
    when tracing, so a wrong one is caught before anything runs, never broadcast over the samples)."""
    shape = tuple(jnp.shape(costs))
    if shape != (N,):
        name = getattr(fn, "__qualname__", None) or type(fn).__name__
        if batch:
            raise ValueError(f"BatchCost {name} must return one cost per sample, shape (N,) = ({N},); it returned "
                             f"shape {shape}")
        raise ValueError(f"cost {name} must return a scalar per sample (shape ()), it returned shape {shape[1:]}")
    return costs


def _stage_costs(cost: Callable, X: jax.Array, U: jax.Array, t, params) -> jax.Array:
    """(N,) running costs of a batch of states at one step (samples on axis 0)."""
    N = X.shape[0]
    if isinstance(cost, BatchCost):
        return _checked_costs(cost.fn(X, U, t, params), N, cost.fn, batch=True)
    return _checked_costs(jax.vmap(cost, in_axes=(0, 0, None, None))(X, U, t, params), N, cost, batch=False)


def _trajectory_costs(cost: Callable, X: jax.Array, U: jax.Array, ts: jax.Array, params) -> jax.Array:
    """(T, N) running costs of the states X (T, N, n) reached by U (T, N, m) at horizon steps ts (T,)."""
    if isinstance(cost, TrajectoryCost):
        return _checked_trajectory_costs(cost.fn(X, U, ts, params), X.shape[:2], cost.fn)
    return jax.vmap(lambda X, U, t: _stage_costs(cost, X, U, t, params))(X, U, ts)


def _checked_trajectory_costs(costs, shape: tuple, fn: Callable) -> jax.Array:
    """``costs`` if it holds one cost per step and sample, ``shape`` = (T, N); a ValueError naming ``fn`` otherwise."""
    if tuple(jnp.shape(costs)) != tuple(shape):
        name = getattr(fn, "__qualname__", None) or type(fn).__name__
        raise ValueError(f"TrajectoryCost {name} must return one cost per step and sample, shape (T, N) = "
                         f"{tuple(shape)}; it returned shape {tuple(jnp.shape(costs))}")
    return costs


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
        total = total + _checked_costs(jax.vmap(terminal_cost, in_axes=(0, None))(X, params), N, terminal_cost,
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


class _Sampling(NamedTuple):
    """The config and what an MPPI iteration derives from it, built once and closed over by the step.

    Attributes:
        sigma, inv_sigma2: (m,) noise std per channel and 1 / sigma^2 (0 where sigma is 0).
        lo, hi: (m,) control bounds, or None where unbounded.
        colour: (T, T) filter of time-correlated noise, or None for white noise.
        reset_plan: (T, m) what a non-finite plan is reset to: the middle of the bounds (zero where unbounded).
        shardings: where the samples live when split over devices, else None.
    """

    config: MPPIConfig
    sigma: jax.Array
    inv_sigma2: jax.Array
    lo: jax.Array | None
    hi: jax.Array | None
    colour: jax.Array | None
    reset_plan: jax.Array
    shardings: Any


def _sampling(config: MPPIConfig) -> _Sampling:
    T, m, N = config.horizon, config.control_dim, config.num_samples
    sigma = jnp.asarray(config.noise_sigma, dtype=jnp.float32)
    lo = None if config.u_min is None else jnp.asarray(config.u_min, jnp.float32)
    hi = None if config.u_max is None else jnp.asarray(config.u_max, jnp.float32)
    if lo is not None and hi is not None:
        reset_control = 0.5 * lo + 0.5 * hi  # (lo + hi) / 2 could overflow float32
    else:
        reset_control = _clip(jnp.zeros((m,), jnp.float32), lo, hi)
    return _Sampling(
        config=config, sigma=sigma, inv_sigma2=jnp.where(sigma > 0, 1.0 / jnp.where(sigma > 0, sigma, 1.0) ** 2, 0.0),
        lo=lo, hi=hi, reset_plan=jnp.broadcast_to(reset_control, (T, m)),
        colour=None if config.noise_exponent == 0.0 else jnp.asarray(coloured_noise_filter(T, config.noise_exponent)),
        shardings=sample_shardings(config.sample_devices, N) if config.sample_devices > 1 else None)


def _clip(u: jax.Array, lo: jax.Array | None, hi: jax.Array | None) -> jax.Array:
    """u clipped to the bounds, channel by channel; a None bound leaves that side open."""
    if lo is not None:
        u = jnp.maximum(u, lo)
    if hi is not None:
        u = jnp.minimum(u, hi)
    return u


def _sample(key: jax.Array, plan: jax.Array, s: _Sampling) -> tuple[jax.Array, jax.Array]:
    """Sampled control sequences around the plan (T, m): controls = clip(U + eps), (N, T, m), and the noise
    eps = controls - U actually applied (sample 0 is the plan itself with ``nominal_sample``)."""
    white = jax.random.normal(key, (s.config.num_samples,) + s.reset_plan.shape, dtype=plan.dtype)
    if s.shardings is not None:  # each device draws, rolls out and costs its own rows
        white = jax.lax.with_sharding_constraint(white, s.shardings.samples)
    if s.colour is not None:
        white = jnp.einsum("ts,nsm->ntm", s.colour, white)  # time-correlated, unit variance per step
    noise = white * s.sigma  # (N, T, m)
    if s.config.nominal_sample:
        noise = noise.at[0].set(0.0)
    controls = _clip(plan[None] + noise, s.lo, s.hi)  # (N, T, m)
    return controls, controls - plan[None]


def _weights(costs: jax.Array, plan: jax.Array, eps: jax.Array, s: _Sampling):
    """(S, w, finite), each (N,): the sample costs S_k with the control cost ``gamma sum_t U_t^T Sigma^-1 eps_{k,t}``
    added, their weights w_k = softmax(-(S_k - min_j S_j) / lambda) (0 where S_k is not finite), the mask."""
    gamma = float(s.config.control_cost_weight)
    if gamma > 0:
        costs = costs + gamma * jnp.einsum("tm,ntm,m->n", plan, eps, s.inv_sigma2)
    weights, finite = importance_weights(costs, float(s.config.temperature))
    return costs, weights, finite


def _update(plan: jax.Array, weights: jax.Array, eps: jax.Array, all_nonfinite: jax.Array, s: _Sampling):
    """U <- clip(U + sum_k w_k eps_k); the plan is kept when every sample cost was non-finite."""
    update = jnp.einsum("n,ntm->tm", weights, eps)
    return jnp.where(all_nonfinite, plan, _clip(plan + update, s.lo, s.hi))


class _IterationStats(NamedTuple):
    """An iteration's figures (see :class:`MPPIInfo`)."""

    min_cost: jax.Array
    mean_cost: jax.Array
    effective_sample_size: jax.Array
    num_nonfinite: jax.Array
    costs: jax.Array


def _iteration_stats(costs: jax.Array, weights: jax.Array, finite: jax.Array, all_nonfinite: jax.Array):
    finite_costs = jnp.where(finite, costs, 0.0)
    num_finite = jnp.sum(finite)
    return _IterationStats(
        min_cost=jnp.min(jnp.where(finite, costs, jnp.inf)),
        mean_cost=jnp.sum(finite_costs) / jnp.maximum(num_finite, 1),
        effective_sample_size=jnp.where(all_nonfinite, 0.0, 1.0 / jnp.sum(weights**2)),
        num_nonfinite=costs.shape[0] - num_finite,
        costs=costs,
    )


def make_mppi(config: MPPIConfig, dynamics: Callable, running_cost: Callable, terminal_cost: Callable | None = None,
              prefix: Prefix | None = None) -> Controller:
    """Build a compiled MPPI controller for the given one-sample model and costs (see module docstring).

    ``prefix`` optionally gives the first steps of the horizon their own model and cost (see Prefix).
    """
    if not isinstance(config, MPPIConfig):
        raise TypeError(f"config must be an MPPIConfig, got {type(config).__name__}")
    if prefix is not None and not (isinstance(prefix.steps, int) and 0 <= prefix.steps <= config.horizon):
        raise ValueError(f"prefix.steps must be an integer in [0, horizon={config.horizon}], got {prefix.steps!r}")
    s = _sampling(config)

    def iteration(carry, key, x0, params):
        """One MPPI update of the plan: sample, roll out, weigh, update."""
        plan, any_all_nonfinite = carry
        controls, eps = _sample(key, plan, s)
        costs = rollout_costs(dynamics, running_cost, terminal_cost, x0, controls, params, prefix)
        costs, weights, finite = _weights(costs, plan, eps, s)
        all_nonfinite = ~jnp.any(finite)
        new_plan = _update(plan, weights, eps, all_nonfinite, s)
        return (new_plan, any_all_nonfinite | all_nonfinite), _iteration_stats(costs, weights, finite, all_nonfinite)

    def init(key, u_init) -> MPPIState:
        u_init = _validate_u_init(u_init, config.horizon, config.control_dim)
        plan = _clip(jnp.broadcast_to(u_init, s.reset_plan.shape).astype(jnp.float32), s.lo, s.hi)
        state = MPPIState(plan=plan, key=key)
        return state if s.shardings is None else jax.device_put(state, s.shardings.replicated)

    def step_pure(state: MPPIState, x0, params):
        key, key_iters = jax.random.split(state.key)
        keys = jax.random.split(key_iters, config.iterations)
        carried_finite = jnp.all(jnp.isfinite(state.plan))
        start = jnp.where(carried_finite, state.plan, s.reset_plan)  # the last finite plan
        (plan, all_nonfinite), stats = jax.lax.scan(lambda c, k: iteration(c, k, x0, params),
                                                    (start, jnp.asarray(False)), keys)
        updated_finite = jnp.all(jnp.isfinite(plan))
        plan = jnp.where(updated_finite, plan, start)
        last = jax.tree_util.tree_map(lambda a: a[-1], stats)
        u0 = plan[0]
        shifted = jnp.concatenate([plan[1:], plan[-1:]], axis=0)
        info = MPPIInfo(**last._asdict(), all_nonfinite=all_nonfinite, plan_reset=~(carried_finite & updated_finite),
                        nominal_trajectory=rollout_states(dynamics, x0, plan, params, prefix))
        return u0, MPPIState(plan=shifted, key=key), info

    options = compiler_options(config.cpu_matmul, config.sample_devices)
    step, num_compilations = _validated_jit(step_pure, dynamics, s, options)
    return Controller(init=init, step=step, step_pure=step_pure, config=config, num_compilations=num_compilations,
                      shardings=s.shardings, compiler_options=options)


def _validated_jit(step_pure: Callable, dynamics: Callable, s: _Sampling, options):
    """The public ``step(state, x0, params)``: ``step_pure`` jitted, its inputs checked before tracing; and
    ``num_compilations() -> int``, the traces of the jitted step so far (one per compiled version)."""
    traces = [0]

    def traced_step(state, x0, params):
        traces[0] += 1  # Python runs here only while JAX traces: once per new input signature, before compiling
        return step_pure(state, x0, params)

    step_jit = jax.jit(traced_step, compiler_options=options)
    checked_state_shapes: set = set()
    T, m = s.reset_plan.shape

    def step(state: MPPIState, x0, params):
        if not isinstance(state, MPPIState):
            raise TypeError(f"state must be the MPPIState returned by init/step, got {type(state).__name__}")
        if tuple(state.plan.shape) != (T, m):
            raise ValueError(f"state.plan must have shape ({T}, {m}) (horizon, control_dim), got {state.plan.shape}")
        x0 = jnp.asarray(x0)
        if not jnp.issubdtype(x0.dtype, jnp.floating):  # an integer or bool state rolls out in the plan's float
            x0 = x0.astype(state.plan.dtype)
        signature = (x0.shape, str(x0.dtype))
        if signature not in checked_state_shapes:
            _validate_x0(dynamics, x0, m, params)
            checked_state_shapes.add(signature)
        replicated = None if s.shardings is None else s.shardings.replicated
        if replicated is not None and not all(getattr(leaf, "sharding", None) == replicated
                                              for leaf in jax.tree_util.tree_leaves((state, x0, params))):
            state, x0, params = jax.device_put((state, x0, params), replicated)  # onto every device
        return step_jit(state, x0, params)

    return step, lambda: traces[0]


def _validate_u_init(u_init, T: int, m: int) -> jax.Array:
    u = jnp.asarray(u_init, dtype=jnp.float32)
    if u.shape not in ((T, m), (m,)):
        raise ValueError(f"u_init must have shape ({T}, {m}) (horizon, control_dim) or ({m},), got {u.shape}")
    if not isinstance(u, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(u))):
        raise ValueError("u_init must be finite")
    return u


def _validate_x0(dynamics: Callable, x0: jax.Array, m: int, params) -> None:
    if x0.ndim != 1:
        raise ValueError(f"x0 must be one state of shape (n,), got shape {x0.shape}")
    try:
        out = jax.eval_shape(lambda x, p: dynamics(x, jnp.zeros((m,), jnp.float32), p), x0, params)  # noqa: B023
    except Exception as err:  # the dynamics could not even be traced with this x0
        raise ValueError(f"x0 of shape {x0.shape} does not fit the dynamics: {err}") from err
    if getattr(out, "shape", None) != x0.shape:
        raise ValueError(f"x0 has shape {x0.shape} but the dynamics map it to shape {getattr(out, 'shape', out)}; "
                         f"x0 must be the full state (n,) that dynamics(x, u, params) returns")
