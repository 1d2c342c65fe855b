"""Which gate a detection shows when the gates look alike: each candidate against the map seen from the estimate.

With one paint for every gate (``render.GATE_PAINTS``), the image detector reports the gate-like components in view
(:class:`~pixelmpc_jax.perception.detector.Candidates`) and cannot say which gate each is. The estimator names it:

1. Predict. Every mapped gate is projected from the estimated pose as a camera's detector would report it
   (:func:`~pixelmpc_jax.perception.detector.detect_in_view`: its centre and the box of its visible frame).
2. Measure. A candidate's distance to a gate's prediction is, in pixels, the larger of the distance between their
   centres and their shape's gap: the largest distance between their opening's corners where both show a corner, else
   the largest gap between their boxes' edges (:func:`detection_distance_px`). So a far gate seen through a near
   one's opening, whose centre the near one's nearly shares, is told apart by its size; and a gate whose frame
   touches another's in the image (one painted component, its box the union of both) is still known by its opening.
3. Decide. The candidate nearest the target gate's prediction is taken when it lies within
   ``AssociationConfig.gate_px`` of it (else the tick is *rejected*) and when nothing rivals it: its distance is
   less than ``AssociationConfig.ratio`` times both the next candidate's distance to the target's prediction and
   its own distance to any other mapped gate's prediction that no other candidate lies nearer to (else the tick is
   *ambiguous*): a far gate whose own component shows beside the target's is explained by that component. Where the
   estimator places the gates with an uncertainty (gates estimated from the map), a prediction may lie anywhere
   within three times what that uncertainty subtends at the gate's distance: a candidate is measured by how far it
   lies beyond that, plus its shape's gap to the prediction's (the size the gate's distance gives it), so that a
   near gate and a far one seen beside it are told apart by their size where their places are uncertain. A rejected or
   ambiguous tick makes no update (the filter sees no detection) and is counted (:data:`OUTCOMES`).

:func:`associate` is the decision, pure (jit- and vmap-able). :func:`make_associating` composes it in front of any
:class:`~pixelmpc_jax.perception.estimator.Estimator`: its state carries the last estimate, which the tick's IMU
carries to the frame's time as the association's prior (the inner filter's own predict then runs as before).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.perception.estimator import Estimator, EstimatorParams, checked_x0
from pixelmpc_jax.perception.particle_filter import propagate_preintegrated
from pixelmpc_jax.settings import Range, check, setting

# What became of a tick's candidates (the per-tick code, EpisodeLog.association): nothing in view; a candidate named
# the target; the nearest lay beyond the gate (or the target is not in view from the estimate); another candidate or
# another gate's prediction nearly as close. -1 where the loop does not associate (the gates have their own hues).
OUTCOMES = ("none", "accepted", "rejected", "ambiguous")
NONE, ACCEPTED, REJECTED, AMBIGUOUS = range(len(OUTCOMES))
NOT_ASSOCIATING = -1


@dataclasses.dataclass(frozen=True)
class AssociationConfig:
    """Static settings of the association (hashable).

    Attributes:
        max_candidates: K, the components the image detector reports at most (the largest), padded to K.
        gate_px: pixels; a candidate farther than this from the target gate's prediction is rejected.
        ratio: the nearest candidate is taken only when its distance is less than ``ratio`` times its rivals' (the
            next candidate's distance to the target's prediction, its distance to another gate's prediction).
    """

    max_candidates: int = setting(4, range=Range(1, 32, integer=True), help="gates painted alike: the image "
                                  "detector's candidates per frame at most (the largest components), in {range}")
    gate_px: float = setting(20.0, range=Range(0.0, 1e4, lo_open=True, unit="px"), help="gates painted alike: a "
                             "candidate farther than this from the target gate's prediction from the estimate is "
                             "rejected (no update, counted), in {range}")
    ratio: float = setting(0.5, range=Range(0.0, 1.0, lo_open=True), help="gates painted alike: the nearest "
                           "candidate is taken only when its distance is under RATIO times the next candidate's and "
                           "under RATIO times its distance to another gate's prediction (else ambiguous: no update, "
                           "counted), in {range}")

    def __post_init__(self):
        check(self)


def detection_distance_px(a: detector_lib.Detection, b: detector_lib.Detection, camera) -> jax.Array:
    """() pixels between two reports of a gate (single ``Detection`` s; ``found`` and ``gate_id`` unread):
    ``max(|c_a - c_b|, shape gap)``, the shape gap ``max_k |corner_a,k - corner_b,k|`` over the opening's corners both
    show, or with none in common ``max_i |box_a,i - box_b,i|`` over the boxes' edges. Centres (2,), corners (4, 2)
    and boxes ``[u_min, v_min, u_max, v_max]`` (4,) are normalised; the gaps are scaled to pixels."""
    scale = jnp.asarray([camera.width, camera.height], a.centre.dtype)
    centre_gap = jnp.sqrt(jnp.sum(((a.centre - b.centre) * scale) ** 2))
    shared = a.corners_visible & b.corners_visible  # (4,)
    corner_gaps = jnp.sqrt(jnp.sum(((a.corners - b.corners) * scale) ** 2, axis=-1))  # (4,)
    corner_gap = jnp.max(jnp.where(shared, corner_gaps, 0.0))
    box_gap = jnp.max(jnp.abs(a.bbox - b.bbox) * jnp.tile(scale, 2))
    return jnp.maximum(centre_gap, jnp.where(jnp.any(shared), corner_gap, box_gap))


def shape_distance_px(a: detector_lib.Detection, b: detector_lib.Detection, camera) -> jax.Array:
    """() pixels between two reports' shapes, wherever they lie: the largest gap between their opening's corners both
    show, each taken from its own centre, or with none in common the larger gap between their boxes' widths and
    heights (single ``Detection`` s, normalised, as :func:`detection_distance_px`)."""
    scale = jnp.asarray([camera.width, camera.height], a.centre.dtype)
    shared = a.corners_visible & b.corners_visible
    gaps = jnp.sqrt(jnp.sum((((a.corners - a.centre) - (b.corners - b.centre)) * scale) ** 2, axis=-1))
    size_a, size_b = a.bbox[2:] - a.bbox[:2], b.bbox[2:] - b.bbox[:2]
    return jnp.where(jnp.any(shared), jnp.max(jnp.where(shared, gaps, 0.0)), jnp.max(jnp.abs(size_a - size_b) * scale))


def predict_gates(gates, x_prior: jax.Array, camera) -> detector_lib.Detection:
    """Every mapped gate (``gates``: a G-batch) as a camera's detector would report it from ``x_prior`` (10,): a
    :class:`~pixelmpc_jax.perception.detector.Detection` with a leading G axis."""
    return jax.vmap(lambda gate: detector_lib.detect_in_view(gate, x_prior, camera))(gates)


def associate(candidates: detector_lib.Candidates, x_prior: jax.Array, gates, camera,
              config: AssociationConfig, gate_std=None) -> tuple[detector_lib.Detection, jax.Array]:
    """The detection of the target gate ``candidates.target`` among ``candidates`` (K slots), from the map's
    ``gates`` (G-batch) seen from the estimated pose ``x_prior`` (10,) (module docstring). ``gate_std``: (G,) m, how
    far each gate's centre may stand from where ``gates`` put it (1 sigma; an estimator that estimates the gates):
    within three times what that std subtends at the gate's distance its prediction may lie anywhere, and a candidate
    is measured by how far it lies beyond that plus how far its shape is from the prediction's
    (:func:`shape_distance_px`: the size the gate's distance gives it), in the gate and the ratio test alike (None:
    the distance of :func:`detection_distance_px`).

    Returns:
        detection: the chosen candidate as the target's ``Detection`` (``found`` only when accepted; a detection
            not found otherwise, centre (0.5, 0.5), no box, no corners).
        outcome: () int32, one of :data:`NONE`, :data:`ACCEPTED`, :data:`REJECTED`, :data:`AMBIGUOUS`.
    """
    predicted = predict_gates(gates, x_prior, camera)  # (G,) leaves
    num_gates = predicted.found.shape[0]
    target = jnp.clip(jnp.asarray(candidates.target, jnp.int32), 0, num_gates - 1)
    dtype = predicted.centre.dtype
    seen = detector_lib.Detection(  # the candidates as K reports
        found=candidates.found, centre=candidates.centre.astype(dtype), bbox=candidates.bbox.astype(dtype),
        corners=candidates.corners.astype(dtype), corners_visible=candidates.corners_visible,
        gate_id=jnp.full(candidates.found.shape, -1, jnp.int32))
    pairwise = jax.vmap(jax.vmap(detection_distance_px, in_axes=(None, 0, None)), in_axes=(0, None, None))
    distance = pairwise(seen, predicted, camera)  # (K, G) px
    visible = candidates.found[:, None] & predicted.found[None, :]
    distance = jnp.where(visible, distance, jnp.inf)
    if gate_std is not None:  # each gate's position uncertainty, in pixels at its distance
        # within its uncertainty a gate may stand anywhere: a candidate is scored by how far it lies beyond that
        # uncertainty plus how far its shape (the size the gate's distance gives it) is from the prediction's, in
        # pixels, and one lying beyond the gate (config.gate_px) outside that uncertainty is no match
        depth = jnp.maximum(jnp.linalg.norm(gates.centre - x_prior[:3], axis=-1), 1.0)  # (G,)
        slack = 3.0 * camera.fx * jnp.asarray(gate_std, dtype) / depth
        shapes = jax.vmap(jax.vmap(shape_distance_px, in_axes=(None, 0, None)), in_axes=(0, None, None))
        beyond = jnp.maximum(distance - slack[None, :], 0.0)
        distance = jnp.where(beyond <= config.gate_px, beyond + shapes(seen, predicted, camera), jnp.inf)
    to_target = distance[:, target]  # (K,)
    best = jnp.argmin(to_target)
    nearest = to_target[best]
    slots, gate_ids = jnp.arange(to_target.shape[0]), jnp.arange(num_gates)
    next_candidate = jnp.min(jnp.where(slots == best, jnp.inf, to_target))
    # another gate rivals the candidate only where the candidate is its nearest: a gate whose own component shows
    # (a far gate seen beside or through the target) is explained by that component, not by this one
    claims = distance[best] <= jnp.min(jnp.where((slots == best)[:, None], jnp.inf, distance), axis=0)  # (G,)
    other_gate = jnp.min(jnp.where((gate_ids == target) | ~claims, jnp.inf, distance[best]))
    rival = jnp.minimum(next_candidate, other_gate)
    outcome = jnp.where(~jnp.any(candidates.found), NONE,
                        jnp.where(~(nearest <= config.gate_px), REJECTED,
                                  jnp.where(~(nearest < config.ratio * rival), AMBIGUOUS, ACCEPTED)))
    taken = outcome == ACCEPTED
    detection = detector_lib.Detection(
        found=taken,
        centre=jnp.where(taken, candidates.centre[best], 0.5),
        bbox=jnp.where(taken, candidates.bbox[best], 0.0),
        corners=jnp.where(taken, candidates.corners[best], 0.0),
        corners_visible=candidates.corners_visible[best] & taken,
        gate_id=target,
    )
    return detection, outcome.astype(jnp.int32)


class AssociatingState(NamedTuple):
    """:func:`make_associating`'s state: the inner estimator's and the last estimate ``mean`` (10,)."""

    inner: Any
    mean: jax.Array


class AssociationInfo(NamedTuple):
    """A step's diagnostics: ``outcome`` () int32 (:data:`OUTCOMES`) and the inner estimator's ``info``."""

    outcome: jax.Array
    inner: Any


def prior_mean(mean: jax.Array, imu) -> jax.Array:
    """(10,) the last estimate ``mean`` carried over the tick by its IMU (``sim.plant.TickIMU``, preintegrated; None:
    kept): the pose the frame was taken from, as the estimate has it before the frame's update."""
    if imu is None:
        return mean
    zero = jnp.zeros(3, mean.dtype)
    return propagate_preintegrated(mean, imu, zero, zero).astype(mean.dtype)


