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

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
from pixelmpc_jax.control.mppi import BatchCost, coloured_noise_filter, rollout_costs
from pixelmpc_jax.dynamics import dof, quadrotor
from pixelmpc_jax.learn.dataset import Lap, lap_input
from pixelmpc_jax.learn.rotation_augment import rotation_homography
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.world import camera as camera_lib

IMAGE_CENTRE_UV = (0.5, 0.5)
RANK_SAMPLES = 512
RANK_T_F = 1.0
RANK_STRIDE = 5


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
                      velocity_fn=None, uv=IMAGE_CENTRE_UV, chunk: int = 1024) -> dict:
    """The DOF's mean Jacobian at the image centre against the exact rotational flow, px/frame per rad/s.

    Args:
        dof_params: the network (passed to ``velocity_fn``).
        q, u: (F, 4) the frames' orientation and the control input the network is given (its variant's).
        camera: the camera (its size sets the pixels; its intrinsics the exact response).
        velocity_fn: ``(dof_params, q, uv, u) -> uv_dot`` in normalised image units per second (default
            ``dof.pixel_velocity``; a stub with a known response in tests).

    Returns:
        ``yaw_to_u`` and ``pitch_to_v``: ``{"dof", "exact", "ratio"}`` (ratio = dof / exact); ``jacobian_dof``
        and ``jacobian_exact``: (2, 3) rows (du, dv), columns (wx, wy, wz); ``jacobian_dof_std``: the spread of
        the DOF's Jacobian over the frames; ``frames``; ``uv``.
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

    def entry(axis: int, rate: int) -> dict:
        d, e = float(mean[axis, rate]), float(exact[axis, rate])
        return {"dof": d, "exact": e, "ratio": d / e if abs(e) > 1e-12 else None}

    return {"yaw_to_u": entry(0, 2), "pitch_to_v": entry(1, 1), "jacobian_dof": mean.tolist(),
            "jacobian_dof_std": jac.std(axis=0).tolist(), "jacobian_exact": exact.tolist(),
            "frames": int(q.shape[0]), "uv": list(uv),
            "units": "px/frame per rad/s of the rate given to the DOF, at the image size"}


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


@functools.lru_cache(maxsize=4)
def _pixel_cost_pair_fn(config: pixelmpc_lib.PixelMPCConfig, velocity_fn=None):
    """The jitted ``(dof_params, x0, uv0, controls (N, n_f, 4), target_centre, target_normal, camera) ->
    (cost_dof (N,), cost_projection (N,))``: the pixel cost of Eq. (18) over the first ``n_f`` steps with the
    pixel from the DOF dynamics and from the exact projection, both as :func:`pixelmpc.make_pixelmpc` models
    and costs them (robot model ``quadrotor.step``, the pixel cost only while the target is ahead)."""
    velocity_fn = dof.pixel_velocity if velocity_fn is None else velocity_fn
    dt = config.mppi.dt
    quad_params = quadrotor.QuadParams()
    n = quadrotor.STATE_DIM

    def dof_dynamics(X, u, p):
        x, uv = X[:n], X[n:]
        uv_dot = velocity_fn(p["dof"], x[quadrotor.QUAT], uv, u)
        return jnp.concatenate([quadrotor.step(x, u, dt, quad_params), uv + dt * uv_dot])

    def projection_dynamics(X, u, p):
        x_next = quadrotor.step(X[:n], u, dt, quad_params)
        uv, _, in_front = camera_lib.project(p["centre"], x_next, p["camera"])
        uv = jnp.where(in_front, uv, pixelmpc_lib.behind_camera_pixel(uv.dtype))
        return jnp.concatenate([x_next, uv])

    def pixel_term(X, p):
        ahead = jnp.dot(X[quadrotor.POS] - p["centre"], p["normal"]) < 0.0
        return ahead.astype(X.dtype) * pixelmpc_lib.pixel_cost(X[n:], config)

    cost = BatchCost(lambda X, U, t, p: jax.vmap(pixel_term, in_axes=(0, None))(X, p))

    @jax.jit
    def pair(dof_params, x0, uv0, controls, centre, normal, camera):
        chex.assert_shape([x0, uv0, controls], [(n,), (2,), (None, None, 4)])
        p = {"dof": dof_params, "centre": centre, "normal": normal, "camera": camera}
        X0 = jnp.concatenate([x0, uv0.astype(x0.dtype)])
        return (rollout_costs(dof_dynamics, cost, None, X0, controls, p),
                rollout_costs(projection_dynamics, cost, None, X0, controls, p))

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


def pixel_cost_rank_correlation(dof_params, laps: list[Lap], track, camera,
                                num_samples: int = RANK_SAMPLES, t_f: float = RANK_T_F, stride: int = RANK_STRIDE,
                                seed: int = 0, velocity_fn=None, config: pixelmpc_lib.PixelMPCConfig | None = None,
                                progress: bool = False) -> dict:
    """Spearman correlation between the DOF's and the exact projection's pixel cost of sampled sequences.

    At every ``stride``-th logged state of ``laps`` where the target gate is detected (geometric detector,
    no noise) with its centre in the image, ``num_samples`` control sequences of ``t_f / dt`` steps are
    sampled as PixelMPC's MPPI samples them (:func:`sample_control_sequences`, PixelMPC's MPPI config) around
    the logged commands from that tick on (the plan MPPI was flying), rolled out with the MPC's robot model
    from the logged state, and costed with PixelMPC's pixel cost (``PixelMPCConfig``, the l1 cost by default)
    with the DOF's pixel and with the target's exact projection. The DOF is given the sampled controls, as
    PixelMPC gives them.

    Returns:
        ``median``, ``q25``, ``q75``, ``mean`` of the per-state correlations; ``states`` counted;
        ``skipped_constant`` (states where either cost did not vary over the samples); ``samples``, ``steps``.
    """
    base = config or pixelmpc_lib.PixelMPCConfig()
    config = dataclasses.replace(base, t_f=float(t_f), mppi=dataclasses.replace(base.mppi, num_samples=num_samples))
    steps = config.pixel_steps
    pair = _pixel_cost_pair_fn(config, velocity_fn)
    key = jax.random.key(seed)
    correlations, skipped = [], 0
    starts = []
    for lap in laps:
        F = lap.u.shape[0]
        for s in range(0, F, int(stride)):
            det = detector_lib.detect_from_geometry(track.gate(int(lap.target[s])), jnp.asarray(lap.states[s]),
                                                    camera)
            if bool(det.found) and bool(camera_lib.in_image(det.centre)):
                starts.append((lap, s, det.centre))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(starts), desc="pixel-cost ranking", unit="state", leave=False)
    for lap, s, uv0 in starts:
        idx = np.minimum(np.arange(s, s + steps), lap.u.shape[0] - 1)
        plan = jnp.asarray(lap.u[idx], jnp.float32)
        key, key_sample = jax.random.split(key)
        controls = sample_control_sequences(key_sample, plan, config.mppi)
        gate = int(lap.target[s])
        cost_dof, cost_exact = pair(dof_params, jnp.asarray(lap.states[s], jnp.float32), uv0, controls,
                                    track.gates.centre[gate], track.gates.normal[gate], camera)
        rho = spearman(np.asarray(cost_dof), np.asarray(cost_exact))
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


@functools.partial(jax.jit, static_argnames=("horizon", "dt", "part"))
def _multistep_lap(dof_params, track, camera, states, controls, target, horizon: int, dt: float, part: str = "dof"):
    """Per start tick s (F,): predicted and true gate-centre pixel for k = 0..K, the pixel model
    ``PIXEL_MODEL_PARTS[part]``. Returns err (F, K+1) px, err_zero (F, K+1) px (the pixel held still),
    valid (F, K+1) bool."""
    velocity = PIXEL_MODEL_PARTS[part]
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

        def step(uv, k):
            j = jnp.minimum(s + k, F - 1)
            uv_next = uv + dt * velocity(dof_params, camera, dt, states[j, 3:7], uv, controls[j])
            return uv_next, uv_next

        uv0 = det.centre[0]
        _, rollout = jax.lax.scan(step, uv0, ks[:-1])
        pred = jnp.concatenate([uv0[None], rollout])  # (K+1, 2)
        err = jnp.linalg.norm((pred - det.centre) * scale, axis=-1)
        err_zero = jnp.linalg.norm((uv0 - det.centre) * scale, axis=-1)
        return err, err_zero, tracked

    return jax.vmap(one_start)(jnp.arange(F))


def multistep_error(dof_params: dof.DOFParams, laps: list[Lap], track, camera,
                    horizon: int = 80, dt: float = timing.CONTROL_DT, input: str = "command",
                    part: str = "dof") -> dict:
    """Mean and std of the pixel error of the gate centre predicted ``k = 1..horizon`` steps ahead (Fig. 7),
    the DOF given the logged control input ``input`` ("command", or "flown": the rates flown over each frame);
    ``part`` swaps the pixel model for one of :data:`PIXEL_MODEL_PARTS` (default the DOF).

    Returns lists of length ``horizon`` (``None`` where no prediction reaches that step): ``mean_px``,
    ``std_px``, ``count``, and ``zero_motion_mean_px`` (the error of assuming the pixel does not move).
    """
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    if part not in PIXEL_MODEL_PARTS:
        raise ValueError(f"part must be one of {tuple(PIXEL_MODEL_PARTS)}, got {part!r}")
    errs, zeros, valids = [], [], []
    for lap in laps:
        err, err_zero, valid = _multistep_lap(dof_params, track, camera, jnp.asarray(lap.states),
                                              jnp.asarray(lap_input(lap, input)),
                                              jnp.asarray(lap.target), int(horizon), float(dt), part)
        errs.append(np.asarray(err)[:, 1:])
        zeros.append(np.asarray(err_zero)[:, 1:])
        valids.append(np.asarray(valid)[:, 1:])
    err, err_zero, valid = (np.concatenate(a) for a in (errs, zeros, valids))

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
        "input": input,
        "part": part,
    }
