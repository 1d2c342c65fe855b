"""The README: short, every Python example runs as pasted on its own, every link resolves, its results table is
the one the result folders give.

Each ```python block of the README and of ``docs/*.md`` runs alone in a fresh interpreter (its own imports,
nothing from the block before it), so a reader can paste any one of them. The long notes live in ``docs/``; every
relative link or image of the README and of ``docs/*.md`` must name a file that exists. The results table is
what ``pixelmpc report --readme`` builds from ``experiments/results/`` (:mod:`experiments.reporting.readme_table`).
"""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
EXAMPLE_TIMEOUT_S = 300
FENCE = re.compile(r"^```[^\n]*\n.*?^```", re.S | re.M)
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)[^)]*\)")  # [text](target) and ![alt](target)


def _markdown_files() -> list[Path]:
    return [README, *sorted((ROOT / "docs").glob("*.md"))]


def _python_blocks(paths=None) -> list[tuple[str, str]]:
    """("file:line", code) of every ```python block of the README and the docs (or of ``paths``)."""
    blocks = []
    for path in paths or _markdown_files():
        text = path.read_text()
        blocks += [(f"{path.relative_to(ROOT).as_posix()}:{text.count(chr(10), 0, match.start()) + 1}", match.group(1))
                   for match in PYTHON_BLOCK.finditer(text)]
    return blocks


def _relative_links(path: Path) -> list[str]:
    """The link and image targets of a Markdown file outside its code blocks, less web addresses and anchors."""
    text = FENCE.sub("", path.read_text())
    targets = [target.split("#")[0] for target in LINK.findall(text)]
    return [t for t in targets if t and not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def test_the_readme_and_the_docs_have_python_examples():
    readme = _python_blocks([README])
    assert readme, "the README shows no library example"
    assert any("jax.vmap(ctrl.step)" in code and "jax.jit(" in code for _, code in readme), (
        "the README's example no longer composes the pure MPPI step in the user's own jit and vmap")
    assert len(_python_blocks()) >= 3


# An example that flies a whole lap of a preset (a minute or more of compiling and flying on two cores) runs with the
# slow checks (--runslow, which CI runs); every other example runs in the default run, in well under a minute.
SLOW_EXAMPLE = re.compile(r"\brace\(preset\(")


def _example_params() -> list:
    return [pytest.param(where, code, id=where, marks=[pytest.mark.slow] if SLOW_EXAMPLE.search(code) else [])
            for where, code in _python_blocks()]


@pytest.mark.parametrize("where, code", _example_params())
def test_python_example_runs_alone(tmp_path, where, code):
    if re.search(r"^u0, ", code, re.M):  # an example that steps a controller must give a finite control vector
        code += "\nimport numpy\nassert numpy.isfinite(numpy.asarray(u0)).all() and numpy.ndim(u0) == 1, u0\n"
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=EXAMPLE_TIMEOUT_S)
    assert done.returncode == 0, (f"the ```python block at {where} failed when run alone "
                                  f"(exit {done.returncode}):\n{done.stderr[-4000:]}")


PUBLIC_IMPORT = re.compile(r"^from pixelmpc_jax import ", re.M)
INTERNAL_IMPORT = re.compile(r"^\s*(from|import) pixelmpc_jax\.", re.M)


def _page_blocks(name: str) -> list[str]:
    return [code for _, code in _python_blocks([ROOT / "docs" / name])]


def test_the_library_examples_use_the_public_surface_and_stay_short():
    """The README's library example, the closed-loop page and the user's own robot import from the package's top
    only; a race from Python is at most 10 lines of user code, the user's unicycle at most 30."""
    readme = _python_blocks([README])[0][1]
    closed_loop, unicycle = _page_blocks("closed_loop.md"), _page_blocks("unicycle.md")
    assert len(closed_loop) == 2 and len(unicycle) == 1
    assert any("race(preset(\"best\")" in code for code in closed_loop)
    assert any("course_from_gates(" in code and 'fly("mppi"' in code for code in closed_loop)
    for code in [readme, *closed_loop, *unicycle]:
        assert PUBLIC_IMPORT.search(code) and not INTERNAL_IMPORT.search(code), code[:200]
    assert all(len(code.splitlines()) <= 10 for code in closed_loop)
    assert len(unicycle[0].splitlines()) <= 30


def test_the_reference_shows_the_readmes_library_example_itself():
    """docs/index.md takes the README's library example between its section markers (one copy, run above)."""
    readme = README.read_text()
    section = re.search(r"<!-- --8<-- \[start:library\] -->\n(.*?)<!-- --8<-- \[end:library\] -->", readme, re.S)
    assert section and section.group(1).strip() == f"```python\n{_python_blocks([README])[0][1]}```"
    assert '--8<-- "README.md:library"' in (ROOT / "docs" / "index.md").read_text()