def _next_gate(candidates: detector_lib.Candidates, x_prior: jax.Array, gates, camera, config: AssociationConfig,
               gate_std, target: detector_lib.Detection) -> detector_lib.Detection:
    """The gate after the target named among ``candidates`` as the target is (:func:`associate`): nothing past the last
    gate, nor where it would take the candidate the target took."""
    num_gates = gates.centre.shape[0]
    following = jnp.asarray(candidates.target, jnp.int32) + 1
    detection, _ = associate(candidates.replace(target=following), x_prior, gates, camera, config, gate_std)
    taken = target.found & jnp.all(detection.centre == target.centre)
    keep = detection.found & (following < num_gates) & ~taken
    return detection.replace(found=keep, corners_visible=detection.corners_visible & keep,
                             gate_id=jnp.minimum(following, num_gates - 1))


def make_associating(estimator: Estimator, config: AssociationConfig = AssociationConfig()) -> Estimator:
    """``estimator`` fed by :func:`associate`: its ``step(state, imu, candidates, params)`` takes the image's
    :class:`~pixelmpc_jax.perception.detector.Candidates`, names the target's from the last estimate carried over the
    tick (:func:`prior_mean`) and the map's gates where the estimator places them (``params.gates``, or
    ``estimator.place_gates`` of them, the association's pixel gate widened by their uncertainty), and steps
    ``estimator`` with that detection (none when rejected or ambiguous). An estimator that takes two detections a
    tick (``Estimator.detections_per_tick``) gets the next gate's too, named the same way. Its ``info`` is
    :class:`AssociationInfo` (the target's outcome); ``init``, ``align``, ``place_gates`` and ``config`` are the
    inner estimator's, the state an :class:`AssociatingState`."""
    per_tick = estimator.detections_per_tick

    def init(key: jax.Array, x0: jax.Array, *gate_std) -> AssociatingState:
        return AssociatingState(inner=estimator.init(key, x0, *gate_std), mean=checked_x0(x0))

    def step(state: AssociatingState, imu, candidates: detector_lib.Candidates, params: EstimatorParams):
        gates, gate_std = params.gates, None
        if estimator.place_gates is not None:
            gates, gate_std = estimator.place_gates(state.inner, params.gates)
        prior = prior_mean(state.mean, imu)
        detection, outcome = associate(candidates, prior, gates, params.camera, config, gate_std)
        if per_tick > 1:
            following = _next_gate(candidates, prior, gates, params.camera, config, gate_std, detection)
            detection = detector_lib.stack_detections(detection, following)
        estimate, inner, info = estimator.step(state.inner, imu, detection, params)
        state = AssociatingState(inner=inner, mean=estimate.mean.astype(state.mean.dtype))
        return estimate, state, AssociationInfo(outcome=outcome, inner=info)

    def check_inputs(state: AssociatingState, imu, candidates: detector_lib.Candidates, params: EstimatorParams):
        k = jnp.shape(candidates.found)
        expected = {"found": (*k,), "centre": (*k, 2), "bbox": (*k, 4), "corners": (*k, 4, 2),
                    "corners_visible": (*k, 4), "target": ()}
        for name, shape in expected.items():
            if len(k) != 1 or jnp.shape(getattr(candidates, name)) != shape:
                raise ValueError(f"candidates.{name} must have shape {shape} (K candidates), got "
                                 f"{jnp.shape(getattr(candidates, name))}")
        inner, imu, _, params = estimator.check(state.inner, imu, None, params)
        return state._replace(inner=inner), imu, candidates, params

    def align(state: AssociatingState, accel_mean, gyro_mean) -> AssociatingState:
        return state._replace(inner=estimator.align(state.inner, accel_mean, gyro_mean))

    return Estimator(init=init, step=step, check=check_inputs, config=estimator.config,
                     align=None if estimator.align is None else align, place_gates=estimator.place_gates,
                     detections_per_tick=per_tick)
