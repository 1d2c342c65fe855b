"""Per-lap metrics of closed-loop episodes and their aggregate (mean and two sigma), as the paper reports.

Works on host numpy arrays of one :class:`~pixelmpc_jax.sim.episode.EpisodeLog` (or a batch of them).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.sim.env import END_NAMES
from pixelmpc_jax.sim.episode import EpisodeLog
from pixelmpc_jax.timing import CONTROL_DT
from pixelmpc_jax.world import camera as camera_lib

LAP_KEYS = (
    "success", "gates_passed", "lap_time_s", "crash", "time_vis_below_50_s", "time_vis_zero_s",
    "time_vis_below_50_unavoidable_s",
    *(f"time_vis_below_50_{cause}_s" for cause in ("above", "below", "left", "right", "behind", "inside")),
    "total_variation_roll", "total_variation_pitch", "total_variation_yaw", "mean_linear_acc",
    "mean_angular_acc", "mean_speed", "flight_time_s", "share_target_in_view", "mean_target_angle_deg",
)


def _euler(quaternions: np.ndarray) -> np.ndarray:
    """(S, 4) -> (S, 3) roll, pitch, yaw (numpy mirror of quadrotor.euler_angles)."""
    qw, qx, qy, qz = quaternions.T
    roll = np.arctan2(2 * (qw * qx + qy * qz), 1 - 2 * (qx**2 + qy**2))
    pitch = np.arcsin(np.clip(2 * (qw * qy - qz * qx), -1.0, 1.0))
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy**2 + qz**2))
    return np.stack([roll, pitch, yaw], axis=1)


def total_variation(angles: np.ndarray) -> float:
    """sum_t |a_{t+1} - a_t| of an angle sequence (rad), wrapped so a crossing of +-pi counts its true size."""
    steps = np.diff(angles)
    steps = (steps + np.pi) % (2 * np.pi) - np.pi
    return float(np.sum(np.abs(steps)))


def low_visibility_ticks(visibility: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks (S,) of the ticks with the target's visibility below 50 % and at 0 %, counted per target gate only
    after it was first seen (visibility > 0) while being the target, as the paper counts a 'loss'.

    Args:
        visibility: (S,) visibility of the current target at each tick.
        target: (S,) index of the target gate at each tick.
    """
    below_50 = np.zeros(visibility.shape, bool)
    zero = np.zeros(visibility.shape, bool)
    for gate in np.unique(target):
        ticks = np.nonzero(target == gate)[0]
        seen = np.nonzero(visibility[ticks] > 0.0)[0]
        if seen.size == 0:
            continue
        after = ticks[seen[0]:]
        below_50[after] = visibility[after] < 0.5
        zero[after] = visibility[after] <= 0.0
    return below_50, zero


def visibility_loss_times(visibility: np.ndarray, target: np.ndarray, dt: float = CONTROL_DT) -> tuple[float, float]:
    """Time (s) with the target's visibility below 50 % and at 0 % (see :func:`low_visibility_ticks`)."""
    below_50, zero = low_visibility_ticks(visibility, target)
    return float(np.sum(below_50)) * dt, float(np.sum(zero)) * dt


@jax.jit
def pointed_visibility(gates, positions: jax.Array, camera: camera_lib.Camera) -> jax.Array:
    """(S,) visibility of gate s from position s with the camera pointed at the gate's centre, without roll.

    That is about the most any attitude shows from there: below 50 % the gate is too close (or too far
    off to the side of its opening) to fit the field of view however the vehicle turns, so no controller
    can avoid that low visibility at that position; low visibility elsewhere comes from the attitude.
    """

    def one(gate, position):
        to_gate = gate.centre - position
        yaw = jnp.arctan2(to_gate[1], to_gate[0])
        pitch = -jnp.arctan2(to_gate[2], jnp.hypot(to_gate[0], to_gate[1]))  # body +x (the optical axis) at it
        q = quadrotor.quat_from_euler(jnp.zeros_like(yaw), pitch, yaw)
        x = jnp.concatenate([position, q, jnp.zeros_like(position)])
        return camera_lib.gate_visibility(gate, x, camera)

    return jax.vmap(one)(gates, positions)


