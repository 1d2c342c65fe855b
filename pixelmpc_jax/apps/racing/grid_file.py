"""Experiments as grid files: a TOML file that names an experiment and its settings, read and checked whole before
anything flies (``pixelmpc experiment run GRID``).

A grid file is one of two kinds. A named experiment::

    experiment = "frontier"        # table2, table4, robustness, fault-curves, frontier, margin-probe, speed-probe
    out = "experiments/results/frontier"
    laps = 10                      # the experiment's own options, by their command-line names
    speeds = [6, 7, 8, 8.5]        # (``--frontier-speeds`` is ``frontier_speeds``; a list for several values)

or explicit cells, each a race (:class:`~pixelmpc_jax.apps.racing.spec.RaceSpec`) set by dotted paths as
:meth:`RaceSpec.with_fields <pixelmpc_jax.apps.racing.spec.RaceSpec.with_fields>` reads them::

    experiment = "cells"
    out = "runs/temperature"
    laps = 4
    seed = 0

    [base]                         # every cell's settings
    controller = "pixelmpc"
    speed = 8.0
    "config.mppi.num_samples" = 512

    [[cell]]                       # one cell: its name and its settings over the base
    name = "cold"
    "config.mppi.temperature" = 0.5

    [product]                      # or: the cells of every combination of these lists (named by their values)
    "config.mppi.temperature" = [0.5, 1.0]
    speed = [8.0, 9.0]

A dotted key may also be written unquoted (TOML nests it: ``config.mppi.temperature = 0.5``); both read the same.
:func:`read_grid_file` checks the whole file, every cell's race built, and refuses anything it does not know with a
one-line ValueError naming the file and the key. A named experiment's options are checked against that experiment's
command (:mod:`pixelmpc_jax.commands.experiment`), the same checks as its flags.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same reader as a package (a dependency there)
    import tomli as tomllib

from pixelmpc_jax.apps.racing.grid import Cell
from pixelmpc_jax.apps.racing.spec import RaceSpec

EXPERIMENTS = ("table2", "table4", "robustness", "fault-curves", "frontier", "margin-probe", "speed-probe")
CELLS = "cells"  # the experiment of explicit cells
CELLS_KEYS = ("experiment", "out", "laps", "seed", "base", "cell", "product")  # what a file of cells may hold
CELL_NAME_MAX = 120  # characters: a cell's name names its files


@dataclasses.dataclass(frozen=True)
class GridFile:
    """A grid file, read and checked (:func:`read_grid_file`).

    Attributes:
        path: the file.
        experiment: one of :data:`EXPERIMENTS`, or :data:`CELLS`.
        options: a named experiment's options, ``{option name: value}`` as the file writes them (empty for cells).
        cells: the cells of an experiment of cells, in the file's order (empty for a named experiment).
        out: the output folder the file names (None: none named).
        laps: laps per cell of an experiment of cells.
        seed: the first lap's seed of an experiment of cells.
    """

    path: Path
    experiment: str
    options: dict = dataclasses.field(default_factory=dict)
    cells: tuple[Cell, ...] = ()
    out: Path | None = None
    laps: int = 1
    seed: int = 0


def read_grid_file(path) -> GridFile:
    """Read the grid file at ``path`` and check all of it (see the module); a ValueError names the first problem."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"no grid file at {str(path)!r}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"grid file {path} cannot be read: {err}") from None
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"grid file {path} is not TOML: {err}") from None
    try:
        return _grid(path, data)
    except ValueError as err:
        raise ValueError(f"grid file {path}: {err}") from None


