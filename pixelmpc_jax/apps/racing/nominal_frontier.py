"""Nominal MPPI's committed speed frontier on the AlphaPilot course, shipped with the package, and what nominal MPPI
loses at PixelMPC's lap time on it: what the main job shows beside its table.

The race flies both controllers at the same target speed, where nominal MPPI flies the faster lap, so the table alone
compares laps of different lengths. The frontier (:mod:`~pixelmpc_jax.apps.experiments.frontier`) holds nominal MPPI
at several target speeds; joined by lap time, it gives nominal MPPI's avoidable time below 50 % and share of time in
view at PixelMPC's lap time (:func:`~pixelmpc_jax.apps.experiments.frontier.interpolate`, never extrapolated).

A plain ``pip install`` ships no ``experiments/``, so nominal MPPI's points of one committed frontier folder
(:data:`SOURCE`) travel in ``pixelmpc_jax/data/nominal_frontier.json`` (:data:`FILE`), with the folder's name, the
race settings its points were flown with, the measure, the device and the date as the folder records them.
:func:`build` makes it from the folder, ``pixelmpc report --frontier-data`` rewrites it (:func:`rewrite`) and a
test fails when it differs from what the folder gives.

A race is held against the frontier only where the frontier says something about it (:func:`why_not_comparable`):
the same course, estimator, gates (unperturbed), camera (no tilt), faults (none) and visibility measure.
"""

from __future__ import annotations

import json
from pathlib import Path

from pixelmpc_jax.apps.experiments import frontier as frontier_lib
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.apps.readme_table import RESULTS, device_name
from pixelmpc_jax.strict_json import dumps, write_atomic
from pixelmpc_jax.world.course import course_title

SOURCE = RESULTS / "best_heldout_700"  # nominal MPPI at 7-10 m/s on the held-out seeds 700-709, 10 laps a speed
IN_PACKAGE = Path("pixelmpc_jax/data/nominal_frontier.json")  # where the file lies in a checkout
FILE = Path(__file__).resolve().parents[2] / "data" / "nominal_frontier.json"  # the package's copy, read by a race
# each nominal point's fields the file keeps: its name and speed, how many laps it finished, and the figures read at
# a lap time (means over the completed laps, :func:`~pixelmpc_jax.apps.experiments.frontier.summarise`)
FIGURES = ("avoidable_s", *frontier_lib.SAME_LAP_TIME_FIGURES)
POINT_FIELDS = ("name", "speed", "laps", "laps_completed", "lap_time_s", *FIGURES)
MADE_BY = "pixelmpc report --frontier-data, from the source folder's frontier.json and results.json"
# the race settings that decide whether the frontier's nominal MPPI flew the race's world, seen the race's way
WORLD = ("course", "estimator", "perturb", "camera_tilt_deg", "faults")


def _world(race: RaceSpec) -> dict:
    """The :data:`WORLD` settings of a race, as the file records them (the faults that are on, each at its value)."""
    return {"course": race.course, "estimator": race.estimator, "perturb": race.perturb,
            "camera_tilt_deg": race.camera_tilt_deg,
            "faults": {name: getattr(race.faults, name) for name in race.faults.active()}}


def build(root: Path, folder: Path = SOURCE) -> dict:
    """The shipped frontier made from a frontier folder of the checkout ``root`` (its ``frontier.json`` and
    ``results.json``): ``source``, ``made_by``, the :data:`WORLD` settings of its nominal races, ``measure``,
    ``device``, ``date``, ``laps`` (a speed), ``seeds`` (first, last) and nominal MPPI's ``points``
    (:data:`POINT_FIELDS`, in order of speed). A ValueError when its nominal points were not all flown in one world
    under one measure."""
    record = json.loads((Path(root) / folder / "frontier.json").read_text())
    results = json.loads((Path(root) / folder / "results.json").read_text())
    flown = [results[point["name"]] for point in record["nominal"]]
    races = [RaceSpec.from_record({k: v for k, v in r["config"].items() if k != "name"}) for r in flown]
    worlds = [_world(race) for race in races]
    measures = {r["measure"] for r in flown}
    if not flown or any(race.controller != "mppi" for race in races) or len(measures) != 1 or any(
            world != worlds[0] for world in worlds):
        raise ValueError(f"{folder}: its nominal points must be nominal MPPI's, flown in one world under one measure "
                         f"(measures {sorted(measures)}, worlds {worlds})")
    measured = record["measured"]
    points = sorted(({field: point[field] for field in POINT_FIELDS} for point in record["nominal"]),
                    key=lambda point: point["speed"])
    return {"source": folder.as_posix(), "made_by": MADE_BY, **worlds[0], "measure": measures.pop(),
            "device": device_name(measured["device"]), "date": measured["written"][:10], "laps": measured["laps"],
            "seeds": measured["seeds"], "points": points}


def _text(data: dict) -> str:
    return dumps(data, indent=2) + "\n"


def rewrite(root: Path, check: bool = False) -> tuple[str | None, str]:
    """(the checkout's shipped frontier file as it is, None when there is none; as :func:`build` makes it from the
    checkout ``root``); the file is rewritten unless ``check`` (or it is current)."""
    path = Path(root) / IN_PACKAGE
    old = path.read_text() if path.is_file() else None
    new = _text(build(root))
    if new != old and not check:
        write_atomic(path, lambda f: f.write(new.encode()))
    return old, new


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
    here = frontier_lib.summarise(pixelmpc)
    lap_time = here["lap_time_s"]
    if lap_time is None:
        return {**entry, "why": "PixelMPC completed no lap"}
    nominal = {figure: frontier_lib.interpolate(frontier["points"], lap_time, figure) for figure in FIGURES}
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
