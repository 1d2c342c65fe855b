"""Per-lap metrics of closed-loop episodes and their aggregate (mean and two sigma), as the paper reports.

Works on host numpy arrays of one :class:`~pixelmpc_jax.sim.episode.EpisodeLog` (or a batch of them), or on the
per-tick record a race writes (``ticks_<controller>.npz``: :func:`visibility_metrics` recomputes a lap's
visibility figures from it).

The visibility measure (:data:`MEASURE`, :func:`visibility_masks`): a gate's low visibility counts at every tick
it is the target, from the tick the previous gate is passed; the part no attitude avoids is excused, capped per
gate at the ticks the race's target speed needs to fly through it. The paper's rule (counted only after the gate
was first seen while being the target) survives only as the ``*_after_seen_s`` columns beside the paper's figures.
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

LOSS_CAUSES = ("excused", "above", "below", "left", "right", "behind", "inside")
# when an avoidable tick falls, counted from the tick its gate became the target: in the first second, the
# second, or later (see :func:`switch_phases`)
PHASES = ("first_second", "second_second", "later")
LAP_KEYS = (
    "success", "gates_passed", "lap_time_s", "crash", "time_vis_below_50_s", "time_vis_zero_s",
    "time_vis_avoidable_s", *(f"time_vis_below_50_{cause}_s" for cause in LOSS_CAUSES),
    *(f"time_vis_avoidable_{phase}_s" for phase in PHASES),
    "time_vis_below_50_after_seen_s", "time_vis_zero_after_seen_s",
    "total_variation_roll", "total_variation_pitch", "total_variation_yaw", "mean_linear_acc",
    "mean_angular_acc", "mean_speed", "flight_time_s", "share_target_in_view", "mean_target_angle_deg",
)
# The visibility measure's name, recorded with every race's results: a result recorded under another measure
# (the paper's "after first seen" rule of earlier versions) is not current and is flown again.
MEASURE = "from-target/capped-floor"

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


def after_seen_ticks(visibility: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The paper's rule, kept only for the column beside the paper's figures: masks (S,) of the ticks with the
    target's visibility below 50 % and at 0 %, counted per target gate only after it was first seen
    (visibility > 0) while being the target.

    It has a blind spot: a controller that does not see the next gate for a while after passing a gate is never
    charged for that time. No gain or claim uses it; see :func:`visibility_masks`.

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


@jax.jit
def pointed_visibility(gates, positions: jax.Array, camera: camera_lib.Camera) -> jax.Array:
    """(S,) visibility of gate s from position s with the camera's optical axis pointed at the gate's centre,
    without roll.

    That is about the most any attitude shows from there: below 50 % the gate is too close (or too far
    off to the side of its opening) to fit the field of view however the vehicle turns, so no controller
    can avoid that low visibility at that position; low visibility elsewhere comes from the attitude.

    The optical axis is the body's +x tilted up by the mount's ``camera.tilt``: the body pitches that much further
    nose down than the ray to the gate (a positive pitch is nose down). Untilted, the body's +x points at the gate.
    """

    def one(gate, position):
        to_gate = gate.centre - position
        yaw = jnp.arctan2(to_gate[1], to_gate[0])
        elevation = jnp.arctan2(to_gate[2], jnp.hypot(to_gate[0], to_gate[1]))
        pitch = -elevation + camera.tilt  # the optical axis, tilted up from body +x by camera.tilt, at the gate
        q = quadrotor.quat_from_euler(jnp.zeros_like(yaw), pitch, yaw)
        x = jnp.concatenate([position, q, jnp.zeros_like(position)])
        return camera_lib.gate_visibility(gate, x, camera)

    return jax.vmap(one)(gates, positions)


def target_gates(gates, target: np.ndarray):
    """The target gate of each tick, stacked from the course's ``gates`` (leading axis G). An index past the
    last gate (every gate passed) names the last: its visibility is recorded as 1 there, so it is never charged."""
    index = np.clip(np.asarray(target), 0, np.asarray(gates.centre).shape[0] - 1)
    return jax.tree_util.tree_map(lambda leaf: leaf[index], gates)


def flown(num_ticks: int, size: int) -> np.ndarray:
    """(size,) mask of the states reached by the flown ticks, 1..num_ticks (state 0 is the start)."""
    ticks = np.arange(size)
    return (ticks >= 1) & (ticks <= num_ticks)


def target_runs(target: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop)]`` of the runs of ticks with one target gate: a run starts at the tick the previous gate
    is passed (or the lap's start) and ends where the next gate becomes the target."""
    edges = np.flatnonzero(np.diff(np.asarray(target))) + 1
    bounds = np.concatenate([[0], edges, [len(target)]])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def excused_ticks(candidates: np.ndarray, distance: np.ndarray, target: np.ndarray, target_speed: float,
                  dt: float = CONTROL_DT) -> np.ndarray:
    """(S,) the low-visibility ticks the floor excuses: of the ``candidates`` (below 50 % where even a camera
    pointed at the target sees under half of it), per target gate at most as many as a vehicle at the race's
    target speed needs to fly straight through that zone, the ones nearest the gate.

    The zone is about the last 2 m before a gate (a pointed camera sees all of a gate from further off, with no
    occlusion), and its depth is measured per gate as the farthest candidate's distance to the gate's centre.
    Without the cap a controller that brakes into each gate and sprints between them would move time into the
    excused zone: with it, lingering there is charged.

    Args:
        candidates: (S,) bool, the ticks the floor could excuse.
        distance: (S,) distance from the vehicle to the target gate's centre, m.
        target: (S,) the target gate's index.
        target_speed: the race's target speed, m/s.
    """
    if not target_speed > 0.0:
        raise ValueError(f"target_speed must be positive to cap the excused time, got {target_speed!r}")
    excused = np.zeros(candidates.shape, bool)
    for start, stop in target_runs(target):
        ticks = start + np.flatnonzero(candidates[start:stop])
        if ticks.size == 0:
            continue
        cap = int(np.ceil(float(np.max(distance[ticks])) / (target_speed * dt) - 1e-9))
        nearest = ticks[np.argsort(distance[ticks], kind="stable")[:cap]]
        excused[nearest] = True
    return excused


