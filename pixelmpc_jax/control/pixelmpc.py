"""PixelMPC (Section IV, Algorithm 3): MPPI over X = [robot state; target pixel] (12,), or (13,) with a depth cue.

The robot follows the paper's quadrotor model; the target gate's pixel follows a pixel model:

* ``"dof"``: the Deep Optical Flow dynamics, uv_{t+1} = uv_t + dt * PolarToEuler(DOF(q_t, uv_t, u_t)),
  Eqs. (10)-(12), starting from the detector's pixel;
* ``"projection"`` (PAMPC-style, for comparison): the target's known 3D centre projected through the
  camera intrinsics at every predicted pose (no network, but the gate's position and the camera must
  be known);
* ``"vdof"`` (beyond the paper, its conclusion's next step): the pixel and the detected gate's apparent size s,
  X = [x; u, v, s] (13,), moved by a learned interaction matrix of the body-frame velocity and the body rates
  (:mod:`pixelmpc_jax.dynamics.vdof`): the velocity and a depth cue the DOF cannot see, and still neither the
  gate's position nor the camera.

The cost is the racing cost of Eq. (19) plus the pixel cost of Eq. (18), ``c_pixel * L1(uv_t, centre)``,
counted over the first ``t_f`` seconds of the horizon, only while the detector reports the target, and
for each predicted state only until it passes the target gate's plane (the target then switches). With
``ControllerConfig.look_ahead`` > 0 (beyond the paper) the state also carries the next gate's pixel state, from the
map and the estimate (map-aided, :func:`map_pixel_state`), moved by the same pixel model, and each predicted state
past the target's plane (but not the next gate's) is charged ``look_ahead`` times the next gate's pixel cost: the
plan then sees the gate it will have to find once it has passed the target.
The pixel does not feed back into the robot, so the pixel model runs only over those first
``n_f = t_f / dt`` steps (an MPPI :class:`~pixelmpc_jax.control.rollout.Prefix`); the rest of the horizon
rolls out the robot alone. Both costs are then evaluated once over all the predicted states (a
:class:`~pixelmpc_jax.control.rollout.TrajectoryCost`). The whole step is one compiled function; DOF weights, the
target pixel and the gates are arguments (new values never recompile), ``t_f``, ``c_pixel`` and sizes are
configuration.
"""

from __future__ import annotations

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pixelmpc_jax import timing
from pixelmpc_jax.control import costs
from pixelmpc_jax.control.mppi import Controller, MPPIConfig, make_mppi
from pixelmpc_jax.control.rollout import Prefix, TrajectoryCost
from pixelmpc_jax.dynamics import dof as dof_lib
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.dynamics import vdof as vdof_lib
from pixelmpc_jax.settings import Range, check, setting
from pixelmpc_jax.world import camera as camera_lib

PIXEL_MODELS = ("dof", "projection", "vdof")
LEARNED_PIXEL_MODELS = ("dof", "vdof")  # the pixel models whose weights are PixelMPCParams.dof
PIXEL_COSTS = ("l1", "border")
BEHIND_CAMERA_OFFSET = 1e3  # a target behind the camera sits this far off the image (before any clip)
STATE_DIM = quadrotor.STATE_DIM + 2
IMAGE_CENTRE = (0.5, 0.5)
# What the pixel cost charges while the detector does not report the target: "none", the paper's (no pixel cost
# until the target is detected); "map", a map-aided prior (the target's pixel projected from the map and the
# estimate, see :func:`map_pixel_state`); "kept", the pixel kept alive by the pixel model once it was detected.
TARGET_PRIORS = ("none", "map", "kept", "seeded")
# Where the target's pixel state starts when the detector reports the gate cut by the image border (an opening corner
# out of view): "detected", the detection's (the centre of its visible outline, as a clipped box gives it); "map", the
# gate's centre and corners projected from the map and the estimate, as a lost target's with the map-aided prior.
PARTIAL_TARGETS = ("detected", "map")
LOOK_AHEAD_MODELS = ("own", "projection")  # what predicts the next gate's pixel with the look-ahead
# From which predicted state the look-ahead charges the next gate: "plane", once the sample has passed the target's
# plane; "plan", from there or from the step the current plan (MPPI's zero-noise sample) passes it, the earlier.
LOOK_AHEAD_FROM = ("plane", "plan")
PIXEL_WEIGHT_MAX = 1e30  # c_pixel * pixel_cost_scale: float32 (3.4e38) holds a horizon of such stage costs
PAPER_NOISE_SIGMA = (0.2, 0.2, 0.3, 2.2)  # the paper's MPPI noise std per control [wx, wy, wz (rad/s), thrust (N)]
# The ranges of ControllerConfig's numeric settings, in its fields' metadata: one rule, checked by ControllerConfig
# and by the flags of `pixelmpc race` that set them (pixelmpc_jax.settings).
T_F_RANGE = Range(0.0, 2.0, unit="s")  # the pixel cost's horizon: at most the paper's 2 s (80 steps of 0.025 s)
C_PIXEL_RANGE = Range(0.0, PIXEL_WEIGHT_MAX)
LOOK_AHEAD_RANGE = Range(0.0, 1e3)
BORDER_MARGIN_RANGE = Range(0.0, 0.5, lo_open=True)
DISTURBANCE_TIME_CONSTANT_RANGE = Range(timing.CONTROL_DT, 60.0, unit="s")
MODEL_LATENCY_RANGE = Range(0, 3, integer=True)  # control ticks
QUATERNION_NORM_RANGE = (0.5, 1.5)  # a state's quaternion this far from unit is not a rotation (a zero one)
DETECTED_PIXEL_RANGE = (-1.0, 2.0)  # a detected target pixel, normalised (the image is [0, 1]^2), with margin


