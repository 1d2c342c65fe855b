"""The import rule of docs/architecture.md: layers import only the layers above them, no module of
the library imports the experiment apps (``pixelmpc_jax.apps``), and the package needs nothing of the checkout
beside it (``benchmarks/``, ``experiments/``, ``tests/``), so it runs from a plain ``pip install``."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "pixelmpc_jax"
# Top to bottom: a module may import its own layer and those before it (and the shared top-level modules).
LAYERS = ("dynamics", "world", "perception", "control", "sim", "learn", "apps")
SHARED = {"timing", "strict_json", "platform_info", "host", "devices"}  # imported by any layer


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
    bad = []
    for module in sorted(m for m in imported_modules(path) if m != "pixelmpc_jax"):
        target = layer_of(module)
        if own in LAYERS and target in LAYERS and LAYERS.index(target) > LAYERS.index(own):
            bad.append(f"{relative} imports {module}")
        elif own in SHARED and target in LAYERS:
            bad.append(f"{relative} (shared by every layer) imports {module}")
    return bad


def test_no_layer_imports_a_later_one_and_the_core_never_imports_the_apps():
    files = sorted(PACKAGE.rglob("*.py"))
    assert any(f.parts[-3:-1] == ("pixelmpc_jax", "learn") for f in files)  # the scan sees the package
    bad = [line for path in files for line in violations(path)]
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)
    core = [path for path in files if path.relative_to(PACKAGE).parts[0] not in ("apps", "cli.py", "commands")]
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
])
def test_the_scan_finds_a_wrong_import(tmp_path, source, own, bad):
    path = tmp_path / own
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(source)
    assert bool(violations(path, tmp_path)) == bad


def module_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """``{module: the package's modules it imports}`` (top level or inside a function), over module files."""
    modules = {".".join(("pixelmpc_jax", *path.relative_to(package).with_suffix("").parts)): path
               for path in package.rglob("*.py")}
    modules = {name.removesuffix(".__init__"): path for name, path in modules.items()}
    return {name: {m for m in imported_modules(path) if m in modules and m != name}
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
    found = [line for path in sorted(PACKAGE.rglob("*.py")) for line in reexports(path)]
    assert found == []
