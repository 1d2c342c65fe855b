"""The package's copy of nominal MPPI's committed frontier, ``pixelmpc_jax/data/nominal_frontier.json``, built from
its folder (``pixelmpc report --frontier-data``).

The folder is the one the results index says the file ships from (``"ships"``, :mod:`~experiments.reporting.index`).
The package reads the file only (:mod:`~pixelmpc_jax.apps.racing.nominal_frontier`); :func:`rewrite` rebuilds it, and
a test fails when it differs from what the folder gives.
"""

from __future__ import annotations

import json
from pathlib import Path

from experiments.reporting import index
from experiments.reporting.readme_table import device_name
from pixelmpc_jax.apps.racing.nominal_frontier import FIGURES
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.strict_json import dumps, write_atomic

IN_PACKAGE = Path("pixelmpc_jax/data/nominal_frontier.json")  # where the file lies in a checkout
# each nominal point's fields the file keeps: its name and speed, how many laps it finished, and the figures read at
# a lap time
POINT_FIELDS = ("name", "speed", "laps", "laps_completed", "lap_time_s", *FIGURES)
MADE_BY = "pixelmpc report --frontier-data, from the source folder's frontier.json and results.json"


def source(root: Path) -> Path:
    """The folder the index says the file ships from (its entry's ``"ships"``), relative to the checkout ``root``."""
    shipped = [name for name, entry in index.load(root)["folders"].items()
               if entry.get("ships") == IN_PACKAGE.as_posix()]
    if len(shipped) != 1:
        raise ValueError(f"{index.INDEX}: {len(shipped)} folders ship {IN_PACKAGE}, one must")
    return index.RESULTS / shipped[0]


def _world(race: RaceSpec) -> dict:
    """The :data:`~pixelmpc_jax.apps.racing.nominal_frontier.WORLD` settings of a race, as the file records them
    (the faults that are on, each at its value)."""
    return {"course": race.course, "estimator": race.estimator, "perturb": race.perturb,
            "camera_tilt_deg": race.camera_tilt_deg,
            "faults": {name: getattr(race.faults, name) for name in race.faults.active()}}


def build(root: Path, folder: Path | None = None) -> dict:
    """The shipped frontier made from a frontier folder of the checkout ``root`` (its ``frontier.json`` and
    ``results.json``; by default :func:`source`): ``source``, ``made_by``, the
    :data:`~pixelmpc_jax.apps.racing.nominal_frontier.WORLD` settings of its nominal races, ``measure``, ``device``,
    ``date``, ``laps`` (a speed), ``seeds`` (first, last) and nominal MPPI's ``points`` (:data:`POINT_FIELDS`, in
    order of speed). A ValueError when its nominal points were not all flown in one world under one measure."""
    folder = source(root) if folder is None else Path(folder)
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
