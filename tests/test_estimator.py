"""The estimator protocol (``perception/estimator.py``): every estimator is a pure ``init``/``step`` pair (``align``
where it has one) that reports the same :class:`Estimate`, and the filters batch with ``jax.vmap`` inside one jit as
they run one by one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import devices
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception import eskf as eskf_lib
from pixelmpc_jax.perception import filter_guards as guards_lib
from pixelmpc_jax.perception import particle_filter as pf_lib
from pixelmpc_jax.perception.estimator import Estimate, Estimator, EstimatorParams, make_truth
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.timing import CONTROL_DT
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

COURSE = course_lib.straight_course(num_gates=2, height=3.0, first_gate_x=20.0)
CAMERA = camera_lib.default_camera()
PF = pf_lib.PFConfig(num_particles=256)
BATCH = 8


def _estimators() -> dict[str, Estimator]:
    return {
        "truth": make_truth(),
        "pf": pf_lib.make_particle_filter(PF),
        "guarded_pf": guards_lib.make_guarded_particle_filter(
            PF, guards_lib.GuardConfig(detection_gate_px=30.0, recover_error_px=120.0)),
        "eskf": eskf_lib.make_eskf(eskf_lib.ESKFConfig(align_s=1.0)),
    }


def _tick(y: float = 0.0):
    """A pose 6 m before the first gate (``y`` m to the side), its detection and a hover tick of IMU samples."""
    x = quadrotor.hover_state((14.0, y, 3.0))
    detection = detector_lib.detect_from_geometry(COURSE.gate(0), x, CAMERA, gate_id=0)
    return x, detection, plant_lib.hover_tick_imu(CONTROL_DT)


def _shapes(tree):
    return jax.tree_util.tree_map(lambda a: (jnp.shape(a), jnp.result_type(a)), tree)


@pytest.mark.parametrize("name", ["truth", "pf", "guarded_pf", "eskf"])
def test_every_estimator_has_the_protocols_shape(name):
    """init -> state; step -> (Estimate, state of the same structure, info); check returns the inputs; align (where
    there is one) keeps the state's structure. Traced only (``jax.eval_shape``): nothing compiles."""
    est = _estimators()[name]
    assert isinstance(est, Estimator) and callable(est.init) and callable(est.step) and callable(est.check)
    x, detection, imu = _tick()
    params = EstimatorParams(gates=COURSE.gates, camera=CAMERA, delay_ticks=0, x_true=x)
    state = jax.eval_shape(est.init, jax.random.PRNGKey(0), x)
    estimate, after, _ = jax.eval_shape(est.step, state, imu, detection, params)
    assert isinstance(estimate, Estimate)
    assert estimate.mean.shape == (quadrotor.STATE_DIM,) and estimate.position_cov_trace.shape == ()
    assert _shapes(estimate.detection) == _shapes(detection)  # the detection as the filter's gate let it through
    assert _shapes(after) == _shapes(state)
    concrete = jax.jit(est.init)(jax.random.PRNGKey(0), x)
    checked = est.check(concrete, imu, detection, params)
    assert checked[1] is imu and checked[2] is detection and checked[3] is params
    if name == "eskf":
        assert _shapes(jax.eval_shape(est.align, state, jnp.zeros(3), jnp.zeros(3))) == _shapes(state)
    else:
        assert est.align is None
    with pytest.raises(ValueError, match="x0 must have shape"):
        est.init(jax.random.PRNGKey(0), jnp.zeros(9))


def test_the_truth_reports_the_true_state_and_keeps_every_detection():
    x, detection, imu = _tick(0.3)
    truth = make_truth()
    params = EstimatorParams(gates=COURSE.gates, camera=CAMERA, x_true=x)
    estimate, state, info = truth.step(truth.init(jax.random.PRNGKey(0), x), imu, detection, params)
    np.testing.assert_array_equal(estimate.mean, x)
    assert float(estimate.position_cov_trace) == 0.0 and estimate.detection is detection and info is None
    with pytest.raises(ValueError, match="params.x_true"):
        truth.check(state, imu, detection, params._replace(x_true=None))


@pytest.mark.parametrize("name", ["pf", "eskf"])
def test_a_vmapped_step_over_eight_filters_in_one_jit_matches_eight_single_runs(name):
    """Eight filters about eight poses, their step vmapped inside one jit, against each filter's own compiled step:
    the same estimates and states (the particle filter to float rounding of the batched kernels)."""
    est = {"pf": pf_lib.make_particle_filter(PF, spread=(0.3, 0.03, 0.2)), "eskf": eskf_lib.make_eskf()}[name]
    ys = np.linspace(-0.4, 0.4, BATCH)
    poses, detections, imu = zip(*(_tick(float(y)) for y in ys))
    poses = jnp.stack(poses)
    detections = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *detections)
    params = EstimatorParams(gates=COURSE.gates, camera=CAMERA)
    keys = jax.random.split(jax.random.PRNGKey(5), BATCH)
    states = jax.jit(jax.vmap(est.init))(keys, poses.at[:, 1].add(0.2))  # each filter starts 0.2 m off

    @jax.jit
    def batched(states, detections):
        return jax.vmap(est.step, in_axes=(0, None, 0, None))(states, imu[0], detections, params)

    b_estimate, b_state, _ = batched(states, detections)
    single = devices.compile_estimator(est)
    for i in range(BATCH):
        state_i, detection_i = (jax.tree_util.tree_map(lambda a, i=i: a[i], tree) for tree in (states, detections))
        estimate, state, _ = single.step(state_i, imu[0], detection_i, params)
        np.testing.assert_allclose(b_estimate.mean[i], estimate.mean, atol=1e-4)
        np.testing.assert_allclose(b_estimate.position_cov_trace[i], estimate.position_cov_trace, rtol=1e-3,
                                   atol=1e-7)
        np.testing.assert_array_equal(b_estimate.detection.found[i], estimate.detection.found)
        for a, b in zip(jax.tree_util.tree_leaves(b_state), jax.tree_util.tree_leaves(state)):
            np.testing.assert_allclose(np.asarray(a[i], np.float64), np.asarray(b, np.float64), atol=1e-4)
    assert single.num_compilations() == 1
