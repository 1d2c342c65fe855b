"""What every estimator is: a pair of pure functions over its own state, built once from its configuration.

Like the controller (:class:`~pixelmpc_jax.control.mppi.Controller`), an :class:`Estimator` is ``init`` and
``step`` (and ``align`` where it has one), pure: nothing is mutated, the PRNG key travels in the state, and the
caller decides how they are compiled and batched (:func:`~pixelmpc_jax.devices.compile_estimator`, or a larger
``jax.jit`` around a closed loop)::

    est = make_eskf(ESKFConfig())                  # or make_particle_filter, make_guarded_particle_filter, make_truth
    state = est.init(key, x0)                      # x0: (10,) the prior's mean
    estimate, state, info = est.step(state, imu, detection, EstimatorParams(track.gates, camera))

Every step returns the same :class:`Estimate` (the mean, its position covariance's trace and the detection as the
filter's gate let it through), so a closed loop built on one estimator reads every other the same way; each
estimator's own diagnostics are in ``info``. This module holds the protocol and the true state's estimator; the
filters build theirs beside their algorithms (:func:`~pixelmpc_jax.perception.particle_filter.make_particle_filter`,
:func:`~pixelmpc_jax.perception.filter_guards.make_guarded_particle_filter`,
:func:`~pixelmpc_jax.perception.eskf.make_eskf`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.dynamics.quadrotor import STATE_DIM


class EstimatorParams(NamedTuple):
    """What a step reads beside its inputs (a pytree: new values never recompile).

    Attributes:
        gates: the map's ``Gate`` batch (G leading axis, ``track.gates``): the corners a detection is compared with.
        camera: the onboard camera.
        delay_ticks: () int, how many ticks before now the detection's image was taken (0: on time); the Kalman
            filter files a late detection at its capture tick, the others ignore it.
        x_true: (10,) the true state, read only by :func:`make_truth` (None for a filter).
    """

    gates: Any
    camera: Any
    delay_ticks: Any = 0
    x_true: jax.Array | None = None


class Estimate(NamedTuple):
    """What every estimator reports at a tick.

    Attributes:
        mean: (10,) the estimated state ``[p, q(wxyz), v]``, ``qw >= 0`` for the filters.
        position_cov_trace: () m^2, trace of the estimate's position covariance (0 for the truth).
        detection: the tick's ``detector.Detection`` as the filter used it: ``found`` and ``corners_visible`` cleared
            where its gate rejected the detection (as given otherwise).
        gates: the map's ``Gate`` batch where an estimator that estimates the gates places them now (the Kalman
            filter started with ``gate_std``); None: the map's gates as they are.
    """

    mean: jax.Array
    position_cov_trace: jax.Array
    detection: Any
    gates: Any = None


class Estimator(NamedTuple):
    """An estimator as pure functions over its state (the controller's shape; module docstring).

    Attributes:
        init: ``init(key, x0) -> state``: the estimator's first state about ``x0`` (10,); ``key`` draws what it
            draws (a particle cloud) and travels in the state. An estimator that can estimate the gates (the Kalman
            filter) takes ``init(key, x0, gate_std)`` too: ``gate_std`` (G, 4) the prior stds of each gate's offset
            from the map (``course.gate_prior_std``), and reports the gates where it places them in ``Estimate.gates``.
        step: ``step(state, imu, detection, params) -> (Estimate, state, info)``: one control tick with the IMU of the
            tick that led to now (``sim.plant.TickIMU``, or None: no motion update) and the detection of the target
            gate (``detector.Detection``, or None: no sensor update); ``params`` an :class:`EstimatorParams`.
        check: ``check(state, imu, detection, params) -> (state, imu, detection, params)``: the step's inputs checked
            outside jit (a ValueError naming the expected shape), as the step takes them.
        config: the configuration it was built with (None for the truth).
        align: ``align(state, accel_mean, gyro_mean) -> state``: the state before the first step, updated with the IMU's
            mean readings (3,), (3,) at rest on the pad; None where the estimator has none.
        place_gates: ``place_gates(state, gates) -> (gates, std)``: the map's ``gates`` (G-batch) where the state
            places them, and how far each centre, seen from the estimate, may still stand off that place, (G,) m (1
            sigma: the gate's own uncertainty and the pose's over its distance); None where the estimator has no
            covariance to tell it (the truth, the particle filter).
        detections_per_tick: K, the gates' detections a step takes: 1, the target gate's; 2 (the Kalman filter with
            the gates as states), the next gate's too, stacked on a leading axis, the target's first.
    """

    init: Callable[..., Any]
    step: Callable[..., tuple[Estimate, Any, Any]]
    check: Callable[..., tuple]
    config: Any = None
    align: Callable[..., Any] | None = None
    place_gates: Callable[..., Any] | None = None
    detections_per_tick: int = 1


def checked_x0(x0) -> jax.Array:
    """An estimator's first state ``x0`` (10,) as float32; a ValueError naming its expected shape."""
    x0 = jnp.asarray(x0, jnp.float32)
    if x0.shape != (STATE_DIM,):
        raise ValueError(f"x0 must have shape ({STATE_DIM},) = [p, q(wxyz), v], got {x0.shape}")
    return x0


def make_truth() -> Estimator:
    """The true state as the estimate: what the controller sees when it is given the world's state
    (``params.x_true``), with no covariance and every detection kept. Its state is a () placeholder."""

    def init(key: jax.Array, x0: jax.Array) -> jax.Array:
        del key
        checked_x0(x0)
        return jnp.zeros(())

    def step(state, imu, detection, params: EstimatorParams):
        del imu
        return Estimate(mean=params.x_true, position_cov_trace=jnp.asarray(0.0), detection=detection), state, None

    def check(state, imu, detection, params: EstimatorParams):
        if params.x_true is None or jnp.shape(params.x_true) != (STATE_DIM,):
            raise ValueError(f"the truth reads params.x_true ({STATE_DIM},), got "
                             f"{None if params.x_true is None else jnp.shape(params.x_true)}")
        return state, imu, detection, params

    return Estimator(init=init, step=step, check=check)


def checked_spread(spread) -> tuple[float, float, float]:
    """A prior's ``spread`` (position m, attitude rad, velocity m/s) as floats; a ValueError naming what is wrong."""
    spread = tuple(float(s) for s in spread)
    if len(spread) != 3 or not all(math.isfinite(s) and s >= 0 for s in spread):
        raise ValueError(f"spread must be 3 finite stds >= 0 (position, attitude, velocity), got {spread}")
    return spread
