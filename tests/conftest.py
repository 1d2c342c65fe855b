import os
import shutil
import tempfile

import pytest

_CACHE_HOME = {}


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run experiment-scale checks marked slow")


def pytest_configure(config):
    """The commands under test keep their compiled steps in ``$XDG_CACHE_HOME`` (see
    :func:`pixelmpc_jax.host.compilation_cache_dir`): point it at a folder of this test process, so a run neither
    writes into the user's cache nor starts warm from an earlier run's (each worker of ``-n`` has its own)."""
    _CACHE_HOME["old"] = os.environ.get("XDG_CACHE_HOME")
    _CACHE_HOME["new"] = tempfile.mkdtemp(prefix="pixelmpc-tests-cache-")
    os.environ["XDG_CACHE_HOME"] = _CACHE_HOME["new"]


def pytest_unconfigure(config):
    if _CACHE_HOME.get("old") is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = _CACHE_HOME["old"]
    shutil.rmtree(_CACHE_HOME.get("new", ""), ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    marker = pytest.mark.skip(reason="experiment-scale; run with --runslow (a faster test covers the code)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(marker)
