"""How the DOF responds to the controls, the thing PixelMPC's pixel cost acts through (Sec. III-D, Fig. 7).

* Multi-step pixel prediction (Fig. 7, :func:`multistep_error`): the target gate's centre
  (``detect_from_geometry`` along the logged trajectory) is predicted ``k = 1..K`` steps ahead by integrating
  the DOF pixel dynamics with the logged orientation and control, as PixelMPC does, ``uv_{k+1} = uv_k + dt *
  pixel_velocity(q_k, uv_k, u_k)``, and compared with where the gate centre really projects. Each start tick
  where the gate is detected with its centre in the image starts one prediction; step ``k`` counts while the
  true centre has stayed in the image and the gate detected on every tick up to ``k``. The same prediction
  with parts of the pixel model swapped (:data:`PIXEL_MODEL_PARTS`: the DOF's response to the rates alone,
  the camera's exact rotational flow alone, and that plus the DOF's flow at zero rate) says which part of
  the DOF holds the prediction back.
* Rotation response (:func:`rotation_response`): the DOF's mean Jacobian at the image centre, px/frame per
  rad/s of the rate given to it (``jax.jacfwd`` over the frames' orientation and input), against the exact
  rotational flow of the pinhole camera per rad/s (``fx dt`` of yaw on u, ``-fy dt`` of pitch on v at the
  images' size), and their ratio: 1 is a pixel model that moves the pixel the way the rates do.
* Pixel-cost ranking (:func:`pixel_cost_rank_correlation`): at logged states where the target is detected,
  512 control sequences are sampled as PixelMPC's MPPI samples them (its noise and bounds, around the logged
  commands as the plan), rolled out with the MPC's robot model over ``t_f = 1 s`` (40 steps), and costed with
  PixelMPC's pixel cost twice: the pixel from the DOF dynamics and from the exact projection of the target.
  The Spearman correlation of the two costs over the samples says whether the DOF ranks the samples as the
  true pixel would (what MPPI's weights depend on); median and quartiles over the states.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.rollout import BatchCost, rollout_costs
from pixelmpc_jax.control.sampling import coloured_noise_filter
from pixelmpc_jax.dynamics import dof, quadrotor, vdof
from pixelmpc_jax.learn.dataset import Lap, lap_input
from pixelmpc_jax.learn.rotation_augment import rotation_homography
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.world import camera as camera_lib

IMAGE_CENTRE_UV = (0.5, 0.5)
RANK_SAMPLES = 512
RANK_T_F = 1.0
RANK_STRIDE = 5
PIXEL_MODELS = ("dof", "vdof")  # the learned pixel models the ranking and the multi-step prediction take


# --------------------------------------------------------------------------------------------------
# Rotation response: how far the DOF moves the pixel per rad/s, against the pinhole camera.
# --------------------------------------------------------------------------------------------------


def exact_rotation_response(camera, dt: float = timing.CONTROL_DT, uv=IMAGE_CENTRE_UV) -> np.ndarray:
    """(2, 3) px/frame per rad/s: the exact rotational flow at the normalised pixel ``uv`` per body rate.

    A point far along the camera ray through ``uv`` (pure rotation: no parallax) is projected after the body
    turned by ``w dt`` (``q (x) exp(w dt / 2)``, the model's convention); ``jax.jacfwd`` at ``w = 0`` gives
    the flow per rad/s over one frame, in pixels at the camera's size. At the image centre of the untilted
    camera this is ``fx dt`` of yaw (wz) on u and ``-fy dt`` of pitch (wy) on v: the camera looks along body
    +x, u grows to the right and v downwards, a positive yaw turns the view left (the scene moves right),
    a positive pitch turns the nose down (the scene moves up). It does not depend on the attitude.
    """
    x0 = quadrotor.hover_state((0.0, 0.0, 0.0))
    uv_px = jnp.asarray(uv, jnp.float32) * jnp.asarray([camera.width, camera.height], jnp.float32)
    far = camera_lib.backproject(uv_px, jnp.asarray(1e4, jnp.float32), x0, camera)
    scale = jnp.asarray([camera.width, camera.height], jnp.float32)

    def pixel(rate, axis):  # the pixel after turning at ``rate`` rad/s about the unit body ``axis`` for dt
        q = quadrotor.quat_multiply(x0[quadrotor.QUAT], quadrotor.quat_exp(rate * axis, dt))
        uv_w, _, _ = camera_lib.project(far, x0.at[quadrotor.QUAT].set(q), camera)
        return uv_w * scale

    jac = jnp.stack([jax.jvp(lambda r, e=e: pixel(r, e), (jnp.asarray(0.0),), (jnp.asarray(1.0),))[1]
                     for e in jnp.eye(3)], axis=1)  # (2, 3): d pixel / d rate at rate 0, per axis
    return np.asarray(jac, np.float64)


def _rotation_jacobian(velocity_fn, dof_params, q, u, uv, scale):
    """(F, 2, 4) d(pixel velocity)/d(input) at ``uv`` per frame, in px/frame per unit input."""
    def one(qf, uf):
        return jax.jacfwd(lambda x: velocity_fn(dof_params, qf, uv, x) * scale)(uf)

    return jax.vmap(one)(q, u)


_rotation_jacobian_jit = jax.jit(_rotation_jacobian, static_argnums=0)


def rotation_response(dof_params, q: np.ndarray, u: np.ndarray, camera, dt: float = timing.CONTROL_DT,
                      velocity_fn=None, uv=IMAGE_CENTRE_UV, chunk: int = 1024, name: str = "dof") -> dict:
    """The DOF's mean Jacobian at the image centre against the exact rotational flow, px/frame per rad/s.

    Args:
        dof_params: the network (passed to ``velocity_fn``).
        q, u: (F, 4) the frames' orientation and the control input the network is given (its variant's).
        camera: the camera (its size sets the pixels; its intrinsics the exact response).
        velocity_fn: ``(dof_params, q, uv, u) -> uv_dot`` in normalised image units per second (default
            ``dof.pixel_velocity``; a stub with a known response in tests; another pixel model's image motion).
        name: what the model's figures are called in the result ("dof"; "vdof" for the velocity-and-depth DOF).

    Returns:
        ``yaw_to_u`` and ``pitch_to_v``: ``{name, "exact", "ratio"}`` (ratio = model / exact); ``jacobian_<name>``
        and ``jacobian_exact``: (2, 3) rows (du, dv), columns (wx, wy, wz); ``jacobian_<name>_std``: the spread of
        the model's Jacobian over the frames; ``frames``; ``uv``.
    """
    velocity_fn = dof.pixel_velocity if velocity_fn is None else velocity_fn
    q, u = np.asarray(q, np.float32), np.asarray(u, np.float32)
    chex.assert_shape([q, u], (None, 4))
    chex.assert_equal_shape([q, u])
    scale = jnp.asarray([camera.width * dt, camera.height * dt], jnp.float32)
    uv_arr = jnp.asarray(uv, jnp.float32)
    jacs = []
    for start in range(0, q.shape[0], chunk):
        stop = min(start + chunk, q.shape[0])
        pad = chunk - (stop - start) if q.shape[0] > chunk else 0
        qc = np.concatenate([q[start:stop], np.repeat(q[stop - 1:stop], pad, 0)])
        uc = np.concatenate([u[start:stop], np.repeat(u[stop - 1:stop], pad, 0)])
        jac = _rotation_jacobian_jit(velocity_fn, dof_params, jnp.asarray(qc), jnp.asarray(uc), uv_arr, scale)
        jacs.append(np.asarray(jac, np.float64)[: stop - start, :, :3])
    jac = np.concatenate(jacs)  # (F, 2, 3)
    mean = jac.mean(axis=0)
    exact = exact_rotation_response(camera, dt, uv)
    model = "DOF" if name == "dof" else name

    def entry(axis: int, rate: int) -> dict:
        d, e = float(mean[axis, rate]), float(exact[axis, rate])
        return {name: d, "exact": e, "ratio": d / e if abs(e) > 1e-12 else None}

    return {"yaw_to_u": entry(0, 2), "pitch_to_v": entry(1, 1), f"jacobian_{name}": mean.tolist(),
            f"jacobian_{name}_std": jac.std(axis=0).tolist(), "jacobian_exact": exact.tolist(),
            "frames": int(q.shape[0]), "uv": list(uv),
            "units": f"px/frame per rad/s of the rate given to the {model}, at the image size"}


# --------------------------------------------------------------------------------------------------
# Pixel-cost ranking of sampled control sequences: DOF against the exact projection.
# --------------------------------------------------------------------------------------------------


def rankdata(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``x`` (1-D), ties given their mean rank (as Spearman's correlation needs)."""
    x = np.asarray(x)
    order = np.argsort(x, kind="mergesort")
    sorted_x = x[order]
    ranks = np.empty(x.shape[0], np.float64)
    ranks[order] = np.arange(1, x.shape[0] + 1, dtype=np.float64)
    # average the ranks over each run of equal values
    boundaries = np.concatenate([[True], sorted_x[1:] != sorted_x[:-1], [True]])
    starts = np.nonzero(boundaries)[0]
    for a, b in zip(starts[:-1], starts[1:]):
        if b - a > 1:
            ranks[order[a:b]] = 0.5 * (a + 1 + b)
    return ranks


def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
    """Spearman's rank correlation of two 1-D arrays (numpy ranks); ``None`` if either is constant."""
    ra, rb = rankdata(a), rankdata(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denominator = np.sqrt(np.sum(ra * ra) * np.sum(rb * rb))
    return float(np.sum(ra * rb) / denominator) if denominator > 0 else None


def _pixel_state_velocity_fn(pixel_model: str, velocity_fn=None) -> Callable:
    """``(params, x (10,), p (d,), u (4,)) -> p_dot (d,)``: the pixel model's dynamics as PixelMPC integrates them,
    "dof" (``velocity_fn(params, q, uv, u)``, default ``dof.pixel_velocity``, d = 2) or "vdof"
    (``velocity_fn(params, x, p, u)``, default ``vdof.pixel_state_velocity``, d = 3)."""
    if pixel_model not in PIXEL_MODELS:
        raise ValueError(f"pixel_model must be one of {PIXEL_MODELS}, got {pixel_model!r}")
    if pixel_model == "vdof":
        return vdof.pixel_state_velocity if velocity_fn is None else velocity_fn
    dof_velocity = dof.pixel_velocity if velocity_fn is None else velocity_fn
    return lambda params, x, uv, u: dof_velocity(params, x[quadrotor.QUAT], uv, u)


@functools.lru_cache(maxsize=8)
def _pixel_cost_pair_fn(config: pixelmpc_lib.ControllerConfig, velocity_fn=None, pixel_model: str = "dof"):
    """The jitted ``(params, x0, p0, controls (N, n_f, 4), target_centre, target_normal, camera) ->
    (cost_model (N,), cost_projection (N,))``: the pixel cost of Eq. (18) over the first ``n_f`` steps with the
    pixel from the learned pixel model's dynamics (``pixel_model`` "dof": p0 the pixel (2,); "vdof": the pixel
    state [u, v, s] (3,), costed on its pixel) and from the exact projection (from ``p0[:2]``), both as
    :func:`pixelmpc.make_pixelmpc` models and costs them (robot model ``quadrotor.step``, the pixel cost only
    while the target is ahead)."""
    velocity = _pixel_state_velocity_fn(pixel_model, velocity_fn)
    dt = config.mppi.dt
    quad_params = quadrotor.QuadParams()
    n = quadrotor.STATE_DIM

    def model_dynamics(X, u, p):
        x, pixel = X[:n], X[n:]
        return jnp.concatenate([quadrotor.step(x, u, dt, quad_params), pixel + dt * velocity(p["dof"], x, pixel, u)])

    def projection_dynamics(X, u, p):
        x_next = quadrotor.step(X[:n], u, dt, quad_params)
        uv, _, in_front = camera_lib.project(p["centre"], x_next, p["camera"])
        uv = jnp.where(in_front, uv, pixelmpc_lib.behind_camera_pixel(uv.dtype))
        return jnp.concatenate([x_next, uv])

    def pixel_term(X, p):
        ahead = jnp.dot(X[quadrotor.POS] - p["centre"], p["normal"]) < 0.0
        return ahead.astype(X.dtype) * pixelmpc_lib.pixel_cost(X[n:n + 2], config)  # a pixel state may hold more

    cost = BatchCost(lambda X, U, t, p: jax.vmap(pixel_term, in_axes=(0, None))(X, p))

    @jax.jit
    def pair(params, x0, p0, controls, centre, normal, camera):
        chex.assert_shape([x0, p0, controls], [(n,), (2 if pixel_model == "dof" else 3,), (None, None, 4)])
        p = {"dof": params, "centre": centre, "normal": normal, "camera": camera}
        return (rollout_costs(model_dynamics, cost, None, jnp.concatenate([x0, p0.astype(x0.dtype)]), controls, p),
                rollout_costs(projection_dynamics, cost, None, jnp.concatenate([x0, p0[:2].astype(x0.dtype)]),
                              controls, p))

    return pair


def sample_control_sequences(key: jax.Array, plan: jax.Array, mppi_config) -> jax.Array:
    """(N, T, m) control sequences around ``plan`` (T, m) as :func:`mppi.make_mppi` samples them: noise of
    std ``noise_sigma`` (coloured if ``noise_exponent``), sample 0 the plan itself (``nominal_sample``),
    clipped to the bounds."""
    N, (T, m) = mppi_config.num_samples, plan.shape
    white = jax.random.normal(key, (N, T, m), dtype=plan.dtype)
    if mppi_config.noise_exponent:
        white = jnp.einsum("ts,nsm->ntm", jnp.asarray(coloured_noise_filter(T, mppi_config.noise_exponent)), white)
    noise = white * jnp.asarray(mppi_config.noise_sigma, plan.dtype)
    if mppi_config.nominal_sample:
        noise = noise.at[0].set(0.0)
    controls = plan[None] + noise
    if mppi_config.u_min is not None:
        controls = jnp.maximum(controls, jnp.asarray(mppi_config.u_min, plan.dtype))
    if mppi_config.u_max is not None:
        controls = jnp.minimum(controls, jnp.asarray(mppi_config.u_max, plan.dtype))
    return controls


def _ranking_starts(laps: list[Lap], track, camera, stride: int, initial) -> list[tuple[Lap, int, jax.Array]]:
    """``(lap, tick, p0)`` of every ``stride``-th tick whose target is detected with its centre in the image; p0
    the pixel model's state of the detection (``initial(detection, gate)``)."""
    starts, detect = [], jax.jit(detector_lib.detect_from_geometry)
    for lap in laps:
        for s in range(0, lap.u.shape[0], int(stride)):
            gate = track.gate(int(lap.target[s]))
            det = detect(gate, jnp.asarray(lap.states[s]), camera)
            if bool(det.found) and bool(camera_lib.in_image(det.centre)):
                starts.append((lap, s, initial(det, gate)))
    return starts


def pixel_cost_rank_correlation(dof_params, laps: list[Lap], track, camera,
                                num_samples: int = RANK_SAMPLES, t_f: float = RANK_T_F, stride: int = RANK_STRIDE,
                                seed: int = 0, velocity_fn=None, config: pixelmpc_lib.ControllerConfig | None = None,
                                progress: bool = False, pixel_model: str = "dof", box_cue: str = "apparent") -> dict:
    """Spearman correlation between a learned pixel model's and the exact projection's pixel cost of sampled
    sequences.

    At every ``stride``-th logged state of ``laps`` where the target gate is detected (geometric detector,
    no noise) with its centre in the image, ``num_samples`` control sequences of ``t_f / dt`` steps are
    sampled as PixelMPC's MPPI samples them (:func:`sample_control_sequences`, PixelMPC's MPPI config) around
    the logged commands from that tick on (the plan MPPI was flying), rolled out with the MPC's robot model
    from the logged state, and costed with PixelMPC's pixel cost (``ControllerConfig``, the l1 cost by default)
    with the model's pixel and with the target's exact projection. The model is given the sampled controls, as
    PixelMPC gives them. ``pixel_model`` "dof" (``dof_params`` a DOF, from the detected centre) or "vdof"
    (``dof_params`` vdof weights, from the detected ``[centre, box size]``, ``box_cue`` as its weights were
    trained, :func:`vdof_detected_state`); the same states and samples for either.

    Returns:
        ``median``, ``q25``, ``q75``, ``mean`` of the per-state correlations; ``states`` counted;
        ``skipped_constant`` (states where either cost did not vary over the samples); ``samples``, ``steps``.
    """
    base = config or pixelmpc_lib.ControllerConfig()
    config = dataclasses.replace(base, t_f=float(t_f), mppi=dataclasses.replace(base.mppi, num_samples=num_samples))
    steps = config.pixel_steps
    pair = _pixel_cost_pair_fn(config, velocity_fn, pixel_model)
    starts = _ranking_starts(laps, track, camera, stride, pixel_state_model(pixel_model, box_cue).initial)
    key = jax.random.key(seed)
    correlations, skipped = [], 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(starts), desc="pixel-cost ranking", unit="state", leave=False)
    for lap, s, p0 in starts:
        idx = np.minimum(np.arange(s, s + steps), lap.u.shape[0] - 1)
        plan = jnp.asarray(lap.u[idx], jnp.float32)
        key, key_sample = jax.random.split(key)
        controls = sample_control_sequences(key_sample, plan, config.mppi)
        gate = int(lap.target[s])
        cost_model, cost_exact = pair(dof_params, jnp.asarray(lap.states[s], jnp.float32), p0, controls,
                                      track.gates.centre[gate], track.gates.normal[gate], camera)
        rho = spearman(np.asarray(cost_model), np.asarray(cost_exact))
        if rho is None:
            skipped += 1
        else:
            correlations.append(rho)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    values = np.asarray(correlations, np.float64)

    def stat(fn):
        return float(fn(values)) if values.size else None

    return {"median": stat(np.median), "q25": stat(lambda v: np.percentile(v, 25)),
            "q75": stat(lambda v: np.percentile(v, 75)), "mean": stat(np.mean), "states": int(values.size),
            "skipped_constant": skipped, "samples": int(num_samples), "steps": int(steps), "t_f_s": float(t_f),
            "stride": int(stride), "pixel_cost": config.pixel_cost}


# --------------------------------------------------------------------------------------------------
# Multi-step pixel prediction (Fig. 7).
# --------------------------------------------------------------------------------------------------


def _at_zero_rate(u: jax.Array) -> jax.Array:
    return u.at[:3].set(0.0)


def exact_rotational_velocity(camera, dt: float, uv: jax.Array, u: jax.Array) -> jax.Array:
    """(2,) pixel velocity (normalised units / s) of a point at infinity while the body turns at ``u[:3]`` rad/s
    for ``dt``: the camera's exact rotational flow (the infinite homography), no translation."""
    scale = jnp.asarray([camera.width, camera.height], jnp.float32)
    h = rotation_homography(quadrotor.rotation_matrix(quadrotor.quat_exp(u[:3], dt)), camera) @ jnp.concatenate(
        [uv * scale, jnp.ones((1,), jnp.float32)])
    return (h[:2] / h[2] / scale - uv) / dt


# Pixel models made of parts of the DOF and of the camera: ``(dof_params, camera, dt, q, uv, u) -> uv_dot``.
PIXEL_MODEL_PARTS = {
    # the DOF, as PixelMPC integrates it
    "dof": lambda p, camera, dt, q, uv, u: dof.pixel_velocity(p, q, uv, u),
    # the DOF's response to the body rates alone: its flow at zero rate (what it learned of the translation,
    # a scene average at that pixel and attitude) taken out
    "dof_rate_response": lambda p, camera, dt, q, uv, u: (dof.pixel_velocity(p, q, uv, u)
                                                          - dof.pixel_velocity(p, q, uv, _at_zero_rate(u))),
    # the camera's exact rotational flow, no translation
    "exact_rotation": lambda p, camera, dt, q, uv, u: exact_rotational_velocity(camera, dt, uv, u),
    # the exact rotational flow plus the DOF's flow at zero rate
    "exact_rotation_dof_rest": lambda p, camera, dt, q, uv, u: (
        exact_rotational_velocity(camera, dt, uv, u) + dof.pixel_velocity(p, q, uv, _at_zero_rate(u))),
}


class PixelStateModel(NamedTuple):
    """A pixel model as the multi-step prediction rolls it along a logged lap (static: hashable functions).

    Attributes:
        initial: ``(detection, gate) -> p (d,)``: the model's pixel state of one detection, ``p[:2]`` the pixel.
        velocity: ``(params, camera, dt, x (10,), p (d,), u (4,)) -> p_dot (d,)`` per second.
    """

    initial: Callable
    velocity: Callable


def detected_centre(detection, gate) -> jax.Array:
    """The DOF's pixel state of a detection: its centre (2,)."""
    return detection.centre


def vdof_detected_state(box_cue: str, detection, gate) -> jax.Array:
    """The vdof's pixel state ``[u, v, s]`` (3,) of a detection of ``gate``: ``s`` the box size of its corners,
    over the opening's ``sqrt(width * height)`` for weights trained with ``box_cue`` "per_gate_size"."""
    gate_size = jnp.sqrt(gate.width * gate.height) if box_cue == "per_gate_size" else 1.0
    return vdof.initial_pixel_state(detection.centre, detection.corners, gate_size)


def _part_velocity(part: str, params, camera, dt: float, x, uv, u) -> jax.Array:
    return PIXEL_MODEL_PARTS[part](params, camera, dt, x[quadrotor.QUAT], uv, u)


def _vdof_velocity(params, camera, dt: float, x, p, u) -> jax.Array:
    return vdof.pixel_state_velocity(params, x, p, u)


DOF_PART_MODELS = {part: PixelStateModel(detected_centre, functools.partial(_part_velocity, part))
                   for part in PIXEL_MODEL_PARTS}
VDOF_BOX_CUES = ("apparent", "per_gate_size")
VDOF_MODELS = {cue: PixelStateModel(functools.partial(vdof_detected_state, cue), _vdof_velocity)
               for cue in VDOF_BOX_CUES}


def pixel_state_model(pixel_model: str = "dof", box_cue: str = "apparent") -> PixelStateModel:
    """The DOF (``pixel_model`` "dof") or the vdof with its weights' ``box_cue`` ("vdof") as a
    :class:`PixelStateModel`."""
    if pixel_model not in PIXEL_MODELS:
        raise ValueError(f"pixel_model must be one of {PIXEL_MODELS}, got {pixel_model!r}")
    if box_cue not in VDOF_BOX_CUES:
        raise ValueError(f"box_cue must be one of {VDOF_BOX_CUES}, got {box_cue!r}")
    return DOF_PART_MODELS["dof"] if pixel_model == "dof" else VDOF_MODELS[box_cue]


@functools.partial(jax.jit, static_argnames=("model", "horizon", "dt"))
def _multistep_lap(model: PixelStateModel, params, track, camera, states, controls, target, horizon: int, dt: float):
    """Per start tick s (F,) and step k = 0..K: the model's pixel state rolled k steps from the detection at s
    along the logged states and ``controls``, against the detection at s + k, both of the start's target gate.

    Returns err (F, K+1) px of the pixel, err_zero (F, K+1) px (the pixel held still), valid (F, K+1) bool (the
    gate detected with its centre in the image on every tick up to k), pred (F, K+1, d) and truth (F, K+1, d)
    the rolled and the detected pixel states."""
    F = controls.shape[0]
    chex.assert_shape([states, controls, target], [(F + 1, quadrotor.STATE_DIM), (F, 4), (F + 1,)])
    scale = jnp.asarray([camera.width, camera.height], jnp.float32)
    ks = jnp.arange(horizon + 1)

    def one_start(s):
        gate = track.gate(target[s])
        idx = jnp.minimum(s + ks, F)  # state index of step k
        det = jax.vmap(lambda x: detector_lib.detect_from_geometry(gate, x, camera))(states[idx])
        seen = det.found & camera_lib.in_image(det.centre) & (s + ks <= F)
        tracked = jnp.cumprod(seen.astype(jnp.int32)).astype(bool)  # seen on every tick up to k
        truth = jax.vmap(model.initial, in_axes=(0, None))(det, gate)  # (K+1, d)

        def step(p, k):
            j = jnp.minimum(s + k, F - 1)
            p_next = p + dt * model.velocity(params, camera, dt, states[j], p, controls[j])
            return p_next, p_next

        _, rollout = jax.lax.scan(step, truth[0], ks[:-1])
        pred = jnp.concatenate([truth[:1], rollout])  # (K+1, d)
        err = jnp.linalg.norm((pred[:, :2] - truth[:, :2]) * scale, axis=-1)
        err_zero = jnp.linalg.norm((truth[0, :2] - truth[:, :2]) * scale, axis=-1)
        return err, err_zero, tracked, pred, truth

    return jax.vmap(one_start)(jnp.arange(F))


def multistep_windows(model: PixelStateModel, params, laps: list[Lap], track, camera, horizon: int = 80,
                      dt: float = timing.CONTROL_DT, input: str = "command") -> dict:
    """The multi-step prediction of every start tick of ``laps`` (rows, laps concatenated), steps k = 1..horizon
    (columns), the model given the logged control input ``input``: ``err``, ``err_zero`` (px), ``valid`` (bool),
    ``pred`` and ``truth`` (..., d) (:func:`_multistep_lap`). Which windows count does not depend on the model."""
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    parts = [_multistep_lap(model, params, track, camera, jnp.asarray(lap.states), jnp.asarray(lap_input(lap, input)),
                            jnp.asarray(lap.target), int(horizon), float(dt)) for lap in laps]
    names = ("err", "err_zero", "valid", "pred", "truth")
    return {name: np.concatenate([np.asarray(part[i])[:, 1:] for part in parts]) for i, name in enumerate(names)}


def multistep_summary(err: np.ndarray, err_zero: np.ndarray, valid: np.ndarray, dt: float) -> dict:
    """Per step k = 1..K (columns of the (S, K) arrays), over the valid windows: ``mean_px``, ``std_px``,
    ``count``, ``zero_motion_mean_px`` (``None`` where no window reaches k); ``steps``, ``dt_s``, ``starts``."""
    horizon = err.shape[1]

    def column_stat(values, fn):
        return [float(fn(values[valid[:, k], k])) if valid[:, k].any() else None for k in range(horizon)]

    return {
        "steps": list(range(1, horizon + 1)),
        "dt_s": float(dt),
        "mean_px": column_stat(err, np.mean),
        "std_px": column_stat(err, np.std),
        "count": [int(c) for c in valid.sum(0)],
        "zero_motion_mean_px": column_stat(err_zero, np.mean),
        "starts": int(valid[:, 0].sum()),
    }


def multistep_error(dof_params: dof.DOFParams, laps: list[Lap], track, camera,
                    horizon: int = 80, dt: float = timing.CONTROL_DT, input: str = "command",
                    part: str = "dof") -> dict:
    """Mean and std of the pixel error of the gate centre predicted ``k = 1..horizon`` steps ahead (Fig. 7),
    the DOF given the logged control input ``input`` ("command", or "flown": the rates flown over each frame);
    ``part`` swaps the pixel model for one of :data:`PIXEL_MODEL_PARTS` (default the DOF).

    Returns lists of length ``horizon`` (``None`` where no prediction reaches that step): ``mean_px``,
    ``std_px``, ``count``, and ``zero_motion_mean_px`` (the error of assuming the pixel does not move).
    """
    if part not in PIXEL_MODEL_PARTS:
        raise ValueError(f"part must be one of {tuple(PIXEL_MODEL_PARTS)}, got {part!r}")
    windows = multistep_windows(DOF_PART_MODELS[part], dof_params, laps, track, camera, horizon, dt, input)
    return {**multistep_summary(windows["err"], windows["err_zero"], windows["valid"], dt), "input": input,
            "part": part}