def _unavoidable(states: np.ndarray, below_50: np.ndarray, target: np.ndarray, track, camera) -> np.ndarray:
    """(S,) the ticks of the ``below_50`` mask at which a camera pointed at the target sees under half of it."""
    if not below_50.any():
        return below_50
    gates = jax.tree_util.tree_map(lambda leaf: leaf[np.asarray(target)], track.gates)
    best = np.asarray(pointed_visibility(gates, jnp.asarray(states[:, quadrotor.POS]), camera))
    return below_50 & (best < 0.5)


def unavoidable_loss_time(states: np.ndarray, visibility: np.ndarray, target: np.ndarray, track, camera,
                          dt: float = CONTROL_DT) -> float:
    """The part (s) of the time with visibility below 50 % that no attitude could have avoided: ticks at which
    even a camera pointed at the target gate (:func:`pointed_visibility`) sees less than half of it."""
    below_50, _ = low_visibility_ticks(visibility, target)
    return float(np.sum(_unavoidable(states, below_50, target, track, camera))) * dt


LOSS_CAUSES = ("unavoidable", "above", "below", "left", "right", "behind", "inside")


@jax.jit
def _target_projection(gates, states: jax.Array, camera: camera_lib.Camera):
    """(S, 2) normalised pixel and (S,) in-front flag of gate s's centre seen from state s."""

    def one(gate, x):
        uv, _, in_front = camera_lib.project(gate.centre, x, camera)
        return uv, in_front

    return jax.vmap(one)(gates, states)


@jax.jit
def _target_angles(gates, states: jax.Array, camera: camera_lib.Camera) -> jax.Array:
    """(S,) degrees between the optical axis at state s and the ray to gate s's centre."""

    def one(gate, x):
        rotation, position = camera_lib.world_to_camera(x, camera)
        p_cam = rotation @ (gate.centre - position)
        return jnp.degrees(jnp.arctan2(jnp.linalg.norm(p_cam[:2]), p_cam[2]))

    return jax.vmap(one)(gates, states)


def view_metrics(states: np.ndarray, visibility: np.ndarray, target: np.ndarray, num_ticks: int, track,
                 camera) -> dict:
    """The two visibility families of current perception-aware racing work, over a lap's flown ticks:
    ``share_target_in_view``, the share of flight time with any of the target gate's outline in the image
    (visibility > 0), and ``mean_target_angle_deg``, the mean angle between the camera's optical axis and the
    ray to the target gate's centre (0 when flying straight at it; the perception term of learned racing
    policies)."""
    if num_ticks == 0:
        return {"share_target_in_view": None, "mean_target_angle_deg": None}
    flown = slice(1, num_ticks + 1)  # the states reached by the flown ticks
    gates = jax.tree_util.tree_map(lambda leaf: leaf[target], track.gates)
    angles = np.asarray(_target_angles(gates, jnp.asarray(states), camera))
    return {"share_target_in_view": float(np.mean(visibility[flown] > 0.0)),
            "mean_target_angle_deg": float(np.mean(angles[flown]))}


