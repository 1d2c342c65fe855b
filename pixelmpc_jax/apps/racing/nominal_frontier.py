"""Nominal MPPI's committed speed frontier on the AlphaPilot course, shipped with the package, and what nominal MPPI
loses at PixelMPC's lap time on it: what the main job shows beside its table.

The race flies both controllers at the same target speed, where nominal MPPI flies the faster lap, so the table alone
compares laps of different lengths. A frontier holds nominal MPPI at several target speeds; joined by lap time, it
gives nominal MPPI's avoidable time below 50 % and share of time in view at PixelMPC's lap time
(:func:`~pixelmpc_jax.apps.racing.frontier_curve.interpolate`, never extrapolated).

A plain ``pip install`` ships no ``experiments/``, so nominal MPPI's points of one committed frontier folder travel
in ``pixelmpc_jax/data/nominal_frontier.json`` (:data:`FILE`), with the folder's name, the race settings its points
were flown with, the measure, the device and the date as the folder records them. The package only reads the file:
``pixelmpc report --frontier-data`` rebuilds it from the folder in a checkout (``experiments/reporting/``), and a
test fails when it differs from what the folder gives.

A race is held against the frontier only where the frontier says something about it (:func:`why_not_comparable`):
the same course, estimator, gates (unperturbed), camera (no tilt), faults (none) and visibility measure.
"""

from __future__ import annotations

import json
from pathlib import Path

from pixelmpc_jax.apps.racing import frontier_curve
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.world.course import course_title

FILE = Path(__file__).resolve().parents[2] / "data" / "nominal_frontier.json"  # the package's copy, read by a race
# the figures of each nominal point the file keeps that are read at a lap time (means over the completed laps,
# :func:`~pixelmpc_jax.apps.racing.frontier_curve.summarise`)
FIGURES = ("avoidable_s", *frontier_curve.SAME_LAP_TIME_FIGURES)
# the race settings that decide whether the frontier's nominal MPPI flew the race's world, seen the race's way
WORLD = ("course", "estimator", "perturb", "camera_tilt_deg", "faults")


def load() -> dict:
    """The frontier shipped in the package (:data:`FILE`)."""
    return json.loads(FILE.read_text())


def why_not_comparable(race: dict, measure: str | None, frontier: dict) -> str | None:
    """Why a race (its ``RaceSpec.record()``) whose laps were measured under ``measure`` cannot be held against the
    ``frontier``, in a few words; None when it can: the same :data:`WORLD` and the same measure."""
    if race["course"] != frontier["course"]:  # a course file the race named need not be here any more
        return (f"the committed frontier was flown on {course_title(frontier['course'])}, this race on "
                f"{course_title(race['course'])}")
    flown, spec = RaceSpec.from_record({field: frontier[field] for field in WORLD}), RaceSpec.from_record(race)
    if spec.estimator != flown.estimator:
        return f"the committed frontier was flown on estimator {flown.estimator}, this race on {spec.estimator}"
    if spec.perturb != flown.perturb:
        return "this race perturbs the gates; the committed frontier flew them where the map puts them"
    if spec.camera_tilt_deg != flown.camera_tilt_deg:
        return (f"this race's camera is tilted {spec.camera_tilt_deg:g} deg; the committed frontier saw through the "
                f"paper's camera (tilt {flown.camera_tilt_deg:g} deg)")
    if spec.faults != flown.faults:
        faults = ", ".join(spec.faults.active()) or "none"
        return f"this race adds faults ({faults}); the committed frontier flew {_faults(flown)}"
    if measure != frontier["measure"]:
        measured = "records no measure" if measure is None else f"is measured under {measure}"
        return f"this race {measured}, the committed frontier under {frontier['measure']}"
    return None


def _faults(race: RaceSpec) -> str:
    return f"with {', '.join(race.faults.active())}" if race.faults.active() else "without faults"


def _provenance(frontier: dict) -> dict:
    speeds = [point["speed"] for point in frontier["points"]]
    return {"source": frontier["source"], "measure": frontier["measure"], "device": frontier["device"],
            "date": frontier["date"], "laps": frontier["laps"], "seeds": frontier["seeds"],
            "speeds": [min(speeds), max(speeds)]}


def held_against(race: dict, pixelmpc: dict | None, frontier: dict | None = None) -> dict:
    """PixelMPC's laps of a race held against nominal MPPI on the committed frontier at PixelMPC's lap time.

    Args:
        race: the race's ``RaceSpec.record()``.
        pixelmpc: PixelMPC's results in the race (``{"laps", "measure", ...}``), None when it did not fly.
        frontier: the frontier (default: the shipped one, :func:`load`).

    Returns:
        ``{"why": None, "frontier": where it comes from, "lap_time_s": PixelMPC's mean over its completed laps,
        "nominal": {figure: nominal MPPI's at that lap time}, "pixelmpc": {figure: PixelMPC's, "laps_completed"}}``
        over :data:`FIGURES`; or ``{"why": why it is not shown, "frontier": ...}`` when PixelMPC did not fly, the
        race is not comparable (:func:`why_not_comparable`), PixelMPC completed no lap or its lap time lies outside
        the frontier's lap times.
    """
    frontier = load() if frontier is None else frontier
    entry = {"why": None, "frontier": _provenance(frontier)}
    if pixelmpc is None:
        return {**entry, "why": "PixelMPC did not fly"}
    why = why_not_comparable(race, pixelmpc.get("measure"), frontier)
    if why is not None:
        return {**entry, "why": why}
    here = frontier_curve.summarise(pixelmpc)
    lap_time = here["lap_time_s"]
    if lap_time is None:
        return {**entry, "why": "PixelMPC completed no lap"}
    nominal = {figure: frontier_curve.interpolate(frontier["points"], lap_time, figure) for figure in FIGURES}
    if nominal["avoidable_s"] is None:
        times = [point["lap_time_s"] for point in frontier["points"]]
        return {**entry, "why": f"PixelMPC's lap time, {lap_time:.2f} s, lies outside the committed frontier's lap "
                                f"times ({min(times):.2f}-{max(times):.2f} s), and it is never extrapolated"}
    return {**entry, "lap_time_s": lap_time, "nominal": nominal,
            "pixelmpc": {**{figure: here[figure] for figure in FIGURES}, "laps_completed": here["laps_completed"]}}


def describe(entry: dict) -> str:
    """:func:`held_against`'s entry in a few lines for the terminal: nominal MPPI's figures at PixelMPC's lap time
    beside PixelMPC's, and where the frontier comes from; or one line saying why they are not shown."""
    head = "nominal MPPI at PixelMPC's lap time"
    if entry["why"] is not None:
        return f"{head}, on the committed frontier: not shown, {entry['why']}"
    nominal, here, source = entry["nominal"], entry["pixelmpc"], entry["frontier"]
    return "\n".join((
        f"{head} ({entry['lap_time_s']:.2f} s), on the committed frontier: avoidable "
        f"{nominal['avoidable_s']:.2f} s below 50 %, in view {100 * nominal['share_target_in_view']:.1f} %",
        f"  (PixelMPC here: avoidable {here['avoidable_s']:.2f} s, in view {100 * here['share_target_in_view']:.1f} "
        f"%, over its {here['laps_completed']} completed lap(s))",
        f"  from {source['source']}: nominal MPPI at {source['speeds'][0]:g}-{source['speeds'][1]:g} m/s, "
        f"{source['laps']} laps a speed, seeds {source['seeds'][0]}-{source['seeds'][1]} ({source['device']}, "
        f"{source['date']})"))
