"""Model Predictive Path Integral control (Williams et al. 2017), generic, as a pair of pure functions.

This module knows nothing of quadrotors or pixels. A problem is three functions written for ONE sample:

    dynamics(x, u, params) -> x_next            # discrete-time model
    running_cost(x, u, t, params) -> scalar     # charged on the state x = x_{t+1} reached by u_t
    terminal_cost(x, params) -> scalar          # optional, on x_T

and ``params`` is any pytree (network weights, targets, gate geometry) passed to all of them: new params
never recompile. A running cost may instead be written for the whole batch of samples at a step and
wrapped in :class:`~pixelmpc_jax.control.rollout.BatchCost`, or for every step and sample at once and wrapped
in :class:`~pixelmpc_jax.control.rollout.TrajectoryCost` (layouts the compiler vectorises better for costs
with inner reductions).
One optimisation iteration samples ``N`` noise sequences (:func:`_sample`), rolls all of them out with
``lax.scan`` over the horizon (the dynamics ``vmap``-ed over samples at each step; the running costs are then
evaluated over all (T, N) predicted states at once, :func:`~pixelmpc_jax.control.rollout.rollout_costs`),
weighs them (:func:`_weights`) and updates the plan (:func:`_update`):

    S_k = sum_t running_cost + terminal_cost + gamma * sum_t U_t^T Sigma^-1 eps_{k,t}
    w_k = softmax(-(S_k - min_j S_j) / lambda)           (non-finite S_k get w_k = 0)
    U  <- clip(U + sum_k w_k eps_k, u_min, u_max)

where ``eps_k`` is the noise after clipping the sampled controls to the bounds. A step runs ``K`` such
iterations (``lax.scan``), returns ``U[0]`` and keeps the plan shifted by one step as the warm start.

Numerics: non-finite sample costs get zero weight; an iteration whose every sample is non-finite keeps the
plan (``info.all_nonfinite``); a plan holding a non-finite value (carried in, or after the update) is
replaced by the last finite one, or by the middle of the bounds (``info.plan_reset``), so ``U[0]`` is always
finite. Settings float32 cannot carry, a state and costs of the wrong shape are refused with a ValueError before
anything runs (:mod:`~pixelmpc_jax.control.mppi_checks`; the state's shape when the step is traced, so under a
plain ``jax.jit`` too; an integer state is cast to float). Input values the step cannot fly (NaN in x0 or the
params, or what the problem's ``input_findings`` refuses) are flagged in ``info.input_rejected``: the plan is then
not updated and the command sent is the carried plan's first control; ``Controller.check(..., values=True)``
raises them outside jit, naming each.

Like an optax transformation, a :class:`Controller` is ``init`` and ``step``, pure functions over a small
NamedTuple state: jit them, vmap them over robots, scan them over time, as the caller's program needs::

    ctrl = make_mppi(config, dynamics, running_cost)
    state = ctrl.init(key, u_init)
    step = devices.compile_controller(ctrl).step     # the fast path: compiled once, its inputs checked
    u0, state, info = step(state, x0, params)

How a step runs, as opposed to what it computes, is :mod:`pixelmpc_jax.devices`'s concern
(:func:`~pixelmpc_jax.devices.compile_controller`). A plain ``jax.jit(ctrl.step)`` computes the same step but
compiles it with XLA's default CPU options, without the YNNPACK ones ``compile_controller`` adds
(:func:`~pixelmpc_jax.devices.compiler_options`). That is the whole difference in speed: a unicycle on one core of
a 2-core AMD EPYC, 1.72 against 1.41 ms a step at 512 x 50 and 8.40 against 6.17 ms at 2048 x 50 (medians;
``jax.jit`` with the same ``compiler_options`` matches ``compile_controller``, and ``compile_controller`` with
``Execution(cpu_matmul="xla")`` matches the plain jit). PixelMPC's step: 24.3 against 18.4 ms at 512 x 80 on both
cores; from 2048 samples its DOF's products run faster on XLA's kernels, which ``compile_controller`` then keeps
(it reads the traced step's largest product, :func:`~pixelmpc_jax.devices.largest_product`), the plain jit's own
program (``pixelmpc bench`` times both, ``apps/bench/jit_paths.py``). A plain jit also skips ``Controller.check``
and the compile count. Inside a jit of one's own, pass ``compiler_options=devices.compiler_options("auto", 1,
devices.largest_product(jax.make_jaxpr(step)(*args)))`` to it for the same kernels.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.control.mppi_checks import (
    FLOAT32_MAX,
    NOISE_EXPONENT_RANGE,
    NUM_SAMPLES_RANGE,
    TEMPERATURE_RANGE,
    check_prefix,
    check_x0,
    checked_config,
    checked_state,
    checked_u_init,
    step_input_checks,
    step_input_findings,
)
from pixelmpc_jax.control.rollout import Prefix, rollout_costs, rollout_states
from pixelmpc_jax.control.sampling import coloured_noise_filter, importance_weights
from pixelmpc_jax.settings import Range, setting


@dataclasses.dataclass(frozen=True)
class MPPIConfig:
    """Static MPPI settings; hashable, so a new config compiles once on purpose.

    Nothing in it is a vehicle's: ``noise_sigma`` is required (keyword only) and is the one source of the number
    of control channels m, which ``u_min``, ``u_max`` and the controller's plan (T, m) follow. A quadrotor's
    settings live with the quadrotor's controller (:func:`~pixelmpc_jax.control.pixelmpc.paper_mppi_config`).

    Attributes:
        num_samples: N, sampled control sequences per iteration, in
            :data:`~pixelmpc_jax.control.mppi_checks.NUM_SAMPLES_RANGE`.
        horizon: T, steps per rollout.
        dt: step length (s); informational for the dynamics the user passes (the paper: 0.025).
        noise_sigma: required; per-channel standard deviation of the control noise, length m (the number of
            control channels); each 0 or in [1e-18, 1e18] (its square and inverse square must be float32 numbers).
        temperature: lambda of the softmax weights, in [1e-30, 3.4e38] (what float32 carries).
        iterations: K optimisation iterations per step.
        u_min, u_max: per-channel control bounds (length m, finite float32 numbers), or None for unbounded.
        control_cost_weight: gamma of the ``gamma * U^T Sigma^-1 eps`` term (0 disables it).
        nominal_sample: sample 0 uses zero noise, so the current plan is always among the candidates.
        noise_exponent: beta of time-correlated ("coloured") sampling noise with power spectrum 1/f^beta
            along the horizon, as in iCEM and MPPI-Generic's coloured sampler: 0 (the paper's) samples white
            noise, 1 pink, 2 red (smooth, slowly varying). Every step's marginal std stays ``noise_sigma``;
            see :func:`~pixelmpc_jax.control.sampling.coloured_noise_filter`.
    """

    num_samples: int = setting(512, range=NUM_SAMPLES_RANGE, help="MPPI samples per step")
    horizon: int = setting(80, range=Range(1, math.inf, integer=True), help="MPPI steps per rollout (T)")
    dt: float = setting(timing.CONTROL_DT, range=Range(0.0, FLOAT32_MAX, lo_open=True, unit="s"),
                        help="MPPI step length")
    noise_sigma: tuple[float, ...] = dataclasses.field(kw_only=True)
    temperature: float = setting(1.0, range=TEMPERATURE_RANGE, help="MPPI lambda")
    iterations: int = setting(1, range=Range(1, math.inf, integer=True), help="MPPI iterations per step (K)")
    u_min: tuple[float, ...] | None = None
    u_max: tuple[float, ...] | None = None
    control_cost_weight: float = setting(0.0, range=Range(0.0, FLOAT32_MAX), help="MPPI control cost weight gamma")
    nominal_sample: bool = True
    noise_exponent: float = setting(0.0, range=NOISE_EXPONENT_RANGE, help="MPPI sampling noise coloured as 1/f^beta "
                                    "along the horizon, beta in {range} (0: white, the paper's)")

    def __post_init__(self):
        for name, value in checked_config(self).items():  # the sequences as tuples of floats
            object.__setattr__(self, name, value)

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
        input_rejected: () bool, True when the step's input could not be flown: x0 held NaN or inf, a float leaf
            of params held NaN, or the problem's own check failed (``make_mppi``'s ``input_findings``: PixelMPC's
            zero quaternion, a detected pixel not normalised). The fallback command sent is then the carried
            plan's first control (the last finite plan's: the reset plan if the carried one was not finite), the
            plan is not updated and is shifted on as usual. ``Controller.check(state, x0, params, values=True)``
            names what was wrong (the checked execution of :func:`~pixelmpc_jax.devices.compile_controller` raises
            it).
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
    input_rejected: jax.Array


class Controller(NamedTuple):
    """MPPI as a pair of pure functions over :class:`MPPIState` (optax's ``(init, update)``).

    Attributes:
        init: ``init(key, u_init) -> MPPIState``; u_init is (T, m) or (m,) (repeated over the horizon).
        step: ``step(state, x0, params) -> (u0, state, info)``: one MPPI step, pure (nothing is mutated, the key
            travels in the state), to ``jax.jit``, ``jax.vmap`` or ``lax.scan`` as the caller's program needs.
        config: the MPPIConfig it was built with.
        check: ``check(state, x0, params, values=False) -> (state, x0, params)``: the step's inputs checked outside
            jit (a ValueError naming what is wrong; :func:`~pixelmpc_jax.control.mppi_checks.step_input_checks`),
            x0 made an array (an integer or bool state in the plan's float type); with ``values`` their numbers too
            (what ``info.input_rejected`` flags inside the step).
        with_sample_placement: ``with_sample_placement(place) -> Controller``: the same controller with
            ``place`` applied to each iteration's (N, T, m) white noise as it is drawn, which says where the caller
            wants the samples to live (how the step runs, not what it computes); ``place`` must return the values
            it is given, so the step computes the same numbers.
    """

    init: Callable[..., MPPIState]
    step: Callable[..., tuple[jax.Array, MPPIState, MPPIInfo]]
    config: MPPIConfig
    check: Callable[..., tuple]
    with_sample_placement: Callable[[Callable | None], Controller]


class _Sampling(NamedTuple):
    """The config and what an MPPI iteration derives from it, built once and closed over by the step.

    Attributes:
        sigma, inv_sigma2: (m,) noise std per channel and 1 / sigma^2 (0 where sigma is 0).
        lo, hi: (m,) control bounds, or None where unbounded.
        colour: (T, T) filter of time-correlated noise, or None for white noise.
        reset_plan: (T, m) what a non-finite plan is reset to: the middle of the bounds (zero where unbounded).
        place_samples: applied to the (N, T, m) white noise as drawn (see ``Controller.with_sample_placement``),
            or None.
    """

    config: MPPIConfig
    sigma: jax.Array
    inv_sigma2: jax.Array
    lo: jax.Array | None
    hi: jax.Array | None
    colour: jax.Array | None
    reset_plan: jax.Array
    place_samples: Callable[[jax.Array], jax.Array] | None = None


def _sampling(config: MPPIConfig) -> _Sampling:
    T, m = config.horizon, config.control_dim
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
        colour=None if config.noise_exponent == 0.0 else jnp.asarray(coloured_noise_filter(T, config.noise_exponent)))


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
    if s.place_samples is not None:
        white = s.place_samples(white)  # where the caller's execution puts the samples, from the draw on
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
              prefix: Prefix | None = None, input_findings: Callable | None = None) -> Controller:
    """MPPI for the given one-sample model and costs (see module docstring), as pure ``init`` and ``step``.

    ``prefix`` optionally gives the first steps of the horizon their own model and cost (see Prefix).
    ``input_findings(x0, params) -> {message: () bool}`` optionally adds the problem's own checks of a step's input:
    it raises a ValueError naming the expected shape while the step is traced, and returns, per message, whether the
    values are sound (True) inside the step (``info.input_rejected``) and outside jit (``Controller.check``).
    Whatever it adds, x0 must be one finite state (n,) that ``dynamics`` maps to (n,), checked when the step is
    traced (an integer state is cast to float32), and no float leaf of ``params`` may hold NaN.
    """
    if not isinstance(config, MPPIConfig):
        raise TypeError(f"config must be an MPPIConfig, got {type(config).__name__}")
    check_prefix(prefix, config.horizon)

    def findings(x0, params):
        return step_input_findings(x0, params, input_findings)

    check = step_input_checks(dynamics, MPPIState, config.horizon, config.control_dim, findings)
    return _controller(_sampling(config), dynamics, running_cost, terminal_cost, prefix, check, findings)


def _controller(s: _Sampling, dynamics: Callable, running_cost: Callable, terminal_cost: Callable | None,
                prefix: Prefix | None, check: Callable, findings: Callable) -> Controller:
    """The init/step pair over the sampling ``s``, closed over once."""
    config = s.config

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
        u_init = checked_u_init(u_init, config.horizon, config.control_dim)
        plan = _clip(jnp.broadcast_to(u_init, s.reset_plan.shape).astype(jnp.float32), s.lo, s.hi)
        return MPPIState(plan=plan, key=key)

    def step(state: MPPIState, x0, params):
        x0 = checked_state(x0, state.plan.dtype)  # shapes and dtypes, while the step is traced
        check_x0(dynamics, x0, config.control_dim, params)
        found = findings(x0, params)
        input_sound = jnp.all(jnp.stack([jnp.asarray(sound, bool) for sound in found.values()]))
        key, key_iters = jax.random.split(state.key)
        keys = jax.random.split(key_iters, config.iterations)
        carried_finite = jnp.all(jnp.isfinite(state.plan))
        start = jnp.where(carried_finite, state.plan, s.reset_plan)  # the last finite plan
        (plan, all_nonfinite), stats = jax.lax.scan(lambda c, k: iteration(c, k, x0, params),
                                                    (start, jnp.asarray(False)), keys)
        updated_finite = jnp.all(jnp.isfinite(plan))
        plan = jnp.where(updated_finite & input_sound, plan, start)  # bad input: the carried (finite) plan
        last = jax.tree_util.tree_map(lambda a: a[-1], stats)
        u0 = plan[0]
        shifted = jnp.concatenate([plan[1:], plan[-1:]], axis=0)
        info = MPPIInfo(**last._asdict(), all_nonfinite=all_nonfinite, plan_reset=~(carried_finite & updated_finite),
                        input_rejected=~input_sound,
                        nominal_trajectory=rollout_states(dynamics, x0, plan, params, prefix))
        return u0, MPPIState(plan=shifted, key=key), info

    def with_sample_placement(place_samples):
        return _controller(s._replace(place_samples=place_samples), dynamics, running_cost, terminal_cost, prefix,
                           check, findings)

    return Controller(init=init, step=step, config=config, check=check, with_sample_placement=with_sample_placement)
