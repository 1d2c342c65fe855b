"""What MPPI refuses before anything runs: settings float32 cannot carry, inputs and costs of the wrong shape.

Every check raises a ValueError (a TypeError for an object of the wrong kind) that names the setting or the
function at fault and the shape or range it must have; none runs inside the compiled step. The cost checks
run while the step is traced, when the shapes are known, so a wrong shape is refused before the step
compiles, never broadcast over the samples.

* :func:`checked_config`: ``MPPIConfig``'s fields (its ``__post_init__``).
* :func:`check_prefix`, :func:`checked_u_init`, :func:`step_input_checks`: what ``make_mppi``, ``init`` and
  ``step`` are given (the step's inputs by ``Controller.check``, outside jit: the compiled step of
  :func:`~pixelmpc_jax.devices.compile_controller` runs it before every call). The state's shape and dtype are
  checked again while the step is traced (:func:`checked_state`, :func:`check_x0`), so they hold under a plain
  ``jax.jit(ctrl.step)`` too.
* :func:`step_input_findings`: the step's input values (a NaN, and what the problem adds: a zero quaternion), flagged
  inside the step (``info.input_rejected``) and raised outside jit by ``Controller.check(..., values=True)`` (the
  checked execution of :func:`~pixelmpc_jax.devices.compile_controller`).
* :func:`checked_costs`, :func:`checked_trajectory_costs`: what a running or terminal cost returns.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import settings
from pixelmpc_jax.settings import Range

FLOAT32_MAX = float(np.finfo(np.float32).max)  # 3.4e38: larger numbers (and inf) do not survive float32
TEMPERATURE_MIN = 1e-30  # a smaller lambda flushes to zero in float32 arithmetic: 0 / 0 = NaN weights
SIGMA_MIN, SIGMA_MAX = 1e-18, 1e18  # sigma^2 and 1 / sigma^2 (the control cost) stay normal float32 numbers
TEMPERATURE_RANGE = Range(TEMPERATURE_MIN, FLOAT32_MAX)  # MPPIConfig.temperature (lambda): what float32 carries
NOISE_EXPONENT_RANGE = Range(0.0, 4.0)  # MPPIConfig.noise_exponent (beta)
NUM_SAMPLES_RANGE = Range(1, 2**20, integer=True)  # MPPIConfig.num_samples (N)


def checked_config(config) -> dict[str, tuple[float, ...] | None]:
    """The sequences of an ``MPPIConfig`` as tuples of floats, ``{"noise_sigma", "u_min", "u_max"}``, once every
    field is checked; a ValueError naming the first field out of its range."""
    settings.check(config)  # the numbers, each in its field's range (MPPIConfig's metadata)
    fields = {"noise_sigma": _checked_sigma(config.noise_sigma)}
    m = len(fields["noise_sigma"])
    for name in ("u_min", "u_max"):
        fields[name] = _checked_bound(name, getattr(config, name), m)
    if fields["u_min"] is not None and fields["u_max"] is not None:
        lo, hi = np.asarray(fields["u_min"]), np.asarray(fields["u_max"])
        if np.any(lo > hi):
            raise ValueError(f"MPPIConfig: u_min > u_max in channels {np.nonzero(lo > hi)[0].tolist()} "
                             f"(u_min={fields['u_min']}, u_max={fields['u_max']})")
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


def step_input_checks(dynamics: Callable, state_type: type, T: int, m: int,
                      findings: Callable[[jax.Array, object], dict]) -> Callable:
    """``check(state, x0, params, values=False) -> (state, x0, params)``: what the public step is given, checked
    outside jit.

    ``state`` must be a ``state_type`` whose plan is (T, m); ``x0`` is made an array (in the plan's float type
    if it is an integer or bool state) and checked against ``dynamics`` once per shape and dtype. With ``values``
    the numbers are checked too (a NaN, a zero quaternion: the ``findings``, run eagerly: the checked execution asks
    only once the step has flagged its input), each failed one named in the ValueError.
    """
    checked_state_shapes: set = set()

    def check(state, x0, params, values=False):
        if not isinstance(state, state_type):
            raise TypeError(f"state must be the MPPIState returned by init/step, got {type(state).__name__}")
        if tuple(state.plan.shape) != (T, m):
            raise ValueError(f"state.plan must have shape ({T}, {m}) (horizon, control_dim), got {state.plan.shape}")
        x0 = checked_state(x0, state.plan.dtype)
        signature = (x0.shape, str(x0.dtype))
        if signature not in checked_state_shapes:
            check_x0(dynamics, x0, m, params)
            checked_state_shapes.add(signature)
        if values:
            failed = [message for message, sound in findings(x0, params).items() if not bool(sound)]
            if failed:
                raise ValueError("; ".join(failed))
        return state, x0, params

    return check


def checked_state(x0, float_dtype) -> jax.Array:
    """``x0`` as an array, an integer or bool state (or a list of numbers) in ``float_dtype``: the rollout carries
    floats. Runs on the host or when the step is traced (shapes and dtypes only)."""
    x0 = jnp.asarray(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(float_dtype)
    return x0


def step_input_findings(x0: jax.Array, params, problem_findings: Callable | None) -> dict:
    """``{message: () bool}``, each True where the step's input is sound: x0 finite, no NaN in any float leaf of
    ``params`` (inf may stand for "no limit" there), and the problem's own ``problem_findings(x0, params)``
    (its shape checks raise while it is traced). Inside the step their conjunction flags ``info.input_rejected``;
    outside jit (``Controller.check(..., values=True)``) each failed message is raised."""
    found = {f"x0 must hold finite numbers, shape {tuple(x0.shape)}; it holds NaN or inf": jnp.all(jnp.isfinite(x0))}
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            found[f"params{jax.tree_util.keystr(path)} must hold no NaN"] = ~jnp.any(jnp.isnan(leaf))
    if problem_findings is not None:
        found.update(problem_findings(x0, params))
    return found


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
