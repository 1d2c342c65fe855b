"""The package's front door (``pixelmpc_jax/__init__.py``): the public names, exactly; each one what it says; nothing
else of the package imports it. A rename or a removal here is a change of the library's interface, made on purpose
(docs/architecture.md: what is public)."""

import ast
import subprocess
import sys
from pathlib import Path

import pixelmpc_jax

FACADE = Path(pixelmpc_jax.__file__)

PUBLIC = [
    "MPPIConfig", "MPPIState", "MPPIInfo", "Controller", "make_mppi",
    "Execution", "CompiledController", "compile_controller",
    "ControllerConfig", "PixelMPCParams", "make_pixelmpc", "make_nominal_mppi", "paper_mppi_config",
    "RacingCostConfig", "racing_params",
    "quadrotor", "load_packaged_dof", "load_packaged_vdof", "default_camera",
    "World", "make_world", "load_course", "make_course", "course_from_gates",
    "fly", "Policy", "make_policy", "EpisodeConfig", "EpisodeLog", "make_runner",
    "PRESETS", "preset", "nominal_of", "RaceSpec", "race", "RaceResult",
    "__version__",
]


def test_the_public_names_are_the_listed_ones():
    assert pixelmpc_jax.__all__ == PUBLIC
    assert all(hasattr(pixelmpc_jax, name) for name in PUBLIC)


def test_each_public_name_is_the_one_from_where_it_lives():
    from pixelmpc_jax.apps.racing import race
    from pixelmpc_jax.control import mppi
    from pixelmpc_jax.dynamics import quadrotor

    assert pixelmpc_jax.make_mppi is mppi.make_mppi and pixelmpc_jax.MPPIConfig is mppi.MPPIConfig
    assert pixelmpc_jax.fly is race.fly and pixelmpc_jax.race is race.race and pixelmpc_jax.quadrotor is quadrotor
    assert pixelmpc_jax.PRESETS == ("best", "paper", "racing")


def test_the_front_door_only_imports_and_lists():
    """The facade holds imports, the version and ``__all__``, and lists every name it imports (no hidden extra)."""
    tree = ast.parse(FACADE.read_text())
    imported = set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            imported |= {alias.asname or alias.name for alias in node.names}
        elif isinstance(node, ast.Assign):
            assert [t.id for t in node.targets] in (["__version__"], ["__all__"])
        else:
            assert isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant), ast.dump(node)[:80]
    assert imported | {"__version__"} == set(PUBLIC)


def test_importing_the_package_starts_no_backend():
    """``import pixelmpc_jax`` makes no array, so a program (and ``pixelmpc``) can still split the CPU into devices
    (:func:`pixelmpc_jax.host.split_host_cpu`) after it."""
    code = ("import pixelmpc_jax\nfrom jax._src import xla_bridge\nimport sys\n"
            "assert not xla_bridge._backends\nassert 'matplotlib' not in sys.modules and 'optuna' not in sys.modules\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
