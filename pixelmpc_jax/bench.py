"""Library entry of ``pixelmpc bench``: the runtime harness in the repository's ``benchmarks/`` folder.

``run_bench(out_dir, quick)`` writes ``bench.json``, ``bench.md`` and ``scaling.png`` into ``out_dir`` and
returns the bench.json content (see ``benchmarks/suite.py``). The harness lives beside the package, not in
it (it needs the repository checkout, and torch/pytorch-mppi for the peer rows: the ``bench`` extra).
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def _suite():
    try:
        from benchmarks import suite
    except ImportError:
        if not (REPO_ROOT / "benchmarks" / "suite.py").exists():
            raise ImportError(f"pixelmpc bench needs the repository checkout: {REPO_ROOT / 'benchmarks'} "
                              f"is missing (the harness is not part of an installed wheel)") from None
        sys.path.insert(0, str(REPO_ROOT))
        from benchmarks import suite
    return suite


def run_bench(out_dir, quick: bool = False, smoke: bool = False) -> dict:
    """Run the runtime harness; ``quick``: the paper-size controller rows, the roofline and the pytorch-mppi
    peer (under 5 min on 2 CPU cores); ``smoke``: tiny sizes for tests. Returns the bench.json content."""
    return _suite().run_bench(out_dir, quick=quick, smoke=smoke)