def loss_causes(states: np.ndarray, below_50: np.ndarray, unavoidable: np.ndarray, target: np.ndarray, track,
                camera) -> np.ndarray:
    """(S,) int: for each tick of the ``below_50`` mask, why the target gate was not in view, as an index into
    :data:`LOSS_CAUSES` (-1 on the other ticks).

    ``unavoidable`` ticks (no attitude shows half the gate) come first; every other low-visibility tick is
    classified by where the target gate's centre projects at the true pose: behind the camera, past the top,
    bottom, left or right border of the image (the axis that is furthest out wins), or inside the image (the
    centre in view but under half of the outline, e.g. a gate seen at a grazing angle).
    """
    causes = np.full(below_50.shape, -1, np.int32)
    if not below_50.any():
        return causes
    gates = jax.tree_util.tree_map(lambda leaf: leaf[np.asarray(target)], track.gates)
    uv, in_front = (np.asarray(a) for a in _target_projection(gates, jnp.asarray(states), camera))
    u_out = np.maximum(-uv[:, 0], uv[:, 0] - 1.0)  # > 0: past the left or right border
    v_out = np.maximum(-uv[:, 1], uv[:, 1] - 1.0)
    side = np.where(uv[:, 0] < 0.5, LOSS_CAUSES.index("left"), LOSS_CAUSES.index("right"))
    vertical = np.where(uv[:, 1] < 0.5, LOSS_CAUSES.index("above"), LOSS_CAUSES.index("below"))
    where = np.where((u_out <= 0) & (v_out <= 0), LOSS_CAUSES.index("inside"), np.where(u_out > v_out, side, vertical))
    where = np.where(in_front, where, LOSS_CAUSES.index("behind"))
    causes[below_50] = where[below_50]
    causes[below_50 & unavoidable] = LOSS_CAUSES.index("unavoidable")
    return causes


def lap_metrics(log: EpisodeLog, dt: float = CONTROL_DT, track=None, camera=None) -> dict:
    """The metrics of one episode (host arrays or device arrays of an unbatched log).

    Given the lap's ``track`` and ``camera``, the metrics also split off the low-visibility time no attitude
    could avoid (``time_vis_below_50_unavoidable_s``, see :func:`unavoidable_loss_time`) and split the rest by
    cause (``time_vis_below_50_<cause>_s``, see :func:`loss_causes`): the unavoidable part and the causes add up
    to ``time_vis_below_50_s``."""
    n = int(log.num_ticks)
    states = np.asarray(log.states)[: n + 1]
    rates = np.asarray(log.body_rates)[: n + 1]
    finished = bool(log.finished)
    cause = int(log.end_cause)
    euler = _euler(states[:, quadrotor.QUAT])
    velocity = states[:, quadrotor.VEL]
    linear_acc = np.linalg.norm(np.diff(velocity, axis=0), axis=1) / dt if n > 0 else np.zeros(1)
    angular_acc = np.linalg.norm(np.diff(rates, axis=0), axis=1) / dt if n > 0 else np.zeros(1)
    # The masks span the whole fixed-length log, its unflown ticks marked fully visible (so never counted),
    # and every lap of a run shares one compiled pointed_visibility.
    target = np.asarray(log.target)
    visibility = np.where(np.arange(target.shape[0]) <= n, np.asarray(log.visibility), 1.0)
    low_50, low_zero = low_visibility_ticks(visibility, target)
    below_50, zero = float(np.sum(low_50)) * dt, float(np.sum(low_zero)) * dt
    unavoidable = None
    causes = dict.fromkeys(LOSS_CAUSES[1:])
    view = {"share_target_in_view": None, "mean_target_angle_deg": None}
    if track is not None and camera is not None:
        view = view_metrics(np.asarray(log.states), visibility, target, n, track, camera)
        all_states = np.asarray(log.states)
        unavoidable_mask = _unavoidable(all_states, low_50, target, track, camera)
        unavoidable = float(np.sum(unavoidable_mask)) * dt
        tick_cause = loss_causes(all_states, low_50, unavoidable_mask, target, track, camera)
        causes = {name: float(np.sum(tick_cause == i)) * dt for i, name in enumerate(LOSS_CAUSES) if i > 0}
    return {
        "success": finished,
        "gates_passed": int(log.gates_passed),
        "lap_time_s": n * dt if finished else None,
        "crash": None if finished else END_NAMES.get(cause, str(cause)),
        "time_vis_below_50_s": below_50,
        "time_vis_zero_s": zero,
        "time_vis_below_50_unavoidable_s": unavoidable,
        **{f"time_vis_below_50_{name}_s": value for name, value in causes.items()},
        "total_variation_roll": total_variation(euler[:, 0]),
        "total_variation_pitch": total_variation(euler[:, 1]),
        "total_variation_yaw": total_variation(euler[:, 2]),
        "mean_linear_acc": float(np.mean(linear_acc)),
        "mean_angular_acc": float(np.mean(angular_acc)),
        "mean_speed": float(np.mean(np.linalg.norm(velocity, axis=1))),
        "flight_time_s": n * dt,
        **view,
    }


