"""The test run's compilation (tests/conftest.py): at XLA's cheapest by default, and as a user's run compiles for
the tests that compare with figures recorded so."""

import os

import pytest
from conftest import FAST_COMPILE_XLA_FLAGS, USER_XLA_FLAGS


def test_the_run_compiles_at_xlas_cheapest_unless_told_otherwise(request):
    flags = os.environ.get("XLA_FLAGS", "")
    if request.config.getoption("--runslow") or request.config.getoption("--optimized-xla"):
        assert FAST_COMPILE_XLA_FLAGS not in flags and USER_XLA_FLAGS not in os.environ
    else:
        assert flags.endswith(FAST_COMPILE_XLA_FLAGS) and USER_XLA_FLAGS in os.environ


@pytest.mark.compiled_as_shipped
def test_a_test_compiled_as_shipped_runs_with_the_flags_the_run_began_with():
    assert FAST_COMPILE_XLA_FLAGS not in os.environ.get("XLA_FLAGS", "")
    assert USER_XLA_FLAGS not in os.environ
