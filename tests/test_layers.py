"""The import rule of docs/architecture.md: layers import only the layers above them, inside ``apps/`` too, no
module of the library imports the experiment apps (``pixelmpc_jax.apps``), and the package needs nothing of the
checkout beside it (``benchmarks/``, ``experiments/``, ``tests/``) and reads no result folder, so it runs from a plain
``pip install``."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "pixelmpc_jax"
# Top to bottom: a module may import its own layer and those before it (and the shared top-level modules).
LAYERS = ("dynamics", "world", "perception", "control", "sim", "learn", "apps")
SHARED = {"timing", "strict_json", "platform_info", "host", "devices", "settings"}  # imported by any layer
# The package's front door, not a layer: it imports what users call from every layer, the apps' races too, and hands
# it on in its __all__ (tests/test_public_api.py); no module of the package imports it.
FACADE = "__init__.py"
# The apps, top to bottom likewise: a race and its grid, the harness that times a step, the experiments that fly
# grids of races (and call the harness in the reproduction), the searches over an experiment's cells.
APPS = ("racing", "bench", "experiments", "tuning")


def imported_modules(path: Path, package: str = "pixelmpc_jax") -> set[str]:
    """Every module under ``package`` a file imports, at its top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return {name for name in names if name == package or name.startswith(f"{package}.")}


def layer_of(module: str) -> str:
    """``pixelmpc_jax.sim.episode`` -> ``sim``; ``pixelmpc_jax.timing`` -> ``timing``."""
    return module.split(".")[1]


def violations(path: Path, package: Path = PACKAGE) -> list[str]:
    """The imports of ``path`` (inside ``package``) that break the rule: a later layer, or any layer from a
    shared module."""
    relative = path.relative_to(package)
    own = relative.parts[0] if len(relative.parts) > 1 else relative.stem
    own_app = relative.parts[1] if own == "apps" and len(relative.parts) > 2 else None
    bad = []
    for module in sorted(m for m in imported_modules(path) if m != "pixelmpc_jax"):
        target = layer_of(module)
        if own in LAYERS and target in LAYERS and LAYERS.index(target) > LAYERS.index(own):
            bad.append(f"{relative} imports {module}")
        elif own in SHARED and target in LAYERS:
            bad.append(f"{relative} (shared by every layer) imports {module}")
        elif own_app is not None and target == "apps":
            app = module.split(".")[2] if module.count(".") >= 2 else None
            if app not in APPS or APPS.index(app) > APPS.index(own_app):
                bad.append(f"{relative} (apps/{own_app}) imports {module}")
    return bad


def test_no_layer_imports_a_later_one_and_the_core_never_imports_the_apps():
    files = sorted(PACKAGE.rglob("*.py"))
    assert any(f.parts[-3:-1] == ("pixelmpc_jax", "learn") for f in files)  # the scan sees the package
    bad = [line for path in files for line in violations(path)]
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)
    core = [path for path in files if path.relative_to(PACKAGE).parts[0] not in ("apps", "cli.py", "commands", FACADE)]
    assert not [path for path in core if any(m.startswith("pixelmpc_jax.apps") for m in imported_modules(path))]


