"""``pixelmpc report``: the README's results table rebuilt from the committed result folders
(:mod:`~pixelmpc_jax.apps.readme_table`), the package's copy of nominal MPPI's committed frontier rebuilt from its
folder (:mod:`~pixelmpc_jax.apps.racing.nominal_frontier`), and a folder's compact per-tick record
(:mod:`~pixelmpc_jax.sim.ticks_compact`) written from its full ones."""

from __future__ import annotations

import difflib
import sys
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.commands import EXIT_FAILED


def add_report(sub) -> None:
    """``pixelmpc report``: the README's results table, the shipped nominal frontier, a folder's compact per-tick
    record."""
    p = sub.add_parser("report", help="rebuild the README's results table from experiments/results (--readme) or the "
                                      "package's nominal frontier (--frontier-data), or write a folder's compact "
                                      "per-tick record (--compact DIR)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--readme", action="store_true",
                      help="rewrite the README's results table (between its results:begin/end markers)")
    what.add_argument("--frontier-data", action="store_true",
                      help="rewrite pixelmpc_jax/data/nominal_frontier.json, nominal MPPI's frontier that `pixelmpc "
                           "race` holds PixelMPC's lap time against, from its committed folder")
    what.add_argument("--compact", type=arg.ticks_dir, metavar="DIR",
                      help="write DIR/ticks_compact.npz from the per-tick records in DIR (ticks_<race>.npz)")
    p.add_argument("--check", action="store_true",
                   help="with --readme or --frontier-data: change nothing; exit 1 and print the difference when the "
                        "file is not current")
    p.add_argument("--root", type=arg.checkout_dir, default=Path("."),
                   help="the checkout whose README, package data and experiments/results to read (default: here)")
    p.set_defaults(func=_cmd_report, validate=_validate)


def _validate(args) -> str | None:
    if args.check and not (args.readme or args.frontier_data):
        return "--check goes with --readme or --frontier-data"
    return None


def _cmd_report(args) -> int:
    if args.compact is not None:
        from pixelmpc_jax.sim import ticks_compact

        path = ticks_compact.convert_folder(args.compact)
        races = ticks_compact.load(path)
        print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB): " + ", ".join(
            f"{name} ({len(race['num_ticks'])} laps)" for name, race in races.items()))
        return 0
    if args.frontier_data:
        from pixelmpc_jax.apps.racing import nominal_frontier

        old, new = nominal_frontier.rewrite(args.root, check=args.check)
        return _reported(old or "", new, nominal_frontier.IN_PACKAGE.as_posix(), "--frontier-data", args.check)
    from pixelmpc_jax.apps import readme_table

    old, new = readme_table.rewrite_readme(args.root, check=args.check)
    return _reported(old, new, "README.md", "--readme", args.check)


def _reported(old: str, new: str, name: str, flag: str, check: bool) -> int:
    """Say whether the file ``name`` was current; with ``check``, print the difference and exit 1 when it was not."""
    if old == new:
        print(f"{name}: current")
        return 0
    if check:
        sys.stdout.writelines(difflib.unified_diff(old.splitlines(keepends=True), new.splitlines(keepends=True),
                                                   name, f"{name} (pixelmpc report {flag})"))
        return EXIT_FAILED
    print(f"{name}: rewritten")
    return 0
