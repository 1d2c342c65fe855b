"""``pixelmpc reproduce``: every table and figure of the paper, ours beside the paper's, in one report.

Parts (each in its own folder under ``out``, each resumable on its own), in the order ``all`` runs them:

- ``frontier``: nominal MPPI flown at eight targets (the paper's paces among them) and the presets at the paper's
  pace against it (the speed frontier, not in the paper); the tables below read their frontier gains off it;
- ``table2``: Tables II and III and Fig. 6 with ground truth, at the paper's 14 m/s label and at its pace, the
  ``paper`` preset's grid with the ``best`` preset beside it;
- ``table4``: Table IV at the labels and the paces, the straight lane's Σ_max, Fig. 6 with the filter, Fig. 9;
- ``dof``: the DOF network's accuracy on held-out flights and Fig. 7 (multi-step error) of the shipped DOF and vdof;
- ``bench``: Table I (runtimes), the controller step and its scaling, the peers, the matmul limit (last: the
  quietest machine);
- ``table2_projection`` (not in ``all``): the Tables II-III grid with the PAMPC-style projection pixel model;
- ``robustness`` (not in ``all``, not in the paper): the faults of a real flight
  (:mod:`pixelmpc_jax.apps.experiments.robustness`), both controllers on both estimators at the paper's pace.

Every race flies the laps of seeds from :data:`SEED` on (seeds no setting was tuned on). A cell that another part
already flew (the same race, laps and seed) is copied from it, not flown again.

``out/reproduce.json`` records each finished part (its wall time, mode, device); a finished part is kept
on the next run (and the grids inside a part keep their finished cells), so an interrupted run resumes
where it stopped. ``out/REPORT.md`` is rebuilt after every part from the parts' own reports.
"""

from __future__ import annotations

import datetime
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

PARTS = ("frontier", "table2", "table4", "dof", "bench", "table2_projection", "robustness")
ALL = PARTS[:-2]
ALIASES = {"all": ALL, "table1": ("bench",), "table3": ("table2",), "fig6": ("table2", "table4"),
           "fig7": ("dof",), "fig9": ("table4",), "projection": ("table2_projection",)}
CHOICES = tuple(ALIASES) + PARTS
TITLES = {"bench": "Table I and the runtime harness", "dof": "DOF accuracy (Section V-A) and Fig. 7",
          "table2": "Tables II-III and Fig. 6 with ground truth",
          "table2_projection": "Tables II-III with the projection pixel model",
          "table4": "Table IV, the straight lane, Fig. 6 with the filter and Fig. 9",
          "frontier": "The speed frontier: PixelMPC against flying slower",
          "robustness": "Robustness to the faults of a real flight (not in the paper)"}
SEED = 200  # the first lap's seed: the search tuned on seeds 0-3, the hand tuning on 0-9, held-out checks 100-109
LAPS = {"frontier": 10, "table2": 10, "table4": 25}  # per cell, as the paper flew them
QUICK_LAPS = 2


def resolve_parts(names: list[str], quick: bool = False) -> list[str]:
    """Expand aliases ("all", "table1", ...) into parts, in the order they run, without repeats."""
    wanted: set[str] = set()
    for name in names:
        if name not in CHOICES:
            raise ValueError(f"unknown part {name!r}; choose from {', '.join(CHOICES)}")
        wanted.update(ALIASES.get(name, (name,)))
    return [p for p in PARTS if p in wanted]


def _laps(part: str, quick: bool) -> int:
    return QUICK_LAPS if quick else LAPS[part]


def _frontier_speeds(quick: bool) -> tuple:
    from pixelmpc_jax.apps.experiments.frontier import DEFAULT_SPEEDS, QUICK_SPEEDS

    return QUICK_SPEEDS if quick else DEFAULT_SPEEDS


def _run_frontier(folder: Path, quick: bool, progress: bool) -> str:
    from pixelmpc_jax.apps.experiments.frontier import preset_cells, run_frontier
    from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEED

    cells = preset_cells(PAPER_PACE_SPEED)
    run_frontier(_frontier_speeds(quick), cells[:2] if quick else cells, folder, laps=_laps("frontier", quick),
                 seed=SEED, progress=progress)
    return "REPORT.md"


def _run_table2(folder: Path, quick: bool, progress: bool, pixel_model: str = "dof") -> str:
    from pixelmpc_jax.apps.experiments.paper import visibility_experiment

    root = folder.parent
    frontier_laps = _laps("frontier", quick)
    # the frontier's gains need the same laps: with fewer (quick), the tables read them off the frontier's own
    visibility_experiment(folder, laps=_laps("table2", quick), pixel_model=pixel_model, quick=quick,
                          progress=progress, seed=SEED, reuse=(root / "frontier", root / "table2"),
                          frontier_dir=root / "frontier" if frontier_laps == _laps("table2", quick) else None,
                          frontier_speeds=_frontier_speeds(quick))
    return "REPORT.md"


