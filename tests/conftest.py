import pytest


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run experiment-scale checks marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    marker = pytest.mark.skip(reason="experiment-scale; run with --runslow (a faster test covers the code)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(marker)