def visibility_masks(visibility: np.ndarray, pointed: np.ndarray, target: np.ndarray, distance: np.ndarray | None,
                     num_ticks: int, target_speed: float, dt: float = CONTROL_DT,
                     excused: np.ndarray | None = None) -> dict:
    """The project's visibility measure over one lap's flown ticks, as masks (S,).

    A gate's low visibility counts at every tick it is the target, from the tick the previous gate is passed
    (``below_50``, ``zero``: nothing excused). The floor no attitude avoids (:func:`pointed_visibility` under
    50 %) is excused, capped per gate by :func:`excused_ticks` (``excused``); ``avoidable`` is the rest.

    What a controller could do to lower the avoidable time without seeing more, and why it cannot:

    - not look at the next gate after a passage: every tick a gate is the target counts, seen or not;
    - linger in the zone close to a gate where the floor excuses: the cap charges what a straight flight at the
      target speed would not spend there;
    - park the gate at the image's border (half the outline in view): the mean angle between the optical axis
      and the target (:func:`view_metrics`) grows, and it is reported beside;
    - fly slower: the frontier compares at the same lap time, against nominal MPPI flown slower;
    - crash early or skip a gate: the frontier uses completed laps only, and the tuner demands every lap.

    Args:
        visibility: (S,) the target's visibility at each state (state 0 is the start).
        pointed: (S,) the target's visibility from a camera at the same position pointed at its centre.
        target: (S,) the target gate's index.
        distance: (S,) distance to the target gate's centre, m (None with ``excused``).
        num_ticks: ticks flown; states past it are not counted.
        target_speed: the race's target speed, m/s (the cap's speed).
        excused: (S,) bool, the ticks the floor excuses, where a record kept them instead of the distances (this
            function's own ``excused`` for the same lap; :mod:`~pixelmpc_jax.sim.ticks_compact`); None: from
            ``distance``.
    """
    counted = flown(num_ticks, len(visibility))
    below_50 = counted & (visibility < 0.5)
    zero = counted & (visibility <= 0.0)
    if excused is None:
        excused = excused_ticks(below_50 & (pointed < 0.5), distance, target, target_speed, dt)
    else:
        excused = np.asarray(excused, bool) & below_50
    return {"below_50": below_50, "zero": zero, "excused": excused, "avoidable": below_50 & ~excused}


