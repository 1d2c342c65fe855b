"""``pixelmpc reproduce``: every table and figure of the paper, ours beside the paper's, in one report.

Parts (each in its own folder under ``out``, each resumable on its own):

- ``bench``: Table I (runtimes), the controller step and its scaling, the peers, the matmul limit;
- ``dof``: the DOF network's accuracy on held-out flights (AEE, baselines, multi-step error, figures);
- ``table2``: Tables II and III and Fig. 8 (visibility, lap time, smoothness) with the DOF pixel model;
- ``table2_projection``: the same grid with the PAMPC-style projection pixel model (not in the paper);
- ``table4``: Table IV, the straight lane and Fig. 9 (racing on the particle filter's estimate);
- ``frontier``: PixelMPC against nominal MPPI flown slower (the speed frontier, not in the paper).

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

PARTS = ("bench", "dof", "table2", "table2_projection", "table4", "frontier")
ALIASES = {"all": PARTS, "table1": ("bench",), "table3": ("table2",), "fig8": ("table2",), "fig9": ("table4",),
           "projection": ("table2_projection",)}
QUICK_PARTS = ("bench", "dof", "table2", "table4")  # --quick all: the paper's tables only
CHOICES = tuple(ALIASES) + PARTS
TITLES = {"bench": "Table I and the runtime harness", "dof": "DOF accuracy (Section V-A)",
          "table2": "Tables II-III and Fig. 8", "table2_projection": "Tables II-III with the projection pixel model",
          "table4": "Table IV, the straight lane and Fig. 9",
          "frontier": "The speed frontier: PixelMPC against flying slower"}


def resolve_parts(names: list[str], quick: bool = False) -> list[str]:
    """Expand aliases ("all", "table1", ...) into parts, in the canonical order, without repeats."""
    wanted: set[str] = set()
    for name in names:
        if name not in CHOICES:
            raise ValueError(f"unknown part {name!r}; choose from {', '.join(CHOICES)}")
        if name == "all" and quick:
            wanted.update(QUICK_PARTS)
        else:
            wanted.update(ALIASES.get(name, (name,)))
    return [p for p in PARTS if p in wanted]


def _runners(quick: bool, progress: bool) -> dict[str, Callable[[Path], str]]:
    """part -> run(folder) -> the part's Markdown report file name inside the folder."""

    def bench(folder: Path) -> str:
        from pixelmpc_jax.apps.bench.suite import run_bench

        run_bench(folder, quick=quick)
        return "bench.md"

    def dof(folder: Path) -> str:
        from pixelmpc_jax.learn.evaluate import run_evaluate

        results = run_evaluate(out_dir=folder, horizon=40 if quick else 80, progress=progress)
        (folder / "REPORT.md").write_text(_dof_report(results))
        return "REPORT.md"

    def table2(folder: Path, pixel_model: str = "dof") -> str:
        from pixelmpc_jax.apps.paper import visibility_experiment

        visibility_experiment(folder, laps=2 if quick else 10, pixel_model=pixel_model, quick=quick,
                              progress=progress)
        return "REPORT.md"

    def table4(folder: Path) -> str:
        from pixelmpc_jax.apps.estimation import estimation_experiment

        estimation_experiment(folder, laps=2 if quick else 25, quick=quick, progress=progress)
        return "REPORT.md"

    def frontier(folder: Path) -> str:
        from pixelmpc_jax.apps.frontier import default_spec, quick_spec, run_frontier

        spec = quick_spec() if quick else default_spec()
        run_frontier(spec.nominal_speeds, spec.cells, folder, laps=spec.laps, progress=progress)
        return "REPORT.md"

    return {"bench": bench, "dof": dof, "table2": table2,
            "table2_projection": lambda folder: table2(folder, "projection"), "table4": table4,
            "frontier": frontier}


def _part_wall_time(folder: Path, measured: float) -> float:
    """A part's wall time: this run's, or, for a grid resumed over several runs, the sum of its cells'."""
    from pixelmpc_jax.apps.grid import load_results

    cells = load_results(folder)
    return max(measured, sum(cell.get("wall_time_s", 0.0) for cell in cells.values() if isinstance(cell, dict)))


def _dof_report(results: dict) -> str:
    from pixelmpc_jax.learn.evaluate import summarise

    lines = ["# DOF accuracy on held-out flights", "", "```", summarise(results), "```", ""]
    for name in ("dof_flow_fields.png", "dof_multistep.png"):
        lines.append(f"![{name}]({name})")
    return "\n".join(lines) + "\n"


def _relink(markdown: str, folder: str) -> str:
    """Point a part report's relative image links at its folder (the combined report sits one level up)."""
    import re

    return re.sub(r"\]\((?!https?:|/)([^)]+\.png)\)", lambda m: f"]({folder}/{m.group(1)})", markdown)


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
        body = "\n".join("#" + line if line.startswith("#") else line for line in body.splitlines())
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
    runners = _runners(quick, progress)
    for part in names:
        entry = state.get(part)
        if entry and entry["quick"] == quick:
            print(f"[{part}] kept: finished {entry['finished']} in {entry['wall_time_s'] / 60:.1f} min")
            continue
        print(f"[{part}] {TITLES[part]} ({'quick' if quick else 'full'}) ...", flush=True)
        folder = out / part
        folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        report = runners[part](folder)
        entry = {"quick": quick, "wall_time_s": _part_wall_time(folder, time.perf_counter() - start),
                 "report": report, "finished": datetime.datetime.now().isoformat(timespec="seconds")}
        # re-read: another process may have finished other parts into the same folder meanwhile
        state = {**_read_state(state_path), part: entry}
        write_json_atomic(state_path, state)
        write_report(out, state)
        print(f"[{part}] done in {state[part]['wall_time_s'] / 60:.1f} min", flush=True)
    write_report(out, state)
    return state