def test_the_reference_documents_every_public_name():
    """docs/api.md renders each name of ``pixelmpc_jax.__all__`` (the preset names are in ``preset``'s docstring)."""
    import pixelmpc_jax

    documented = set(re.findall(r"^::: pixelmpc_jax\.(\w+)$", (ROOT / "docs" / "api.md").read_text(), re.M))
    assert documented == set(pixelmpc_jax.__all__) - {"__version__", "PRESETS"}


def test_the_reference_builds_without_a_warning(tmp_path):
    """``mkdocs build --strict`` (the docs extra; CI installs it and builds the reference so too)."""
    pytest.importorskip("mkdocstrings")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=EXAMPLE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-4000:]


def test_the_readme_is_short():
    assert len(README.read_text().splitlines()) <= 150


def test_the_readme_results_table_is_what_the_result_folders_give():
    """``pixelmpc report --readme --check`` passes: the table between the markers is :func:`readme_table.table` of
    the committed folders the results index lists, and docs/results.md's list of folders is the index's (run
    ``pixelmpc report --readme`` after a result or the index changes)."""
    from experiments.reporting import index, readme_table

    old, new = readme_table.rewrite_readme(ROOT, check=True)
    assert old == new, "README.md's results table is stale: run `pixelmpc report --readme`"
    old, new = index.rewrite_results_doc(ROOT, check=True)
    assert old == new, "docs/results.md's list of folders is stale: run `pixelmpc report --readme`"


def test_the_docs_the_readme_links_to_exist():
    linked = [t for t in _relative_links(README) if t.startswith("docs/")]
    assert linked, "the README links to no docs/ file"
    assert not [t for t in linked if not (ROOT / t).is_file()]
    orphans = {p.name for p in (ROOT / "docs").glob("*.md")} - {Path(t).name for t in linked}
    assert not orphans, f"docs/ files the README does not link to: {sorted(orphans)}"


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_and_images_resolve(path):
    missing = [t for t in _relative_links(path) if not (path.parent / t).exists()]
    assert not missing, f"{path.relative_to(ROOT)} links to files that do not exist: {missing}"


def test_the_scan_finds_links_and_images_and_skips_code(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("See [a](docs/a.md#part) and ![b](../b.png), not [web](https://x.org) or [top](#top).\n"
                    "```python\nx = [1](2)\n```\n")
    assert _relative_links(page) == ["docs/a.md", "../b.png"]


SESSION_DATE = re.compile(r"\bsessions?\b", re.I)


def test_no_figure_is_dated_by_a_work_session():
    """A figure carries its device and date, never "session 2" or "this session"."""
    pages = [*_markdown_files(), *sorted(ROOT.glob("benchmarks/results/*/README.md")),
             *sorted(ROOT.glob("experiments/results/*/README.md"))]
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in pages
             for n, line in enumerate(p.read_text().splitlines(), 1) if SESSION_DATE.search(line)]
    assert not found, "\n".join(found)


# Output names that docstrings use as placeholders for a folder the user picks.
OUTPUT_FOLDERS = {"out", "out_dir", "OUT", "DIR"}
# Stale references kept visible here until they are fixed (none now).
KNOWN_STALE: set = set()


def _docstring_file_references():
    """(file, name) for every project file a docstring names: a path with a folder, a bare ``.py`` name,
    or a bare upper-case ``.md`` document (not the ``REPORT.md`` the experiments write)."""
    import ast

    root = Path(__file__).resolve().parent.parent
    token = re.compile(r"[\w./-]+\.(?:py|md|json|msgpack|npz|toml)\b")
    for folder in ("pixelmpc_jax", "experiments", "benchmarks"):
        for path in sorted((root / folder).rglob("*.py")):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                for name in token.findall(ast.get_docstring(node) or ""):
                    if "/" in name and name.split("/")[0] not in OUTPUT_FOLDERS:
                        yield path.relative_to(root).as_posix(), name
                    elif "/" not in name and (name.endswith(".py") or re.fullmatch(r"[A-Z_]+\.md", name)
                                              and name != "REPORT.md"):
                        yield path.relative_to(root).as_posix(), name


def test_the_files_docstrings_name_exist():
    root = Path(__file__).resolve().parent.parent
    tracked = {p.name for folder in ("pixelmpc_jax", "experiments", "benchmarks", "tests")
               for p in (root / folder).rglob("*.py")}
    missing = []
    for where, name in _docstring_file_references():
        if "/" in name:
            found = (root / name).exists() or (root / "pixelmpc_jax" / name).exists()
        else:
            found = name in tracked or (root / name).exists()
        if not found and (where, name) not in KNOWN_STALE:
            missing.append(f"{where}: {name}")
    assert not missing, "docstrings name files that do not exist:\n" + "\n".join(missing)