def _run_table4(folder: Path, quick: bool, progress: bool) -> str:
    from pixelmpc_jax.apps.experiments.estimation import estimation_experiment

    estimation_experiment(folder, laps=_laps("table4", quick), quick=quick, progress=progress, seed=SEED)
    return "REPORT.md"


def _run_dof(folder: Path, quick: bool, progress: bool) -> str:
    """The shipped DOF's accuracy and Fig. 7 for it and for the ``best`` preset's vdof (beside the turned DOF)."""
    from pixelmpc_jax.dynamics.vdof import PACKAGED_VDOF
    from pixelmpc_jax.learn.evaluate import run_evaluate

    horizon = 40 if quick else 80
    results = run_evaluate(out_dir=folder / "paper_dof", horizon=horizon, progress=progress)
    vdof_results = run_evaluate(weights=PACKAGED_VDOF, out_dir=folder / "vdof", horizon=horizon, progress=progress)
    (folder / "REPORT.md").write_text(_dof_report(results, vdof_results))
    return "REPORT.md"


def _run_bench(folder: Path, quick: bool, progress: bool) -> str:
    from pixelmpc_jax.apps.bench.suite import run_bench

    run_bench(folder, quick=quick)
    return "bench.md"


def _run_robustness(folder: Path, quick: bool, progress: bool) -> str:
    from pixelmpc_jax.apps.experiments.robustness import robustness_experiment

    robustness_experiment(folder, quick=quick, progress=progress)
    return "REPORT.md"


RUNNERS: dict[str, Callable[[Path, bool, bool], str]] = {
    "frontier": _run_frontier, "table2": _run_table2, "table4": _run_table4, "dof": _run_dof, "bench": _run_bench,
    "table2_projection": lambda folder, quick, progress: _run_table2(folder, quick, progress, "projection"),
    "robustness": _run_robustness}


def _part_wall_time(folder: Path, measured: float) -> float:
    """A part's wall time: this run's, or, for a grid resumed over several runs, the sum of its cells'."""
    from pixelmpc_jax.apps.racing.grid import load_results

    cells = load_results(folder)
    return max(measured, sum(cell.get("wall_time_s", 0.0) for cell in cells.values() if isinstance(cell, dict)))


def _dof_report(results: dict, vdof_results: dict) -> str:
    from pixelmpc_jax.learn import vdof_eval
    from pixelmpc_jax.learn.evaluate import summarise

    lines = ["# DOF accuracy on held-out flights and Fig. 7", "", "The shipped DOF (the `paper` preset's pixel model):",
             "", "```", summarise(results), "```", "", "![DOF flow fields](paper_dof/dof_flow_fields.png)",
             "![Fig. 7, the shipped DOF](paper_dof/dof_multistep.png)", "",
             "The `best` preset's pixel model, vdof (velocity and the gate's apparent size), beside the DOF trained "
             "with turned rows on the same frames:", "", "```", vdof_eval.summarise(vdof_results), "```", "",
             "![Fig. 7, vdof](vdof/vdof_multistep.png)"]
    return "\n".join(lines) + "\n"


def _relink(markdown: str, folder: str) -> str:
    """Point a part report's relative image links at its folder (the combined report sits one level up)."""
    import re

    return re.sub(r"\]\((?!https?:|/)([^)]+\.png)\)", lambda m: f"]({folder}/{m.group(1)})", markdown)