def switch_phases(target: np.ndarray, dt: float = CONTROL_DT) -> np.ndarray:
    """(S,) int index into :data:`PHASES` of each tick: whether it lies in the first second after its gate became
    the target (the tick the previous gate was passed, or the start), in the second one, or later."""
    phases = np.zeros(len(target), np.int32)
    second = round(1.0 / dt)
    for start, stop in target_runs(target):
        since = np.arange(stop - start)
        phases[start:stop] = np.where(since < second, 0, np.where(since < 2 * second, 1, 2))
    return phases


def tick_geometry(states: np.ndarray, target: np.ndarray, gates, camera) -> tuple[np.ndarray, np.ndarray]:
    """(S,) the pointed camera's visibility of the target (:func:`pointed_visibility`) and the distance to its
    centre, m, at each state."""
    targets = target_gates(gates, target)
    positions = np.asarray(states)[:, quadrotor.POS]
    pointed = np.asarray(pointed_visibility(targets, jnp.asarray(positions, jnp.float32), camera))
    return pointed, target_distance(states, target, gates)


def target_distance(states: np.ndarray, target: np.ndarray, gates) -> np.ndarray:
    """(S,) the distance from each state's position to its target gate's centre, m."""
    return np.linalg.norm(np.asarray(states)[:, quadrotor.POS] - np.asarray(target_gates(gates, target).centre), axis=1)


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


def view_metrics(states: np.ndarray, visibility: np.ndarray, target: np.ndarray, num_ticks: int, gates,
                 camera) -> dict:
    """The two visibility families of current perception-aware racing work, over a lap's flown ticks:
    ``share_target_in_view``, the share of flight time with any of the target gate's outline in the image
    (visibility > 0), and ``mean_target_angle_deg``, the mean angle between the camera's optical axis and the
    ray to the target gate's centre (0 when flying straight at it; the perception term of learned racing
    policies)."""
    if num_ticks == 0:
        return {"share_target_in_view": None, "mean_target_angle_deg": None}
    counted = flown(num_ticks, len(visibility))
    angles = np.asarray(_target_angles(target_gates(gates, target), jnp.asarray(states, jnp.float32), camera))
    return {"share_target_in_view": float(np.mean(visibility[counted] > 0.0)),
            "mean_target_angle_deg": float(np.mean(angles[counted]))}


def loss_causes(states: np.ndarray, below_50: np.ndarray, excused: np.ndarray, target: np.ndarray, gates,
                camera) -> np.ndarray:
    """(S,) int: for each tick of the ``below_50`` mask, why the target gate was not in view, as an index into
    :data:`LOSS_CAUSES` (-1 on the other ticks).

    ``excused`` ticks (no attitude shows half the gate, within the cap) come first; every other low-visibility
    tick is classified by where the target gate's centre projects at the true pose: behind the camera, past the
    top, bottom, left or right border of the image (the axis that is furthest out wins), or inside the image (the
    centre in view but under half of the outline, e.g. a gate seen at a grazing angle).
    """
    causes = np.full(below_50.shape, -1, np.int32)
    if not below_50.any():
        return causes
    uv, in_front = (np.asarray(a) for a in _target_projection(target_gates(gates, target),
                                                               jnp.asarray(states, jnp.float32), camera))
    u_out = np.maximum(-uv[:, 0], uv[:, 0] - 1.0)  # > 0: past the left or right border
    v_out = np.maximum(-uv[:, 1], uv[:, 1] - 1.0)
    side = np.where(uv[:, 0] < 0.5, LOSS_CAUSES.index("left"), LOSS_CAUSES.index("right"))
    vertical = np.where(uv[:, 1] < 0.5, LOSS_CAUSES.index("above"), LOSS_CAUSES.index("below"))
    where = np.where((u_out <= 0) & (v_out <= 0), LOSS_CAUSES.index("inside"), np.where(u_out > v_out, side, vertical))
    where = np.where(in_front, where, LOSS_CAUSES.index("behind"))
    causes[below_50] = where[below_50]
    causes[below_50 & excused] = LOSS_CAUSES.index("excused")
    return causes


