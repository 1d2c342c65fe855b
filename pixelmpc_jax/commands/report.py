"""``pixelmpc report``: the README's results table and ``docs/results.md``'s list of folders rebuilt from the results
index and the committed result folders, the package's copy of nominal MPPI's committed frontier rebuilt from its
folder, and a folder's compact per-tick record (:mod:`~pixelmpc_jax.sim.ticks_compact`) written from its full ones.

The first two read a checkout's ``experiments/results/`` through the repository's reporting tools,
``experiments/reporting/`` in the checkout (not part of the installed library, which never reads the results): the
command imports them from the checkout it is given and refuses in one line where there is none."""

from __future__ import annotations

import difflib
import importlib
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
                      help="rewrite the README's results table and docs/results.md's list of folders (between their "
                           "markers) from experiments/results/index.json")
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
        frontier_data = reporting(args.root, "frontier_data")
        old, new = frontier_data.rewrite(args.root, check=args.check)
        return _reported(old or "", new, frontier_data.IN_PACKAGE.as_posix(), "--frontier-data", args.check)
    index, readme_table = reporting(args.root, "index"), reporting(args.root, "readme_table")
    readme = _reported(*readme_table.rewrite_readme(args.root, check=args.check), "README.md", "--readme", args.check)
    results = _reported(*index.rewrite_results_doc(args.root, check=args.check), index.RESULTS_DOC.as_posix(),
                        "--readme", args.check)
    return max(readme, results)


TOOLS = Path("experiments/reporting")


def reporting(root: Path, module: str):
    """The module ``module`` of the reporting tools of the checkout ``root`` (``experiments/reporting/``), imported
    from there; a ValueError in one line when ``root`` holds none (the tools are not installed with the package)."""
    if not (Path(root) / TOOLS / "__init__.py").is_file():
        raise ValueError(f"pixelmpc report reads a checkout's results with its tools in {TOOLS.as_posix()}/, and "
                         f"{Path(root).resolve()} holds none (run it from a checkout, or name one with --root)")
    checkout = str(Path(root).resolve())
    if checkout not in sys.path:
        sys.path.insert(0, checkout)
    return importlib.import_module(f"experiments.reporting.{module}")


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