def _grid(path: Path, data: dict) -> GridFile:
    experiment = data.get("experiment")
    if experiment is None:
        raise ValueError(f"it names no experiment: add experiment = one of {', '.join((*EXPERIMENTS, CELLS))}")
    if experiment not in (*EXPERIMENTS, CELLS):
        raise ValueError(f"unknown experiment {experiment!r}; choose one of {', '.join((*EXPERIMENTS, CELLS))}")
    out = data.get("out")
    if out is not None and not isinstance(out, str):
        raise ValueError(f"out must be a folder's path (a string), got {out!r}")
    out = None if out is None else Path(out)
    if experiment != CELLS:
        options = {k: v for k, v in data.items() if k != "experiment"}
        for key, value in options.items():
            if isinstance(value, dict):
                raise ValueError(f"{experiment} takes options, not tables: [{key}] is for experiment = \"cells\"")
        return GridFile(path, experiment, options=options, out=out)
    unknown = sorted(set(data) - set(CELLS_KEYS))
    if unknown:
        raise ValueError(f"unknown key {unknown[0]!r}; a grid of cells takes {', '.join(CELLS_KEYS)}")
    laps, seed = data.get("laps", 1), data.get("seed", 0)
    for name, value, lo in (("laps", laps, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ValueError(f"{name} must be an integer of at least {lo}, got {value!r}")
    return GridFile(path, CELLS, cells=tuple(_cells(data)), out=out, laps=laps, seed=seed)


def _cells(data: dict) -> list[Cell]:
    """The cells of a grid of cells: ``[[cell]]`` tables, or the ``[product]`` of lists, over the ``[base]``."""
    base = dotted(_table(data, "base"), "base")
    if ("cell" in data) == ("product" in data):
        raise ValueError("a grid of cells takes either [[cell]] tables or a [product] table (one of them)")
    if "cell" in data:
        tables = data["cell"]
        if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
            raise ValueError("cell must be a list of tables: write each as [[cell]]")
        named = []
        for index, table in enumerate(tables):
            settings = dotted(table, f"cell {index + 1}")
            name = settings.pop("name", None)
            if not isinstance(name, str) or not name:
                raise ValueError(f"cell {index + 1} has no name: add name = \"...\"")
            named.append((name, settings))
    else:
        named = _product(dotted(_table(data, "product"), "product"))
    cells = [_cell(name, base, settings) for name, settings in named]
    names = [cell.name for cell in cells]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"cell names repeat: {', '.join(repeated)}")
    return cells


def _table(data: dict, key: str) -> dict:
    table = data.get(key, {})
    if not isinstance(table, dict):
        raise ValueError(f"{key} must be a table: write it as [{key}]")
    return table


def dotted(table: dict, where: str, prefix: str = "") -> dict:
    """``{dotted path: value}`` of a TOML table of settings, nested tables (TOML's unquoted dotted keys) flattened
    into their paths: ``{"config": {"mppi": {"temperature": 1}}}`` -> ``{"config.mppi.temperature": 1}``. A path
    written twice (quoted and nested) is a ValueError naming it."""
    flat: dict = {}
    for key, value in table.items():
        path = f"{prefix}{key}"
        items = dotted(value, where, f"{path}.") if isinstance(value, dict) else {path: value}
        for item_path, item in items.items():
            if item_path in flat:
                raise ValueError(f"{where} sets {item_path} twice")
            flat[item_path] = item
    return flat


def _product(lists: dict) -> list[tuple[str, dict]]:
    """``(name, settings)`` of every combination of the ``[product]`` lists, in order, the last list varying
    fastest; each named by its values (``speed8_temperature0.5``, a path by its last part)."""
    if not lists:
        raise ValueError("[product] is empty: give each setting a list of values")
    for path, values in lists.items():
        if not isinstance(values, list) or not values:
            raise ValueError(f"[product] {path} must be a list of values, got {values!r}")
    paths = list(lists)
    combos = []
    for values in itertools.product(*(lists[p] for p in paths)):
        name = "_".join(f"{p.rsplit('.', 1)[-1]}{_value_name(v)}" for p, v in zip(paths, values))
        combos.append((name, dict(zip(paths, values))))
    return combos


def _value_name(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _cell(name: str, base: dict, settings: dict) -> Cell:
    """The cell ``name`` flying ``base`` with ``settings`` over it; a ValueError names a setting the race refuses."""
    if len(name) > CELL_NAME_MAX or "/" in name or name.strip() != name:
        raise ValueError(f"cell name {name!r} must be at most {CELL_NAME_MAX} characters, without '/' or edge spaces")
    fields = {**base, **settings}
    try:
        spec = RaceSpec().with_fields(fields)
    except (KeyError, TypeError):  # a path through a setting that is not a table of settings
        bad = next(path for path in fields if not _reaches(path))
        raise ValueError(f"cell {name!r}: unknown setting {bad}") from None
    except ValueError as err:
        raise ValueError(f"cell {name!r}: {err}") from None
    return Cell(name, spec)


def _reaches(path: str) -> bool:
    """Whether ``path``'s parents are tables of a race's record (its last part is checked by the race itself)."""
    node = RaceSpec().record()
    for part in path.split(".")[:-1]:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return isinstance(node, dict)