def visibility_metrics(states: np.ndarray, visibility: np.ndarray, target: np.ndarray, num_ticks: int,
                       gates, camera, target_speed: float, dt: float = CONTROL_DT, pointed: np.ndarray | None = None
                       ) -> dict:
    """A lap's visibility figures from its per-tick record (what ``ticks_<controller>.npz`` holds): the time
    below 50 % and at 0 % counted from the target (:func:`visibility_masks`), its avoidable part, its split by
    cause (:func:`loss_causes`; the causes add up to ``time_vis_below_50_s``) and of the avoidable time by when
    it falls after its gate became the target (:func:`switch_phases`), the share of flight time with the
    target in view and the mean angle to it (:func:`view_metrics`), and the paper's "after first seen" rule
    (``*_after_seen_s``, for the column beside the paper's figures only).

    Args:
        states: (S, 10) true states, state 0 the start.
        visibility: (S,) the target's visibility at each state.
        target: (S,) the target gate's index.
        gates: the course's gates as flown (leading axis G).
        pointed: (S,) :func:`pointed_visibility` of the target, computed here when not given.
    """
    states, target = np.asarray(states), np.asarray(target)
    counted = flown(num_ticks, len(visibility))
    visibility = np.where(counted, np.asarray(visibility), 1.0)  # unflown ticks never count
    computed, distance = tick_geometry(states, target, gates, camera)
    pointed = computed if pointed is None else np.asarray(pointed)
    masks = visibility_masks(visibility, pointed, target, distance, num_ticks, target_speed, dt)
    tick_cause = loss_causes(states, masks["below_50"], masks["excused"], target, gates, camera)
    phase = switch_phases(target, dt)
    seen_50, seen_zero = after_seen_ticks(np.where(np.arange(len(visibility)) <= num_ticks, visibility, 1.0), target)
    return {
        "time_vis_below_50_s": float(np.sum(masks["below_50"])) * dt,
        "time_vis_zero_s": float(np.sum(masks["zero"])) * dt,
        "time_vis_avoidable_s": float(np.sum(masks["avoidable"])) * dt,
        **{f"time_vis_below_50_{name}_s": float(np.sum(tick_cause == i)) * dt for i, name in enumerate(LOSS_CAUSES)},
        **{f"time_vis_avoidable_{name}_s": float(np.sum(masks["avoidable"] & (phase == i))) * dt
           for i, name in enumerate(PHASES)},
        "time_vis_below_50_after_seen_s": float(np.sum(seen_50)) * dt,
        "time_vis_zero_after_seen_s": float(np.sum(seen_zero)) * dt,
        **view_metrics(states, visibility, target, num_ticks, gates, camera),
    }


def lap_metrics(log: EpisodeLog, dt: float = CONTROL_DT, track=None, camera=None, target_speed: float | None = None
                ) -> dict:
    """The metrics of one episode (host arrays or device arrays of an unbatched log).

    Given the lap's ``track``, ``camera`` and the race's ``target_speed``, the metrics hold the visibility
    figures of :func:`visibility_metrics`; without them those are None (the flight figures stay)."""
    n = int(log.num_ticks)
    states = np.asarray(log.states)[: n + 1]
    rates = np.asarray(log.body_rates)[: n + 1]
    finished = bool(log.finished)
    cause = int(log.end_cause)
    euler = _euler(states[:, quadrotor.QUAT])
    velocity = states[:, quadrotor.VEL]
    linear_acc = np.linalg.norm(np.diff(velocity, axis=0), axis=1) / dt if n > 0 else np.zeros(1)
    angular_acc = np.linalg.norm(np.diff(rates, axis=0), axis=1) / dt if n > 0 else np.zeros(1)
    view = dict.fromkeys(VISIBILITY_KEYS)
    if track is not None and camera is not None and target_speed is not None:
        # the whole fixed-length log, so every lap of a run shares one compiled pointed_visibility
        view = visibility_metrics(np.asarray(log.states), np.asarray(log.visibility), np.asarray(log.target), n,
                                  track.gates, camera, target_speed, dt)
    return {
        "success": finished,
        "gates_passed": int(log.gates_passed),
        "lap_time_s": n * dt if finished else None,
        "crash": None if finished else END_NAMES.get(cause, str(cause)),
        **view,
        "total_variation_roll": total_variation(euler[:, 0]),
        "total_variation_pitch": total_variation(euler[:, 1]),
        "total_variation_yaw": total_variation(euler[:, 2]),
        "mean_linear_acc": float(np.mean(linear_acc)),
        "mean_angular_acc": float(np.mean(angular_acc)),
        "mean_speed": float(np.mean(np.linalg.norm(velocity, axis=1))),
        "flight_time_s": n * dt,
    }