def _overview(out: Path) -> list[str]:
    """The presets, and the paper's pace as the frontier measured it: our nominal laps beside the paper's."""
    from pixelmpc_jax.apps.racing.frontier_curve import interpolate
    from pixelmpc_jax.apps.racing.presets import PAPER_NOMINAL_LAP_S, PAPER_PACE_SPEEDS, WHY

    lines = ["The presets: " + "; ".join(f"`{name}`: {why}" for name, why in WHY.items()) + ".", "",
             f"Every race flies seeds {SEED} onwards, which no setting was tuned on. The paper's pace: the targets at "
             "which our nominal MPPI flies the paper's nominal laps."]
    path = out / "frontier" / "frontier.json"
    nominal = {p["speed"]: p for p in json.loads(path.read_text())["nominal"]} if path.exists() else {}
    lines += ["", "| paper label | paper's nominal lap [s] | our pace (recorded) | our nominal lap there [s] | "
              "target giving the paper's lap on these seeds |", "|---|---|---|---|---|"]
    for label, pace in PAPER_PACE_SPEEDS.items():
        point = nominal.get(pace) or {}
        ours = (f"{point['lap_time_s']:.1f} ± {point['lap_time_two_sigma_s']:.1f}"
                if point.get("lap_time_s") is not None else "-")
        paper = PAPER_NOMINAL_LAP_S.get(label)
        here = interpolate(list(nominal.values()), paper, "speed") if paper is not None else None
        lines.append(f"| {label:g} m/s | {paper if paper is not None else '- (straight lane)'} | {pace:g} m/s | "
                     f"{ours} | {f'{here:.2f} m/s' if here is not None else '-'} |")
    return lines + ["", "The paces were read off the nominal frontier on seeds 0-9 (`presets.PAPER_PACE_SPEEDS`) and "
                    "stay fixed, so every table flies the same targets; the last column is where this run's own "
                    "frontier puts the paper's laps: a 10-lap block of seeds moves the nominal lap by a few per cent.",
                    ""]


def write_report(out: Path, state: dict) -> Path:
    """Combine the finished parts' reports into ``out/REPORT.md``."""
    from pixelmpc_jax.platform_info import device_line

    lines = ["# pixelmpc-jax: the paper reproduced", "",
             f"Written {datetime.datetime.now().isoformat(timespec='seconds')} on {device_line()}.", "",
             "| part | mode | wall time | finished |", "|---|---|---|---|"]
    partial = [part for part in PARTS if part not in state and (out / part / "REPORT.md").exists()]
    for part in PARTS:
        entry = state.get(part)
        if entry:
            lines.append(f"| [{TITLES[part]}](#{part}) | {'quick' if entry['quick'] else 'full'} | "
                         f"{entry['wall_time_s'] / 60:.1f} min | {entry['finished']} |")
        elif part in partial:
            lines.append(f"| [{TITLES[part]}](#{part}) | - | - | no: interrupted, resume with "
                         f"`pixelmpc reproduce {part} --out {out}` |")
        elif part in ALL and state:
            lines.append(f"| {TITLES[part]} | - | - | not run yet: `pixelmpc reproduce {part} --out {out}` |")
    lines += ["", *_overview(out)]
    total = sum(entry["wall_time_s"] for entry in state.values())
    lines += ["", f"Total wall time of the finished parts: {total / 60:.1f} min (an unfinished part reports the "
              "wall time of its finished cells in its own section).", ""]
    for part in PARTS:
        entry = state.get(part)
        if not entry and part not in partial:
            continue
        report = out / part / (entry["report"] if entry else "REPORT.md")
        body = report.read_text() if report.exists() else f"(missing: {report})\n"
        # demote the part's headings one level under its section
        body_lines = body.splitlines()
        if body_lines and body_lines[0].startswith("# ") and body_lines[0][2:].strip() == TITLES[part]:
            body_lines = body_lines[1:]  # the section's own title says it
        body = "\n".join("#" + line if line.startswith("#") else line for line in body_lines)
        lines += [f'<a id="{part}"></a>', "", f"## {TITLES[part]}", "", _relink(body, part), ""]
    path = out / "REPORT.md"
    tmp = path.with_suffix(f".md.{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return path


def _read_state(path: Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {}


def reproduce(parts: list[str], out: Path, quick: bool = False, progress: bool = True) -> dict:
    """Run the named parts (aliases allowed) into ``out`` and write ``out/REPORT.md``; returns the state."""
    from pixelmpc_jax.strict_json import write_json_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = resolve_parts(parts, quick)
    state_path = out / "reproduce.json"
    state = _read_state(state_path)
    for part in names:
        entry = state.get(part)
        if entry and entry["quick"] == quick:
            print(f"[{part}] kept: finished {entry['finished']} in {entry['wall_time_s'] / 60:.1f} min")
            continue
        print(f"[{part}] {TITLES[part]} ({'quick' if quick else 'full'}) ...", flush=True)
        folder = out / part
        folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        report = RUNNERS[part](folder, quick, progress)
        entry = {"quick": quick, "wall_time_s": _part_wall_time(folder, time.perf_counter() - start),
                 "report": report, "finished": datetime.datetime.now().isoformat(timespec="seconds")}
        # re-read: another process may have finished other parts into the same folder meanwhile
        state = {**_read_state(state_path), part: entry}
        write_json_atomic(state_path, state)
        write_report(out, state)
        print(f"[{part}] done in {state[part]['wall_time_s'] / 60:.1f} min", flush=True)
    write_report(out, state)
    return state
