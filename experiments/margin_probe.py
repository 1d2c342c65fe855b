"""The robustness experiment's ``margin`` lever on the ``best`` preset, where the reproduction reports it: Table IV's
filter cells at both paces (25 laps from seed 200) and the true-state frontier cell at the preset's pace (10 laps).

    pixelmpc reproduce frontier --out runs/reproduce
    python experiments/margin_probe.py --out runs/margin --frontier runs/reproduce/frontier

The frontier folder's nominal cells are copied, not flown again. Resumable per cell; prints each cell's figures and
writes ``truth/``, ``pf/`` (grid folders) and ``truth_frontier.json``.
"""

import argparse
import json
from pathlib import Path

from pixelmpc_jax.apps import frontier, grid, robustness, tune
from pixelmpc_jax.apps.presets import PAPER_PACE_SPEEDS, preset
from pixelmpc_jax.apps.reproduce import SEED

FRONTIER_SPEEDS = (6.0, 7.0, 8.0, 8.5, 9.1, 10.0, 12.0, 14.0)  # the reproduction's nominal frontier, m/s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frontier", type=Path, nargs="*", default=(), help="grid folders to copy nominal cells from")
    args = parser.parse_args(argv)
    best = preset("best")
    spec = robustness.race("pixelmpc", "truth", levers="margin")  # best, fault-free, with the margin lever
    truth = [frontier.nominal_cell(v, best.max_time_s) for v in FRONTIER_SPEEDS]
    truth.append(grid.Cell(f"margin_v{best.speed:g}", spec))
    tune.adopt(truth, args.out / "truth", 10, SEED, args.frontier)
    results = grid.run_grid(truth, args.out / "truth", laps=10, seed=SEED, progress=True)
    built = frontier.build(results, FRONTIER_SPEEDS, truth[-1:], 10, SEED, best.max_time_s)
    (args.out / "truth_frontier.json").write_text(json.dumps(built, indent=1, default=str))
    row = built["cells"][0]
    print(f"{row['name']}: {row['laps_completed']}/10 laps, {row['lap_time_s']:.2f} s, "
          f"avoidable {row['avoidable_s']:.2f} s, frontier gain {row['frontier_gain']:.2f} "
          f"{row['frontier_gain_interval']}", flush=True)
    for label in (16.0, 14.0):
        cell = grid.Cell(f"margin_{PAPER_PACE_SPEEDS[label]:g}ms_pf",
                         spec.replace(speed=PAPER_PACE_SPEEDS[label], estimator="pf"))
        done = grid.run_grid([cell], args.out / "pf", laps=25, seed=SEED, progress=True)[cell.name]
        failures = {}
        for lap in done["laps"]:
            if not lap["success"]:
                failures[lap.get("crash")] = failures.get(lap.get("crash"), 0) + 1
        print(f"{cell.name}: {sum(lap['success'] for lap in done['laps'])}/25 laps, failures {failures}", flush=True)


if __name__ == "__main__":
    main()