VISIBILITY_KEYS = tuple(key for key in LAP_KEYS if key.startswith(("time_vis", "share_", "mean_target")))


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


TAIL_OVER_MEDIAN = 0.10  # a lap more than 10 % over the median lap time is in the tail


def lap_tail(laps: list[dict]) -> dict:
    """A set of laps' tail, to report beside its mean: ``laps``, ``laps_finished``, ``median_lap_s`` and
    ``worst_lap_s`` of the finished laps, ``worst_over_median`` (the worst lap's excess over the median, a fraction)
    and ``share_over_median`` (the share of the finished laps more than :data:`TAIL_OVER_MEDIAN` over the median;
    the laps not finished are counted in ``laps_finished``, not here). Lap time figures are None with no lap
    finished."""
    times = np.asarray([lap["lap_time_s"] for lap in laps if lap.get("success") and lap.get("lap_time_s") is not None],
                       np.float64)
    tail = {"laps": len(laps), "laps_finished": int(times.size), "median_lap_s": None, "worst_lap_s": None,
            "worst_over_median": None, "share_over_median": None}
    if times.size:
        median, worst = float(np.median(times)), float(times.max())
        tail.update(median_lap_s=median, worst_lap_s=worst, worst_over_median=worst / median - 1.0,
                    share_over_median=float(np.mean(times > (1.0 + TAIL_OVER_MEDIAN) * median)))
    return tail


def tail_columns(tail: dict) -> tuple[str, str, str]:
    """A table's three tail columns of :func:`lap_tail`: laps finished (``39/40``), the worst lap against the median
    (``+4.0 %``) and the laps more than 10 % over the median (``1 (2.6 %)``)."""
    finished = f"{tail['laps_finished']}/{tail['laps']}"
    if tail["worst_over_median"] is None:
        return finished, "-", "-"
    slow = round(tail["share_over_median"] * tail["laps_finished"])
    return finished, f"{100 * tail['worst_over_median']:+.1f} %", f"{slow} ({100 * tail['share_over_median']:.1f} %)"


def format_table(laps: list[dict], aggregate_row: dict | None = None) -> str:
    """A fixed-width summary table of the laps for the terminal."""
    header = f"{'lap':>4} {'ok':>3} {'gates':>5} {'lap [s]':>8} {'end':>12} {'vis<50 [s]':>10} {'vis=0 [s]':>9} " \
             f"{'TV r/p/y [rad]':>20} {'lin acc':>8} {'ang acc':>8}"
    rows = [header, "-" * len(header)]
    for i, lap in enumerate(laps):
        lap_time = f"{lap['lap_time_s']:.2f}" if lap["lap_time_s"] is not None else "-"
        tv = f"{lap['total_variation_roll']:.1f}/{lap['total_variation_pitch']:.1f}/{lap['total_variation_yaw']:.1f}"
        below_50, zero = (f"{lap[k]:.2f}" if lap.get(k) is not None else "-"
                          for k in ("time_vis_below_50_s", "time_vis_zero_s"))
        rows.append(f"{i:>4} {'yes' if lap['success'] else 'no':>3} {lap['gates_passed']:>5} {lap_time:>8} "
                    f"{lap['crash'] or '-':>12} {below_50:>10} {zero:>9} "
                    f"{tv:>20} {lap['mean_linear_acc']:>8.2f} {lap['mean_angular_acc']:>8.2f}")
    if aggregate_row:
        def fmt(key):
            entry = aggregate_row.get(key) or {}
            if entry.get("mean") is None:
                return "-"
            return f"{entry['mean']:.2f}+-{entry['two_sigma']:.2f}"

        rows.append("-" * len(header))
        rows.append(f"success rate {aggregate_row['success_rate'] * 100:.0f}% of {aggregate_row['num_laps']}; "
                    f"lap time {fmt('lap_time_s')} s; vis<50 {fmt('time_vis_below_50_s')} s "
                    f"(avoidable {fmt('time_vis_avoidable_s')} s); "
                    f"vis=0 {fmt('time_vis_zero_s')} s (mean +- 2 sigma)")
        split = [(name, (aggregate_row.get(f"time_vis_below_50_{name}_s") or {}).get("mean")) for name in LOSS_CAUSES]
        if all(value is not None for _, value in split):
            rows.append("vis<50 by cause (mean s): " + ", ".join(f"{name} {value:.2f}" for name, value in split))
    return "\n".join(rows)