def unbatch(log: EpisodeLog) -> list[EpisodeLog]:
    """Split a batched log (leading axis B) into B single logs on the host."""
    host = EpisodeLog(*[np.asarray(field) for field in log])
    if host.num_ticks.ndim == 0:
        return [host]
    return [EpisodeLog(*[field[i] for field in host]) for i in range(host.num_ticks.shape[0])]


def aggregate(laps: list[dict]) -> dict:
    """For each numeric key, ``{"mean", "two_sigma", "n"}`` over the laps where it is defined (lap time over
    the completed laps only), plus ``success_rate`` and the number of laps."""
    out: dict = {"num_laps": len(laps), "success_rate": (sum(bool(lap["success"]) for lap in laps) / len(laps))
                 if laps else math.nan}
    for key in LAP_KEYS:
        if key in ("success", "crash"):
            continue
        values = [float(lap[key]) for lap in laps if lap.get(key) is not None]
        if not values:
            out[key] = {"mean": None, "two_sigma": None, "n": 0}
            continue
        arr = np.asarray(values)
        out[key] = {"mean": float(arr.mean()), "two_sigma": float(2 * arr.std()), "n": len(values)}
    return out


def format_table(laps: list[dict], aggregate_row: dict | None = None) -> str:
    """A fixed-width summary table of the laps for the terminal."""
    header = f"{'lap':>4} {'ok':>3} {'gates':>5} {'lap [s]':>8} {'end':>12} {'vis<50 [s]':>10} {'vis=0 [s]':>9} " \
             f"{'TV r/p/y [rad]':>20} {'lin acc':>8} {'ang acc':>8}"
    rows = [header, "-" * len(header)]
    for i, lap in enumerate(laps):
        lap_time = f"{lap['lap_time_s']:.2f}" if lap["lap_time_s"] is not None else "-"
        tv = f"{lap['total_variation_roll']:.1f}/{lap['total_variation_pitch']:.1f}/{lap['total_variation_yaw']:.1f}"
        rows.append(f"{i:>4} {'yes' if lap['success'] else 'no':>3} {lap['gates_passed']:>5} {lap_time:>8} "
                    f"{lap['crash'] or '-':>12} {lap['time_vis_below_50_s']:>10.2f} {lap['time_vis_zero_s']:>9.2f} "
                    f"{tv:>20} {lap['mean_linear_acc']:>8.2f} {lap['mean_angular_acc']:>8.2f}")
    if aggregate_row:
        def fmt(key):
            entry = aggregate_row.get(key) or {}
            if entry.get("mean") is None:
                return "-"
            return f"{entry['mean']:.2f}+-{entry['two_sigma']:.2f}"

        rows.append("-" * len(header))
        rows.append(f"success rate {aggregate_row['success_rate'] * 100:.0f}% of {aggregate_row['num_laps']}; "
                    f"lap time {fmt('lap_time_s')} s; vis<50 {fmt('time_vis_below_50_s')} s; "
                    f"vis=0 {fmt('time_vis_zero_s')} s (mean +- 2 sigma)")
        split = [(name, (aggregate_row.get(f"time_vis_below_50_{name}_s") or {}).get("mean")) for name in LOSS_CAUSES]
        if all(value is not None for _, value in split):
            rows.append("vis<50 by cause (mean s): " + ", ".join(f"{name} {value:.2f}" for name, value in split))
    return "\n".join(rows)
