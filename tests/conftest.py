import os
import shutil
import tempfile

import pytest

_CACHE_HOME = {}
# Compilations shorter than this are not written to the shared cache: loading one costs about as much as making it.
_MIN_CACHED_COMPILE_S = 0.2


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run experiment-scale checks marked slow")


def pytest_configure(config):
    """One compilation cache for the whole run, made before the first compile.

    The commands under test keep their compiled steps in ``$XDG_CACHE_HOME`` (see
    :func:`pixelmpc_jax.host.compilation_cache_dir`). The first process of the run (the xdist controller, or the
    only process without ``-n``) points it at a fresh folder, so a run neither writes into the user's cache nor
    starts warm from an earlier run's. The xdist workers and the commands' subprocesses inherit it. Every test
    process keeps its own compilations there too (JAX's persistent cache), so a step that two test files or a
    test and a subprocess compile is compiled once per run."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        _CACHE_HOME["old"] = os.environ.get("XDG_CACHE_HOME")
        _CACHE_HOME["new"] = tempfile.mkdtemp(prefix="pixelmpc-tests-cache-")
        os.environ["XDG_CACHE_HOME"] = _CACHE_HOME["new"]
    from pixelmpc_jax.host import use_compilation_cache

    use_compilation_cache(min_compile_s=_MIN_CACHED_COMPILE_S)


def pytest_unconfigure(config):
    if "new" not in _CACHE_HOME:  # a worker: the folder is the controller's
        return
    if _CACHE_HOME.get("old") is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = _CACHE_HOME["old"]
    shutil.rmtree(_CACHE_HOME["new"], ignore_errors=True)


# The files that compile the most (closed-loop episodes, subprocesses), heaviest first, as ``--durations`` measured
# them. They are handed out first: with one file to a worker (``--dist loadfile``), a run that hands out its longest
# files last ends on one worker while the other waits.
HEAVIEST_FIRST = ("test_episode.py", "test_pixelmpc.py", "test_collect.py", "test_compare.py", "test_golden_laps.py",
                  "test_env.py", "test_particle_filter.py", "test_evaluate.py", "test_sharding.py", "test_frontier.py",
                  "test_sample_devices.py", "test_eskf.py", "test_quadrotor.py", "test_vdof.py", "test_cli.py")


def _heaviest_first(items) -> None:
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file keeps its own order


def pytest_collection_modifyitems(config, items):
    _heaviest_first(items)
    if config.getoption("--runslow"):
        return
    marker = pytest.mark.skip(reason="experiment-scale; run with --runslow (a faster test covers the code)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(marker)
