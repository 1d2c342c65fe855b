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


def test_rendered_batches_compile_optimised_where_the_run_compiles_at_its_cheapest(request):
    """``render_batch`` is jitted with XLA's default optimisation (``compiler_options``) where the run compiles at its
    cheapest (tests/conftest.py), and only there: such a program may not be called inside another jit."""
    import jax
    import jax.numpy as jnp

    from pixelmpc_jax.world import camera, course, render

    straight = course.straight_course(num_gates=1)
    view = camera.default_camera(wh=(8, 6))
    poses = jnp.zeros((1, 10)).at[:, 3].set(1.0)
    inside_another = jax.jit(lambda x: render.render_batch(straight, x, view, supersample=1).depth.sum())
    if FAST_COMPILE_XLA_FLAGS in os.environ.get("XLA_FLAGS", ""):
        with pytest.raises(ValueError, match="compiler_options"):
            inside_another(poses)
    else:
        assert bool(jnp.isfinite(inside_another(poses)))


def test_a_test_process_gets_each_computation_back_finished():
    """JAX runs the tests' CPU computations on the calling thread (tests/conftest.py), so a result is ready when the
    call returns. With JAX's default dispatch this product of 1,500 x 1,500 matrices is still running then."""
    import jax
    import jax.numpy as jnp

    product = jax.jit(lambda a: a @ a)
    a = jnp.ones((1500, 1500))
    product(a).block_until_ready()  # compiled
    assert product(a).is_ready()