def test_the_package_imports_nothing_of_the_checkout(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import os\ndef f():\n    from benchmarks import suite\n")
    assert imported_modules(probe, "benchmarks") == {"benchmarks", "benchmarks.suite"}  # the scan sees one
    checkout = [f"{path.relative_to(PACKAGE)} imports {module}" for path in sorted(PACKAGE.rglob("*.py"))
                for folder in ("benchmarks", "experiments", "tests") for module in imported_modules(path, folder)]
    assert not checkout, "\n".join(checkout)


@pytest.mark.parametrize("source, own, bad", [
    ("from pixelmpc_jax.apps import race\n", "sim/x.py", True),
    ("def f():\n    import pixelmpc_jax.apps.racing.grid\n", "learn/x.py", True),  # a lazy import counts too
    ("from pixelmpc_jax.sim import episode\n", "control/x.py", True),
    ("from pixelmpc_jax.world import track\n", "timing.py", True),
    ("from pixelmpc_jax.sim import episode\n", "apps/x.py", False),
    ("from pixelmpc_jax import timing\n", "dynamics/x.py", False),
    ("from pixelmpc_jax.dynamics import dof\n", "learn/x.py", False),
    ("from pixelmpc_jax.devices import replicate\n", "control/x.py", False),
    ("from pixelmpc_jax.control import mppi\n", "devices.py", True),
    ("from pixelmpc_jax.apps.experiments import frontier\n", "apps/racing/x.py", True),
    ("def f():\n    from pixelmpc_jax.apps.tuning import search\n", "apps/experiments/x.py", True),
    ("from pixelmpc_jax.apps import readme_table\n", "apps/racing/x.py", True),  # a module outside the apps' order
    ("from pixelmpc_jax.apps.racing import grid\n", "apps/tuning/x.py", False),
    ("from pixelmpc_jax.apps.bench.suite import run_bench\n", "apps/experiments/x.py", False),
    ("from pixelmpc_jax.apps.experiments import frontier\n", "apps/experiments/x.py", False),
])
def test_the_scan_finds_a_wrong_import(tmp_path, source, own, bad):
    path = tmp_path / own
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(source)
    assert bool(violations(path, tmp_path)) == bad


# The library: pure functions, compiled by their callers (the runners, the commands; on the host through
# pixelmpc_jax.devices: compile_controller, compile_estimator, compiled), never by themselves.
LIBRARY = ("dynamics", "world", "perception", "control")


def jit_sites(path: Path) -> list[str]:
    """Where ``path`` compiles: ``jax.jit`` (called, as a decorator, in a ``partial``) or ``jit`` taken from jax."""
    name = path.relative_to(PACKAGE) if path.is_relative_to(PACKAGE) else path.name
    jits = {"jit", "pjit"}
    return [f"{name}:{node.lineno}" for node in ast.walk(ast.parse(path.read_text()))
            if (isinstance(node, ast.Attribute) and node.attr in jits and isinstance(node.value, ast.Name)
                and node.value.id == "jax")
            or (isinstance(node, ast.ImportFrom) and node.module == "jax" and {a.name for a in node.names} & jits)]


def test_the_library_layers_compile_nothing(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text('"""Not a jax.jit."""\nimport jax\nfrom functools import partial\nfrom jax import jit\n'
                     '@partial(jax.jit, static_argnames="n")\ndef f(x, n):\n    return x\n')
    assert jit_sites(probe) == ["probe.py:4", "probe.py:5"]  # the scan sees both, not the docstring
    found = [site for layer in LIBRARY for path in sorted((PACKAGE / layer).rglob("*.py")) for site in jit_sites(path)]
    assert found == [], "jit in the library (its callers compile: pixelmpc_jax.devices.compiled):\n" + "\n".join(found)


def test_every_app_has_its_place_in_the_order():
    apps = sorted(path.name for path in (PACKAGE / "apps").iterdir() if path.is_dir() and path.name != "__pycache__")
    assert apps == sorted(APPS)
    assert sorted(path.name for path in (PACKAGE / "apps").glob("*.py")) == ["__init__.py"]


# the package's strings that name the results folder, each with why it may: nowhere does the package read it
NAMES_THE_RESULTS = {"commands/experiment.py": "the folders experiments write into by default (--out)",
                     "arguments.py": "checkout_dir: a checkout is what `pixelmpc report --root` names"}


def results_paths(path: Path) -> list[str]:
    """The string constants of ``path`` (docstrings aside) that name a path in ``experiments/results``, or the folder
    ``experiments`` as a path's first part (``Path("experiments") / "results"``)."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body
                  and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [node.value for node in ast.walk(tree) if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and id(node) not in docstrings and (node.value.startswith("experiments/results")
                                                or node.value in ("experiments", "experiments/"))]


def test_the_package_reads_no_result_folder(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text('"""Reads experiments/results/ (a docstring may say so)."""\nfrom pathlib import Path\n'
                     'A = Path("experiments") / "results"\nB = "experiments/results/x/frontier.json"\n')
    assert sorted(results_paths(probe)) == ["experiments", "experiments/results/x/frontier.json"]  # the scan sees them
    found = {path.relative_to(PACKAGE).as_posix(): results_paths(path) for path in sorted(PACKAGE.rglob("*.py"))}
    assert {name: paths for name, paths in found.items() if paths and name not in NAMES_THE_RESULTS} == {}


def module_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """``{module: the package's modules it imports}`` (top level or inside a function), over module files."""
    modules = {".".join(("pixelmpc_jax", *path.relative_to(package).with_suffix("").parts)): path
               for path in package.rglob("*.py")}
    modules = {name.removesuffix(".__init__"): path for name, path in modules.items()}
    # ``from pixelmpc_jax import devices`` names the module devices, not the front door (which no module imports:
    # test_no_module_of_the_package_imports_the_front_door)
    return {name: {m for m in imported_modules(path) if m in modules and m not in (name, "pixelmpc_jax")}
            for name, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph``, each as the modules along it (depth-first search)."""
    found, state = [], {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = "open"
        for target in sorted(graph.get(node, ())):
            if state.get(target) == "open":
                found.append(trail[trail.index(target):] + [target])
            elif target not in state:
                visit(target, trail + [target])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return found


def test_no_import_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]  # the search sees one
    graph = module_graph()
    assert "pixelmpc_jax.world.track" in graph["pixelmpc_jax.world.course"]
    assert cycles(graph) == []


def reexports(path: Path) -> list[str]:
    """What makes ``path`` hand on another module's names: a module ``__getattr__``, or an ``__all__`` or
    ``import X as X`` naming an imported name."""
    tree = ast.parse(path.read_text())
    imported = {alias.asname or alias.name.split(".")[0] for node in tree.body
                if isinstance(node, (ast.Import, ast.ImportFrom)) for alias in node.names}
    found = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            found.append(f"{path.name}: a module __getattr__")
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            names = {elt.value for elt in getattr(node.value, "elts", []) if isinstance(elt, ast.Constant)}
            found += [f"{path.name}: __all__ hands on {name}" for name in sorted(names & imported)]
        if isinstance(node, ast.ImportFrom):
            found += [f"{path.name}: import {a.name} as {a.asname}" for a in node.names if a.asname == a.name]
    return found


def test_no_module_hands_on_another_modules_names(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from os import path\n__all__ = ['path']\ndef __getattr__(name):\n    pass\n")
    assert reexports(probe) == ["probe.py: __all__ hands on path", "probe.py: a module __getattr__"]
    found = [line for path in sorted(PACKAGE.rglob("*.py")) if path != PACKAGE / FACADE for line in reexports(path)]
    assert found == []


def facade_imports(path: Path) -> list[str]:
    """The names ``path`` takes from the package's front door (``from pixelmpc_jax import X`` where ``X`` is no
    module of the package, nor the version the front door itself defines)."""
    modules = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir() if p.is_dir()}
    modules.add("__version__")
    return [alias.name for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ImportFrom) and node.module == "pixelmpc_jax" and node.level == 0
            for alias in node.names if alias.name not in modules]


def test_no_module_of_the_package_imports_the_front_door(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from pixelmpc_jax import devices, make_mppi\n")
    assert facade_imports(probe) == ["make_mppi"]  # the scan sees one
    found = {path.relative_to(PACKAGE).as_posix(): facade_imports(path) for path in sorted(PACKAGE.rglob("*.py"))}
    assert {name: names for name, names in found.items() if names} == {}
