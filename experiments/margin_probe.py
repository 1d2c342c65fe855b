"""The ``best`` preset's clearance to the gate frames (``presets.BEST_VEHICLE_RADIUS_M``, 0.3 m) against the vehicle's
own 0.1 m, where the reproduction reports it: Table IV's filter cells at both paces (25 laps) and the true-state
frontier cell at the preset's pace (10 laps).

    pixelmpc reproduce frontier --out runs/reproduce
    python experiments/margin_probe.py --out runs/margin --frontier runs/reproduce/frontier [--seed 200]

The frontier folder's nominal cells (the same seeds) are copied, not flown again. Resumable per cell; prints each
cell's figures and writes ``truth/``, ``pf/`` (grid folders) and ``truth_frontier.json``. Cells: ``margin_*`` the
preset, ``plain_*`` the preset with the 0.1 m clearance.
"""

import argparse
import dataclasses
import json
from pathlib import Path

from pixelmpc_jax.apps import frontier, grid, tune
from pixelmpc_jax.apps.presets import PAPER_PACE_SPEEDS, preset
from pixelmpc_jax.apps.reproduce import SEED
from pixelmpc_jax.control.costs import RacingCostConfig

FRONTIER_SPEEDS = (6.0, 7.0, 8.0, 8.5, 9.1, 10.0, 12.0, 14.0)  # the reproduction's nominal frontier, m/s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frontier", type=Path, nargs="*", default=(), help="grid folders to copy nominal cells from")
    parser.add_argument("--seed", type=int, default=SEED, help="the first lap's seed (default: the reproduction's)")
    args = parser.parse_args(argv)
    best = preset("best")
    plain = best.replace(config=dataclasses.replace(best.config, racing=RacingCostConfig()))  # the vehicle's 0.1 m
    truth = [frontier.nominal_cell(v, best.max_time_s) for v in FRONTIER_SPEEDS]
    truth += [grid.Cell(f"margin_v{best.speed:g}", best), grid.Cell(f"plain_v{best.speed:g}", plain)]
    tune.adopt(truth, args.out / "truth", 10, args.seed, args.frontier)
    results = grid.run_grid(truth, args.out / "truth", laps=10, seed=args.seed, progress=True)
    built = frontier.build(results, FRONTIER_SPEEDS, truth[-2:], 10, args.seed, best.max_time_s)
    (args.out / "truth_frontier.json").write_text(json.dumps(built, indent=1, default=str))
    for row in built["cells"]:
        print(f"{row['name']}: {row['laps_completed']}/10 laps, {row['lap_time_s']:.2f} s, "
              f"avoidable {row['avoidable_s']:.2f} s, frontier gain {row['frontier_gain']:.2f} "
              f"{row['frontier_gain_interval']}", flush=True)
    for label in (16.0, 14.0):
        for name, spec in (("margin", best), ("plain", plain)):
            cell = grid.Cell(f"{name}_{PAPER_PACE_SPEEDS[label]:g}ms_pf",
                             spec.replace(speed=PAPER_PACE_SPEEDS[label], estimator="pf"))
            done = grid.run_grid([cell], args.out / "pf", laps=25, seed=args.seed, progress=True)[cell.name]
            failures = {}
            for lap in done["laps"]:
                if not lap["success"]:
                    failures[lap.get("crash")] = failures.get(lap.get("crash"), 0) + 1
            print(f"{cell.name}: {sum(lap['success'] for lap in done['laps'])}/25 laps, failures {failures}",
                  flush=True)


if __name__ == "__main__":
    main()
