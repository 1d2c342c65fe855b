"""What MPPI refuses before anything runs: settings float32 cannot carry, inputs and costs of the wrong shape.

Every check raises a ValueError (a TypeError for an object of the wrong kind) that names the setting or the
function at fault and the shape or range it must have; none runs inside the compiled step. The cost checks
run while the step is traced, when the shapes are known, so a wrong shape is refused before the step
compiles, never broadcast over the samples.

* :func:`checked_config`: ``MPPIConfig``'s fields (its ``__post_init__``).
* :func:`check_prefix`, :func:`checked_u_init`, :func:`step_input_checks`: what ``make_mppi``, ``init`` and
  ``step`` are given (the step's inputs by ``Controller.check``, outside jit: the compiled step of
  :func:`~pixelmpc_jax.devices.compile_controller` runs it before every call).
* :func:`checked_costs`, :func:`checked_trajectory_costs`: what a running or terminal cost returns.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

FLOAT32_MAX = float(np.finfo(np.float32).max)  # 3.4e38: larger numbers (and inf) do not survive float32
TEMPERATURE_MIN = 1e-30  # a smaller lambda flushes to zero in float32 arithmetic: 0 / 0 = NaN weights
SIGMA_MIN, SIGMA_MAX = 1e-18, 1e18  # sigma^2 and 1 / sigma^2 (the control cost) stay normal float32 numbers


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def checked_config(config) -> dict[str, tuple[float, ...] | None]:
    """The sequences of an ``MPPIConfig`` as tuples of floats, ``{"noise_sigma", "u_min", "u_max"}``, once every
    field is checked; a ValueError naming the first field out of its range."""
    for name in ("num_samples", "horizon", "iterations"):
        value = getattr(config, name)
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"MPPIConfig.{name} must be a positive integer, got {value!r}")
    if not (_is_number(config.dt) and 0 < config.dt <= FLOAT32_MAX):
        raise ValueError(f"MPPIConfig.dt must be a positive finite number, got {config.dt!r}")
    if not (_is_number(config.temperature) and TEMPERATURE_MIN <= config.temperature <= FLOAT32_MAX):
        raise ValueError(f"MPPIConfig.temperature (lambda) must be a number in [{TEMPERATURE_MIN:g}, "
                         f"{FLOAT32_MAX:.4g}] (what float32 carries), got {config.temperature!r}")
    fields = {"noise_sigma": _checked_sigma(config.noise_sigma)}
    m = len(fields["noise_sigma"])
    for name in ("u_min", "u_max"):
        fields[name] = _checked_bound(name, getattr(config, name), m)
    if fields["u_min"] is not None and fields["u_max"] is not None:
        lo, hi = np.asarray(fields["u_min"]), np.asarray(fields["u_max"])
        if np.any(lo > hi):
            raise ValueError(f"MPPIConfig: u_min > u_max in channels {np.nonzero(lo > hi)[0].tolist()} "
                             f"(u_min={fields['u_min']}, u_max={fields['u_max']})")
    if not (isinstance(config.noise_exponent, (int, float)) and 0.0 <= config.noise_exponent <= 4.0):
        raise ValueError(f"MPPIConfig.noise_exponent (beta) must lie in [0, 4], got {config.noise_exponent!r}")
    if not (_is_number(config.control_cost_weight) and 0 <= config.control_cost_weight <= FLOAT32_MAX):
        raise ValueError(f"MPPIConfig.control_cost_weight must be a finite number >= 0, "
                         f"got {config.control_cost_weight!r}")
    return fields


def _checked_sigma(noise_sigma) -> tuple[float, ...]:
    """``MPPIConfig.noise_sigma`` as a tuple of floats (m,), each 0 or in [SIGMA_MIN, SIGMA_MAX]."""
    try:
        sigma = np.asarray(noise_sigma, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"MPPIConfig.noise_sigma must be numbers, got {noise_sigma!r}") from err
    if sigma.ndim != 1 or sigma.size == 0:
        raise ValueError(f"MPPIConfig.noise_sigma must be a 1-D sequence (m,), one std per control channel; "
                         f"got shape {sigma.shape}")
    if not np.all((sigma == 0) | ((sigma >= SIGMA_MIN) & (sigma <= SIGMA_MAX))):
        raise ValueError(f"MPPIConfig.noise_sigma: each std must be 0 or a number in [{SIGMA_MIN:g}, "
                         f"{SIGMA_MAX:g}] (its square and inverse square must be float32 numbers), "
                         f"got {noise_sigma!r}")
    return tuple(float(s) for s in sigma)


def _checked_bound(name: str, bound, m: int) -> tuple[float, ...] | None:
    """``MPPIConfig.u_min`` or ``u_max`` as a tuple of floats (m,), finite float32 numbers; None stays None."""
    if bound is None:
        return None
    try:
        arr = np.asarray(bound, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"MPPIConfig.{name} must be numbers, got {bound!r}") from err
    if arr.shape != (m,):
        raise ValueError(f"MPPIConfig.{name} must have shape ({m},) to match noise_sigma, got shape {arr.shape}")
    if not np.all(np.abs(arr) <= FLOAT32_MAX):  # also rejects NaN and inf
        raise ValueError(f"MPPIConfig.{name} must be finite numbers in [-{FLOAT32_MAX:.4g}, "
                         f"{FLOAT32_MAX:.4g}] (float32), got {bound!r}; None leaves the controls unbounded")
    return tuple(float(b) for b in arr)


def check_prefix(prefix, horizon: int) -> None:
    """A ValueError unless ``prefix`` is None or its ``steps`` is an integer in [0, horizon]."""
    if prefix is not None and not (isinstance(prefix.steps, int) and 0 <= prefix.steps <= horizon):
        raise ValueError(f"prefix.steps must be an integer in [0, horizon={horizon}], got {prefix.steps!r}")


def checked_u_init(u_init, T: int, m: int) -> jax.Array:
    """``u_init`` as a float32 array if it is a finite (T, m) plan or one (m,) control; a ValueError otherwise."""
    u = jnp.asarray(u_init, dtype=jnp.float32)
    if u.shape not in ((T, m), (m,)):
        raise ValueError(f"u_init must have shape ({T}, {m}) (horizon, control_dim) or ({m},), got {u.shape}")
    if not isinstance(u, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(u))):
        raise ValueError("u_init must be finite")
    return u


def step_input_checks(dynamics: Callable, state_type: type, T: int, m: int) -> Callable:
    """``check(state, x0, params) -> (state, x0, params)``: what the public step is given, checked before tracing.

    ``state`` must be a ``state_type`` whose plan is (T, m); ``x0`` is made an array (in the plan's float type
    if it is an integer or bool state) and checked against ``dynamics`` once per shape and dtype.
    """
    checked_state_shapes: set = set()

    def check(state, x0, params):
        if not isinstance(state, state_type):
            raise TypeError(f"state must be the MPPIState returned by init/step, got {type(state).__name__}")
        if tuple(state.plan.shape) != (T, m):
            raise ValueError(f"state.plan must have shape ({T}, {m}) (horizon, control_dim), got {state.plan.shape}")
        x0 = jnp.asarray(x0)
        if not jnp.issubdtype(x0.dtype, jnp.floating):  # an integer or bool state rolls out in the plan's float
            x0 = x0.astype(state.plan.dtype)
        signature = (x0.shape, str(x0.dtype))
        if signature not in checked_state_shapes:
            check_x0(dynamics, x0, m, params)
            checked_state_shapes.add(signature)
        return state, x0, params

    return check


def check_x0(dynamics: Callable, x0: jax.Array, m: int, params) -> None:
    """A ValueError unless ``x0`` is one state (n,) that ``dynamics(x0, u, params)`` maps to the same shape."""
    if x0.ndim != 1:
        raise ValueError(f"x0 must be one state of shape (n,), got shape {x0.shape}")
    try:
        out = jax.eval_shape(lambda x, p: dynamics(x, jnp.zeros((m,), jnp.float32), p), x0, params)
    except Exception as err:  # the dynamics could not even be traced with this x0
        raise ValueError(f"x0 of shape {x0.shape} does not fit the dynamics: {err}") from err
    if getattr(out, "shape", None) != x0.shape:
        raise ValueError(f"x0 has shape {x0.shape} but the dynamics map it to shape {getattr(out, 'shape', out)}; "
                         f"x0 must be the full state (n,) that dynamics(x, u, params) returns")


def checked_costs(costs, N: int, fn: Callable, batch: bool) -> jax.Array:
    """``costs`` if it holds one cost per sample, (N,); a ValueError naming ``fn`` otherwise (``batch``: ``fn`` is
    a ``BatchCost``'s function, else a one-sample cost vmapped over the samples)."""
    shape = tuple(jnp.shape(costs))
    if shape != (N,):
        name = getattr(fn, "__qualname__", None) or type(fn).__name__
        if batch:
            raise ValueError(f"BatchCost {name} must return one cost per sample, shape (N,) = ({N},); it returned "
                             f"shape {shape}")
        raise ValueError(f"cost {name} must return a scalar per sample (shape ()), it returned shape {shape[1:]}")
    return costs


def checked_trajectory_costs(costs, shape: tuple, fn: Callable) -> jax.Array:
    """``costs`` if it holds one cost per step and sample, ``shape`` = (T, N); a ValueError naming ``fn`` otherwise."""
    if tuple(jnp.shape(costs)) != tuple(shape):
        name = getattr(fn, "__qualname__", None) or type(fn).__name__
        raise ValueError(f"TrajectoryCost {name} must return one cost per step and sample, shape (T, N) = "
                         f"{tuple(shape)}; it returned shape {tuple(jnp.shape(costs))}")
    return costs