def paper_mppi_config(num_samples: int = 512, horizon: int = 80, temperature: float = 200.0,
                      rate_max: float = 6.0, dt: float = timing.CONTROL_DT) -> MPPIConfig:
    """The paper's MPPI settings: dt 0.025 s, T 80, N 512, K 1, sigma (0.2, 0.2, 0.3, 2.2).

    The temperature (lambda) and the body-rate limit are not given in the paper: lambda = 200 suits the
    scale of our racing cost (the closed-loop laps are least sensitive there), the thrust range is the
    vehicle's. The bounds are :meth:`~pixelmpc_jax.dynamics.quadrotor.QuadParams.control_bounds`' float32
    numbers, computed in numpy: building the config creates no JAX array (it may run before the backend starts).
    """
    params = quadrotor.QuadParams()
    rates = np.full(3, rate_max, np.float32)
    lo = np.concatenate([-rates, np.asarray([params.thrust_min], np.float32)])
    hi = np.concatenate([rates, np.asarray([params.thrust_max], np.float32)])
    return MPPIConfig(num_samples=num_samples, horizon=horizon, dt=dt, noise_sigma=PAPER_NOISE_SIGMA,
                      temperature=temperature, iterations=1, u_min=tuple(lo.tolist()), u_max=tuple(hi.tolist()))


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Static settings of the racing controller, PixelMPC or nominal MPPI (hashable; a new config compiles once).

    Both controllers fly ``mppi``, ``racing``, ``model_latency_ticks`` and ``disturbance_time_constant_s``; the
    rest is PixelMPC's pixel cost and pixel model, which nominal MPPI does not evaluate.

    Attributes:
        mppi: sampling settings (the paper's by default).
        racing: the racing cost's settings.
        t_f: seconds of the horizon over which the pixel cost counts (the paper: 1 or 2), in :data:`T_F_RANGE`.
        c_pixel: the pixel cost weight of Eq. (18) (the paper: 3e6, 6e6, 9e6), in :data:`C_PIXEL_RANGE`.
        pixel_cost_scale: our stage cost is ``c_pixel * pixel_cost_scale * L1`` per step. The paper's
            numbers do not transfer as they stand (its cost's units and step weighting are not given);
            the scale is calibrated so the paper's c_pixel grid spans the same range of behaviour
            (see docs/choices.md).
        pixel_model: "dof", "projection" or "vdof" (see the module docstring).
        pixel_error_clip: each axis of ``uv - centre`` is clipped to this many image widths/heights before
            the L1 norm (None: unclipped, as the paper writes it). A target pixel outside the image is lost
            wherever it is; unclipped, the error of a predicted pixel near the camera plane (a gate just
            beside or behind the camera) grows without bound and swamps every other term.
        pixel_deadzone: the error of each axis is counted only beyond this distance from the centre (0, the
            paper's cost, by default). A dead zone of 0.3 charges only a pixel near or past the image border:
            a cost on keeping the target in view rather than centred.
        pixel_cost: the form of the per-step pixel cost. "l1" (the paper's Eq. 18): the L1 distance of the
            pixel from the image centre. "border": a barrier on the image border, zero while the pixel is
            more than ``border_margin`` inside the image and ``((e - (0.5 - m)) / m)^2`` per axis beyond,
            e = |uv - 0.5| (clipped), m = ``border_margin``: 1 at the border, growing past it. It charges
            what the visibility metric counts (the gate leaving the view), not the distance from the
            centre, so it brakes only where the view is at stake. Either model (DOF or projection)
            drives it.
        border_margin: m of the "border" cost, as a fraction of the image width / height.
        box_size_limit: "vdof" only: the pixel cost counts only while the predicted box size s (the gate's
            apparent size, :func:`~pixelmpc_jax.dynamics.vdof.box_size`) is below this. A gate close enough to
            fill the view cannot be kept whole in it by any attitude; its pixel then only pulls the drone off the
            gate's centre line. None: counted until the gate is passed, as the other models (for which it is
            always None: a preset's limit does not stop another model's pixel cost).
        model_latency_ticks: control ticks between a command and its effect that the controller's model
            predicts across (in :data:`MODEL_LATENCY_RANGE`; 0: none, the paper's). The controller in the loop then
            plans from the estimate rolled forward through the commands it sent and the plant has not applied yet.
            For a known actuation latency (:class:`~pixelmpc_jax.sim.faults.Faults`); nominal MPPI flies it too.
        disturbance_time_constant_s: s; the controller's model adds an external acceleration (wind, a mass, drag or
            thrust off the model's) that the controller in the loop estimates from the residual of its own one-tick
            predictions, with this time constant (offset-free MPC; ``PixelMPCParams.disturbance``). None: no
            disturbance model (the paper's). Nominal MPPI flies it too.
        target_prior: what the pixel cost charges while the detector does not report the target
            (:data:`TARGET_PRIORS`): "none", the paper's (no pixel cost until it is detected, so a gate that has
            just become the target is not looked for); "map", the map-aided prior (its pixel projected from the
            map and the estimate, :func:`map_pixel_state`), charged like a detected one; "kept", the pixel kept
            alive (once the target has been detected, its pixel state as the pixel model predicted it for this
            tick from the last, under the command sent: no map needed, ``sim.policies.KeptPixel``); "seeded", the
            kept pixel once the target has been detected, and before that the map-aided prior (so a gate that has
            just become the target is looked for from the first tick, as the look-ahead looked for it before).
        look_ahead: the weight, relative to the target's, of the next gate's pixel cost on the predicted states
            past the target's plane (0: none, the paper's; the state then holds one pixel). The next gate's
            pixel starts from the map and the estimate (map-aided: the detector reports only the target).
        look_ahead_model: what predicts the next gate's pixel along the horizon with the look-ahead
            (:data:`LOOK_AHEAD_MODELS`): "own", the controller's pixel model; "projection", the gate's centre from
            the map projected through each predicted pose (map-aided, as the next gate's pixel already starts; the
            target's pixel stays the pixel model's). The projection pixel model always predicts it so.
        look_ahead_from: from which predicted state the look-ahead charges the next gate (:data:`LOOK_AHEAD_FROM`):
            "plane", once the sample has passed the target's plane, so a sample that stops short of the gate escapes
            the next gate's cost (near a gate the vehicle can still stop before, a plan that brakes to a hover is
            then cheaper than one that flies through with the next gate out of view); "plan", from there or from
            the step at which the current plan passes the plane, whichever is earlier: a sample that delays the
            passage the plan intends pays the next gate's cost all the same. The plan is MPPI's zero-noise sample,
            so "plan" needs ``mppi.nominal_sample``.
        partial_target: where the target's pixel state starts when the detector reports it cut by the image border
            (:data:`PARTIAL_TARGETS`): "detected", the detection's, the paper's (a camera's detector reports the
            centre of the gate's visible outline, which stays inside the image as the gate leaves it, so a gate
            mostly out of view is charged as if centred); "map", the gate's centre and corners projected from the map
            and the estimate (map-aided, as the look-ahead's next gate), which leave the image with the gate.
    """

    mppi: MPPIConfig = dataclasses.field(default_factory=paper_mppi_config)
    racing: costs.RacingCostConfig = dataclasses.field(default_factory=costs.RacingCostConfig)
    t_f: float = setting(1.0, range=T_F_RANGE, help="PixelMPC pixel-cost horizon t_f, in {range} (the MPC horizon)")
    c_pixel: float = setting(9e6, range=C_PIXEL_RANGE, help="PixelMPC pixel-cost weight")
    pixel_cost_scale: float = 3e-5
    pixel_model: str = setting(
        "dof", choices=PIXEL_MODELS, help="PixelMPC's pixel model: dof, the paper's DOF network; vdof, the learned "
        "model with velocity and the gate's size; or projection, the PAMPC-style projection of the known gate")
    pixel_error_clip: float | None = 1.0
    pixel_deadzone: float = 0.0
    pixel_cost: str = setting(
        "l1", choices=PIXEL_COSTS, help="PixelMPC pixel cost: l1, the paper's distance from the image centre, or "
        "border, a barrier on the image border that charges only a gate leaving the view")
    border_margin: float = setting(0.15, range=BORDER_MARGIN_RANGE, help="where the border cost starts, as a "
                                   "fraction of the image inside the border")
    box_size_limit: float | None = None
    model_latency_ticks: int = setting(0, range=MODEL_LATENCY_RANGE, help="ticks of actuation latency the "
                                       "controller's model predicts across, in {range} (0: none)")
    disturbance_time_constant_s: float | None = setting(
        None, range=DISTURBANCE_TIME_CONSTANT_RANGE, none="no model", help="s: the controller's model learns an "
        "external push (wind, model error) with this time constant")
    target_prior: str = setting(
        "none", choices=TARGET_PRIORS, help="what PixelMPC's pixel cost charges while the target is not detected: "
        "none, the paper's (no pixel cost); map, its pixel projected from the map and the estimate; kept, its last "
        "pixel moved on by the pixel model since it was last seen; or seeded, kept once seen and from the map before")
    look_ahead: float = setting(
        0.0, range=LOOK_AHEAD_RANGE, help="PixelMPC's weight, relative to the target's, of the next gate's pixel "
        "cost on the predicted states past the target (its pixel from the map and the estimate); 0: none, the "
        "paper's; in {range}")
    look_ahead_model: str = setting(
        "own", choices=LOOK_AHEAD_MODELS, help="what predicts the next gate's pixel along the horizon with the "
        "look-ahead: own, PixelMPC's pixel model; projection, the gate's centre from the map projected through each "
        "predicted pose (map-aided)")
    partial_target: str = setting(
        "detected", choices=PARTIAL_TARGETS, help="where PixelMPC's target pixel starts when the detector reports "
        "the gate cut by the image border: detected, the centre of its visible outline (the paper's); map, the gate "
        "projected from the map and the estimate")
    look_ahead_from: str = setting(
        "plane", choices=LOOK_AHEAD_FROM, help="from which predicted state the look-ahead charges the next gate: "
        "plane, once the sample has passed the target's plane (a sample that stops short of the gate escapes it); "
        "plan, from there or from the step the current plan passes it, the earlier")

    def __post_init__(self):
        check(self)  # each setting in its field's range or choices
        object.__setattr__(self, "look_ahead", float(self.look_ahead))
        if self.look_ahead_from == "plan" and not self.mppi.nominal_sample:
            raise ValueError("look_ahead_from='plan' reads the current plan from MPPI's zero-noise sample: it needs "
                             "mppi.nominal_sample")
        if not (0.0 <= self.pixel_cost_scale < math.inf):
            raise ValueError(f"pixel_cost_scale must be a finite number >= 0, got {self.pixel_cost_scale!r}")
        if not (self.c_pixel * self.pixel_cost_scale <= PIXEL_WEIGHT_MAX):
            raise ValueError(f"c_pixel must be a finite number >= 0 with c_pixel * pixel_cost_scale <= "
                             f"{PIXEL_WEIGHT_MAX:g} (a horizon of such costs must stay a float32 number), got "
                             f"{self.c_pixel!r} (scale {self.pixel_cost_scale!r})")
        if not (0.0 <= self.pixel_deadzone < 0.5):
            raise ValueError(f"pixel_deadzone must lie in [0, 0.5), got {self.pixel_deadzone!r}")
        if self.pixel_error_clip is not None and not (self.pixel_error_clip > 0.0):
            raise ValueError(f"pixel_error_clip must be positive or None, got {self.pixel_error_clip!r}")
        if self.box_size_limit is not None and not (0.0 < self.box_size_limit < math.inf):
            raise ValueError(f"box_size_limit must be a positive finite number or None, got {self.box_size_limit!r}")
        object.__setattr__(self, "model_latency_ticks", int(self.model_latency_ticks))
        tau = self.disturbance_time_constant_s
        if tau is not None and tau < self.mppi.dt:
            raise ValueError(f"ControllerConfig.disturbance_time_constant_s must be at least the step "
                             f"{self.mppi.dt:g} s, got {tau!r}")
        if self.pixel_model != "vdof":  # only vdof predicts a box size: the limit flies nothing elsewhere
            object.__setattr__(self, "box_size_limit", None)
        if self.pixel_model == "projection":  # its own model is the projection
            object.__setattr__(self, "look_ahead_model", "own")

    @property
    def pixel_dim(self) -> int:
        """The size of the target's pixel state: ``[u, v]``, or ``[u, v, s]`` with the vdof pixel model."""
        return 3 if self.pixel_model == "vdof" else 2

    @property
    def next_pixel_dim(self) -> int:
        """The size of the next gate's pixel state: 0 without the look-ahead, ``[u, v]`` where the projection
        predicts it, else :attr:`pixel_dim`."""
        if self.look_ahead == 0:
            return 0
        return 2 if self.look_ahead_model == "projection" else self.pixel_dim

    @property
    def pixel_steps(self) -> int:
        """n_f: horizon steps over which the pixel is modelled and costed."""
        return min(int(round(self.t_f / self.mppi.dt)), self.mppi.horizon)


@struct.dataclass
class PixelMPCParams:
    """Dynamic inputs of one PixelMPC step (a pytree).

    Attributes:
        racing: the racing cost's per-tick params (path windows, gates, target speed).
        dof: the learned pixel model's weights: :class:`~pixelmpc_jax.dynamics.dof.DOFParams` for "dof",
            :class:`~pixelmpc_jax.dynamics.vdof.VDOFParams` for "vdof" (unused by the projection model).
        target_active: () bool, the detector reports the target this tick (else no pixel cost).
        target_centre: (3,) the target gate's centre, world frame.
        target_normal: (3,) the target gate's normal (direction of travel). A predicted state past the
            target's plane has passed the gate; the paper then switches to the next target, so the pixel
            cost stops counting for that sample (otherwise flying through the gate would be penalised by
            the pixel of a gate already behind the camera).
        camera: the onboard camera (projection model only).
        disturbance: (3,) m/s^2, the estimated external acceleration the robot model adds (with
            ``ControllerConfig.disturbance_time_constant_s``; None without).
        next_active: () bool, there is a gate after the target (with ``ControllerConfig.look_ahead``; None
            without).
        next_centre, next_normal: (3,) the next gate's centre and normal (with ``look_ahead``; None without).
    """

    racing: costs.RacingParams
    dof: dof_lib.DOFParams | vdof_lib.VDOFParams
    target_active: jax.Array
    target_centre: jax.Array
    target_normal: jax.Array
    camera: camera_lib.Camera
    disturbance: jax.Array | None = None
    next_active: jax.Array | None = None
    next_centre: jax.Array | None = None
    next_normal: jax.Array | None = None


def pixel_cost(uv: jax.Array, config: ControllerConfig) -> jax.Array:
    """Eq. (18)'s integrand per step for a pixel ``uv`` (..., 2) -> (...), of the form ``config.pixel_cost``.

    "l1": c_pixel * scale * (|u - 0.5| + |v - 0.5|), each axis less the dead zone (at least 0);
    "border": c_pixel * scale * sum_axes (max(e - (0.5 - m), 0) / m)^2 with e = |uv - 0.5|, m the margin.
    Each axis's distance from the centre is first clipped to ``pixel_error_clip``, so the pixel of a target
    behind the camera (placed :data:`BEHIND_CAMERA_OFFSET` off the image) costs the most any pixel can.
    """
    chex.assert_axis_dimension(uv, -1, 2)
    error = jnp.abs(uv - jnp.asarray(IMAGE_CENTRE, uv.dtype))
    if config.pixel_error_clip is not None:
        error = jnp.minimum(error, config.pixel_error_clip + config.pixel_deadzone)
    if config.pixel_cost == "border":
        margin = config.border_margin
        excess = jnp.maximum(error - (0.5 - margin), 0.0) / margin
        per_axis = excess**2
    else:
        per_axis = jnp.maximum(error - config.pixel_deadzone, 0.0)
    return config.c_pixel * config.pixel_cost_scale * (per_axis[..., 0] + per_axis[..., 1])


def map_pixel_state(gate, x_est: jax.Array, camera: camera_lib.Camera) -> tuple[jax.Array, jax.Array]:
    """The map-aided prior of a target the detector does not report: its centre's pixel (2,) and its inner
    corners' pixels (4, 2) projected through ``camera`` from the estimate ``x_est`` with the map's ``gate``; a
    centre behind the camera takes :func:`behind_camera_pixel`, which the pixel cost charges the most."""
    centre, _, in_front = camera_lib.project(gate.centre, x_est, camera)
    corners, _, _ = camera_lib.project(gate.corners(), x_est, camera)
    return jnp.where(in_front, centre, behind_camera_pixel(centre.dtype)), corners


def behind_camera_pixel(dtype=jnp.float32) -> jax.Array:
    """(2,) the pixel given to a target behind the camera: far outside the image on both axes, so that after
    the clip it costs at least as much as any pixel in front (a gate just past the image border must never
    cost more than turning away from it altogether)."""
    return jnp.full((2,), IMAGE_CENTRE[0] - BEHIND_CAMERA_OFFSET, dtype)


def disturbed_step(x: jax.Array, u: jax.Array, dt: float, quad_params: quadrotor.QuadParams,
                   disturbance: jax.Array | None) -> jax.Array:
    """:func:`~pixelmpc_jax.dynamics.quadrotor.step` with an external acceleration ``disturbance`` (3,) on the
    velocity (Euler: the force ``w_f = m a`` of Eq. 4); ``None``: the step itself. -> (10,)."""
    x_next = quadrotor.step(x, u, dt, quad_params)
    return x_next if disturbance is None else x_next.at[quadrotor.VEL].add(dt * disturbance.astype(x.dtype))


def quaternion_findings(x: jax.Array) -> dict:
    """``{message: () bool}`` of a robot state's values (:func:`~pixelmpc_jax.control.mppi.make_mppi`'s
    ``input_findings``): its quaternion must be a rotation, of norm in :data:`QUATERNION_NORM_RANGE` (an all-zero
    one would be flown as the identity)."""
    lo, hi = QUATERNION_NORM_RANGE
    norm = jnp.linalg.norm(x[quadrotor.QUAT])
    return {f"the state's quaternion [qw, qx, qy, qz] (x[3:7]) must be a rotation, of norm in [{lo:g}, {hi:g}] (an "
            f"all-zero quaternion is none)": (norm >= lo) & (norm <= hi)}


def _shape_check(name: str, value, shape: tuple) -> None:
    if jnp.shape(value) != shape:
        raise ValueError(f"PixelMPCParams.{name} must have shape {shape}, got shape {jnp.shape(value)}")


def pixelmpc_input_findings(config: ControllerConfig):
    """``findings(X0, params) -> {message: () bool}``: PixelMPC's own checks of a step's input (``make_mppi``'s
    ``input_findings``). Shapes raise while the step is traced: X0 (10 + pixel_dim + next_pixel_dim,), the racing
    params one window per horizon step (:func:`~pixelmpc_jax.control.costs.check_racing_params`), the gates' centre
    and normal (3,). Values: the quaternion (:func:`quaternion_findings`) and, where the target's pixel is the
    detector's (``target_prior`` "none", ``partial_target`` "detected"), a detected pixel normalised, within
    :data:`DETECTED_PIXEL_RANGE` (a pixel in pixels, 320 for 640 px, is not)."""
    n = quadrotor.STATE_DIM + config.pixel_dim + config.next_pixel_dim
    pixel = "[u, v, s]" if config.pixel_dim == 3 else "[u, v]"
    layout = f"[x (10,); target {pixel}" + (f"; next gate's pixel ({config.next_pixel_dim},)]" if
                                             config.next_pixel_dim else "]")
    detected_only = config.target_prior == "none" and config.partial_target == "detected"

    def findings(X0, p):
        if jnp.shape(X0) != (n,):
            raise ValueError(f"PixelMPC state X0 must have shape ({n},) = {layout}, got shape {jnp.shape(X0)}")
        if not isinstance(p, PixelMPCParams):
            raise TypeError(f"PixelMPC params must be a PixelMPCParams, got {type(p).__name__}")
        costs.check_racing_params(p.racing, config.mppi.horizon)
        _shape_check("target_active", p.target_active, ())
        for name in ("target_centre", "target_normal") + (("next_centre", "next_normal") if config.look_ahead else ()):
            _shape_check(name, getattr(p, name), (3,))
        if p.disturbance is not None:
            _shape_check("disturbance", p.disturbance, (3,))
        found = quaternion_findings(X0)
        if detected_only:
            lo, hi = DETECTED_PIXEL_RANGE
            uv = X0[quadrotor.STATE_DIM:quadrotor.STATE_DIM + 2]
            message = (f"the detected target pixel X0[10:12] must be normalised (pixel / image size; the image is "
                       f"[0, 1]^2), within [{lo:g}, {hi:g}] while target_active")
            found[message] = ~p.target_active | jnp.all((uv >= lo) & (uv <= hi))
        return found

    return findings


def make_nominal_mppi(mppi_config: MPPIConfig | None = None,
                      cost_config: costs.RacingCostConfig | None = None,
                      quad_params: quadrotor.QuadParams | None = None, disturbance: bool = False) -> Controller:
    """The paper's baseline, "nominal MPPI": the 10-state robot model with the racing cost of Eq. (19) only;
    ``step(state, x0 (10,), params: RacingParams)``; with ``disturbance`` the model adds an external acceleration
    and ``params`` is ``(RacingParams, disturbance (3,))``."""
    mppi_config = mppi_config or paper_mppi_config()
    cost_config = cost_config or costs.RacingCostConfig()
    quad_params = quad_params or quadrotor.QuadParams()
    dt = mppi_config.dt

    def dynamics(x, u, p):
        return disturbed_step(x, u, dt, quad_params, p[1] if disturbance else None)

    def trajectory_cost(X, U, steps, p):
        return costs.racing_costs(X, steps, p[0] if disturbance else p, cost_config)

    def findings(x0, p):
        costs.check_racing_params(p[0] if disturbance else p, mppi_config.horizon)
        return quaternion_findings(x0)

    return make_mppi(mppi_config, dynamics, TrajectoryCost(trajectory_cost), input_findings=findings)


def make_pixelmpc(config: ControllerConfig | None = None,
                  quad_params: quadrotor.QuadParams | None = None) -> Controller:
    """Compose robot dynamics, the pixel model, the racing and pixel costs into one MPPI controller.

    The controller's state is X = [x (10,); uv (2,)] ([x; uv; s] (13,) for "vdof"), with ``look_ahead`` > 0
    followed by the next gate's pixel state (``[u, v]`` with the projection look-ahead model);
    ``step(state, X0, params: PixelMPCParams)``.
    The initial pixel ``uv`` is the detector's (normalised) target pixel; with the projection model it
    is recomputed from the pose at every step. ``config`` defaults to ``ControllerConfig()`` (built here, not at
    import: building it creates arrays, which would start the JAX backend before ``jax.distributed``).
    """
    config = ControllerConfig() if config is None else config
    quad_params = quad_params or quadrotor.QuadParams()
    dt = config.mppi.dt
    n_f = config.pixel_steps

    def robot_step(X, u, p):
        return disturbed_step(X[:quadrotor.STATE_DIM], u, dt, quad_params, p.disturbance)

    # The rest of the horizon: the robot alone, the pixel carried unchanged and not costed.
    def dynamics(X, u, p):
        return jnp.concatenate([robot_step(X, u, p), X[quadrotor.STATE_DIM:]])

    P = config.pixel_dim
    gates = 2 if config.look_ahead > 0 else 1  # the target's pixel state, and the next gate's with the look-ahead
    projected_next = gates == 2 and config.look_ahead_model == "projection"  # the next gate's pixel, map-aided

    def each_gate(pixel_step):
        """``pixel_step(x, pixel (P,), u, p) -> next pixel`` over the target's pixel state, and the next gate's with
        the look-ahead (one call per gate, batched) unless the projection predicts it."""
        if gates == 1 or projected_next:
            return lambda x, pixels, u, p: pixel_step(x, pixels, u, p)
        return lambda x, pixels, u, p: jax.vmap(lambda one: pixel_step(x, one, u, p))(
            pixels.reshape(gates, P)).reshape(-1)

    if config.pixel_model == "dof":
        def dof_step(x, uv, u, p):
            return uv + dt * dof_lib.pixel_velocity(p.dof, x[quadrotor.QUAT], uv, u)

        step_pixels = each_gate(dof_step)

    elif config.pixel_model == "vdof":
        def vdof_step(x, pixel, u, p):
            return pixel + dt * vdof_lib.pixel_state_velocity(p.dof, x, pixel, u)

        step_pixels = each_gate(vdof_step)

    def project_gate(x_next, centre, p):
        uv, _, in_front = camera_lib.project(centre, x_next, p.camera)
        # behind the camera the projection means nothing: the pixel goes far off the image (the worst cost)
        return jnp.where(in_front, uv, behind_camera_pixel(uv.dtype))

    if config.pixel_model in LEARNED_PIXEL_MODELS:
        def prefix_dynamics(X, u, p):
            x, pixels = X[:quadrotor.STATE_DIM], X[quadrotor.STATE_DIM:]
            x_next = robot_step(X, u, p)
            if projected_next:
                return jnp.concatenate([x_next, step_pixels(x, pixels[:P], u, p),
                                        project_gate(x_next, p.next_centre, p)])
            return jnp.concatenate([x_next, step_pixels(x, pixels, u, p)])

    else:
        def prefix_dynamics(X, u, p):
            x_next = robot_step(X, u, p)
            uvs = [project_gate(x_next, p.target_centre, p)]
            if gates == 2:
                uvs.append(project_gate(x_next, p.next_centre, p))
            return jnp.concatenate([x_next, *uvs])

    def ahead_of(X, centre, normal):
        """(T, N) bool: the predicted position is before the plane of the gate at ``centre``, facing ``normal``."""
        offset = [X[..., i] - centre[i] for i in range(3)]  # elementwise, as in racing_costs
        return offset[0] * normal[0] + offset[1] * normal[1] + offset[2] * normal[2] < 0.0

    def gate_pixel_cost(X, k, counted):
        """The pixel cost of the k-th gate's pixel state where ``counted`` (T, N)."""
        start = quadrotor.STATE_DIM + k * P
        if config.box_size_limit is not None and not (k == 1 and projected_next):  # vdof: not once it fills the view
            counted = counted & (X[..., start + 2] < config.box_size_limit)
        uv = X[..., start:start + 2]  # a pixel state may carry more than the pixel
        return counted.astype(X.dtype) * pixel_cost(uv, config)

    def trajectory_cost(X, U, steps, p):
        """X (T, N, 12) -> (T, N): the racing cost, plus over the first n_f steps the pixel cost of each predicted
        state while the target is detected and not yet passed (the gate's plane still ahead); with the look-ahead,
        ``look_ahead`` times the next gate's once past the target's plane and before the next gate's."""
        total = costs.racing_costs(X, steps, p.racing, config.racing)
        if n_f == 0:
            return total
        ahead = ahead_of(X, p.target_centre, p.target_normal)
        in_prefix = (steps < n_f)[:, None]
        total = total + gate_pixel_cost(X, 0, in_prefix & p.target_active & ahead)
        if gates == 2:
            past = ~ahead
            if config.look_ahead_from == "plan":  # from the step the plan (sample 0) passes the target's plane on
                past = past | (jnp.cumsum(past[:, 0].astype(jnp.int32)) > 0)[:, None]
            beyond = in_prefix & p.next_active & past & ahead_of(X, p.next_centre, p.next_normal)
            total = total + config.look_ahead * gate_pixel_cost(X, 1, beyond)
        return total

    cost = TrajectoryCost(trajectory_cost)  # one call over the whole horizon: the prefix shares it
    prefix = Prefix(n_f, prefix_dynamics, cost) if n_f > 0 else None
    return make_mppi(config.mppi, dynamics, cost, prefix=prefix, input_findings=pixelmpc_input_findings(config))
