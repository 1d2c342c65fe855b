"""A race's figures over its completed laps, and nominal MPPI's frontier of them read at a lap time.

A frontier (:mod:`~pixelmpc_jax.apps.experiments.frontier`) joins nominal MPPI's points, flown at several target
speeds, by lap time; the main job reads the committed one at PixelMPC's lap time
(:mod:`~pixelmpc_jax.apps.racing.nominal_frontier`). Both read a point as :func:`summarise` gives it and the frontier
at a lap time as :func:`interpolate` does, never extrapolated.
"""

from __future__ import annotations

import numpy as np

from pixelmpc_jax.sim.metrics import LOSS_CAUSES, PHASES, lap_tail

# nominal MPPI's figures read at a cell's lap time, beside the gain
SAME_LAP_TIME_FIGURES = ("vis_below_50_s", "share_target_in_view", "mean_target_angle_deg")


def _stats(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    arr = np.asarray(values, dtype=float)
    return float(arr.mean()), float(2 * arr.std())


def summarise(result: dict) -> dict:
    """Means (and two sigma) over the completed laps of one cell's race results."""
    laps = result.get("laps", [])
    done = [lap for lap in laps if lap.get("success") and lap.get("lap_time_s") is not None]
    lap_time, lap_sigma = _stats([lap["lap_time_s"] for lap in done])
    avoidable, avoidable_sigma = _stats([lap["time_vis_avoidable_s"] for lap in done
                                         if lap.get("time_vis_avoidable_s") is not None])
    vis, _ = _stats([lap["time_vis_below_50_s"] for lap in done if lap.get("time_vis_below_50_s") is not None])
    in_view, _ = _stats([lap["share_target_in_view"] for lap in done if lap.get("share_target_in_view") is not None])
    angle, _ = _stats([lap["mean_target_angle_deg"] for lap in done if lap.get("mean_target_angle_deg") is not None])
    causes = {}
    for cause in LOSS_CAUSES:
        key = f"time_vis_below_50_{cause}_s"
        causes[cause] = _stats([lap[key] for lap in done if lap.get(key) is not None])[0]
    phases = {phase: _stats([lap[f"time_vis_avoidable_{phase}_s"] for lap in done
                             if lap.get(f"time_vis_avoidable_{phase}_s") is not None])[0] for phase in PHASES}
    return {"lap_time_s": lap_time, "lap_time_two_sigma_s": lap_sigma, "avoidable_s": avoidable,
            "avoidable_two_sigma_s": avoidable_sigma, "vis_below_50_s": vis, "share_target_in_view": in_view,
            "mean_target_angle_deg": angle,
            "success_rate": len(done) / len(laps) if laps else None, "laps": len(laps), "laps_completed": len(done),
            "all_laps_completed": bool(laps) and len(done) == len(laps), "causes": causes,
            "phases": phases, "tail": lap_tail(laps)}


def curve(nominal: list[dict], y: str) -> tuple[np.ndarray, np.ndarray]:
    """The points (lap time, ``y``) of ``nominal`` that record both, sorted by lap time: two arrays (P,)."""
    points = sorted((p["lap_time_s"], p[y]) for p in nominal if p["lap_time_s"] is not None and p[y] is not None)
    return np.asarray([p[0] for p in points]), np.asarray([p[1] for p in points])


def interpolate(nominal: list[dict], lap_time: float | None, y: str = "avoidable_s") -> float | None:
    """The nominal curve's ``y`` at ``lap_time`` (linear between the points sorted by lap time); None when the
    lap time lies outside the nominal lap times (no extrapolation) or is None."""
    xs, ys = curve(nominal, y)
    if lap_time is None or len(xs) == 0 or not xs[0] <= lap_time <= xs[-1]:
        return None
    return float(np.interp(lap_time, xs, ys))
