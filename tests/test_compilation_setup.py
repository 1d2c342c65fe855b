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
    """``render_batch`` as its callers compile it (``devices.compiled``) is jitted with XLA's default optimisation
    (``compiler_options``) where the run compiles at its cheapest (tests/conftest.py), and only there: such a program
    may not be called inside another jit. ``render_batch`` itself is pure, and traced inside another jit alike."""
    import jax
    import jax.numpy as jnp

    from pixelmpc_jax import devices
    from pixelmpc_jax.world import camera, course, render

    straight = course.straight_course(num_gates=1)
    view = camera.default_camera(wh=(8, 6))
    poses = jnp.zeros((1, 10)).at[:, 3].set(1.0)
    compiled = devices.compiled(render.render_batch, ("supersample", "chunk"))
    assert compiled is devices.compiled(render.render_batch, ("supersample", "chunk"))  # one program, asked twice
    inside_another = jax.jit(lambda x: compiled(straight, x, view, supersample=1).depth.sum())
    if FAST_COMPILE_XLA_FLAGS in os.environ.get("XLA_FLAGS", ""):
        with pytest.raises(ValueError, match="compiler_options"):
            inside_another(poses)
    else:
        assert bool(jnp.isfinite(inside_another(poses)))
    pure = jax.jit(lambda x: render.render_batch(straight, x, view, supersample=1).depth.sum())
    assert bool(jnp.isfinite(pure(poses)))


def test_a_test_process_gets_each_computation_back_finished():
    """JAX runs the tests' CPU computations on the calling thread (tests/conftest.py), so a result is ready when the
    call returns. With JAX's default dispatch this product of 1,500 x 1,500 matrices is still running then."""
    import jax
    import jax.numpy as jnp

    product = jax.jit(lambda a: a @ a)
    a = jnp.ones((1500, 1500))
    product(a).block_until_ready()  # compiled
    assert product(a).is_ready()


def test_the_heaviest_files_are_handed_out_first(request):
    """Every file HEAVIEST_FIRST names exists, and xdist keeps the collection's order (its own reorder, the files
    with the most tests first, would hand the golden laps out last)."""
    from pathlib import Path

    from conftest import HEAVIEST_FIRST

    here = Path(__file__).resolve().parent
    assert len(set(HEAVIEST_FIRST)) == len(HEAVIEST_FIRST)
    assert [name for name in HEAVIEST_FIRST if not (here / name).is_file()] == []
    assert request.config.getoption("loadscopereorder", default=False) is False
