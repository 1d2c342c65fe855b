"""Grid cells on an executor and experiments as grid files: the file read and checked whole before anything flies,
each experiment's grid file the same run as its command's defaults, a failed cell named while the others are
written, a run interrupted and resumed, and (``--runslow``) a tiny frontier on a local Dask cluster giving the laps
of the in-process run."""

import math
from pathlib import Path

import numpy as np
import pytest
import standard_race

from pixelmpc_jax import cli
from pixelmpc_jax.apps.experiments import frontier as F
from pixelmpc_jax.apps.racing import executor as ex
from pixelmpc_jax.apps.racing import grid, race
from pixelmpc_jax.apps.racing.grid_file import read_grid_file
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.sim.metrics import MEASURE

GRIDS = Path(__file__).resolve().parents[1] / "experiments" / "grids"
COMMANDS = {"frontier.toml": "frontier", "table2.toml": "table2", "table4.toml": "table4",
            "robustness.toml": "robustness", "fault_curves.toml": "fault-curves", "margin_probe.toml": "margin-probe",
            "speed_probe.toml": "speed-probe"}


def _write(tmp_path, text: str) -> Path:
    path = tmp_path / "grid.toml"
    path.write_text(text)
    return path


def _checked(path, *flags):
    """``pixelmpc experiment run PATH`` parsed and its grid file checked (nothing flies)."""
    args = cli.build_parser().parse_args(["experiment", "run", str(path), *flags])
    args.precheck(args)
    return args


def _command_args(name: str, out):
    args = cli.build_parser().parse_args(["experiment", name, "--out", str(out)])
    return args


def _normal(value):
    """A parsed option with lists as tuples (a file writes a list where a flag's default is a tuple)."""
    if isinstance(value, (list, tuple)):
        return tuple(_normal(v) for v in value)
    return value


@pytest.mark.parametrize("file", sorted(COMMANDS))
def test_each_experiments_grid_file_is_its_commands_default_run(file):
    """experiments/grids/NAME.toml parses to the options of `pixelmpc experiment NAME --out OUT` (the frontier's
    speeds and laps written out: the values its defaults stand for)."""
    checked = _checked(GRIDS / file).grid_args
    default = _command_args(COMMANDS[file], checked.out)
    differ = {key for key in vars(checked) if key not in ("func", "validate", "precheck")
              and _normal(getattr(default, key)) != _normal(getattr(checked, key))}
    if COMMANDS[file] == "frontier":
        assert F.default_spec().laps == checked.laps and F.default_spec().cells
        assert tuple(sorted({v for vs in checked.speeds for v in vs})) == F.DEFAULT_SPEEDS
        differ -= {"laps", "speeds"}
    if COMMANDS[file] == "robustness":
        assert default.estimators is None  # "all", as the file leaves it
    assert differ == set(), file


def test_a_grid_of_cells_reads_base_cells_and_nested_or_quoted_paths(tmp_path):
    grid_file = read_grid_file(_write(tmp_path, """
experiment = "cells"
out = "runs/x"
laps = 2
seed = 7
[base]
controller = "pixelmpc"
config.mppi.num_samples = 256
[[cell]]
name = "cold"
"config.mppi.temperature" = 0.5
[[cell]]
name = "fast"
speed = 9.0
"""))
    assert [c.name for c in grid_file.cells] == ["cold", "fast"] and (grid_file.laps, grid_file.seed) == (2, 7)
    cold, fast = (c.spec for c in grid_file.cells)
    assert cold.controller == fast.controller == "pixelmpc"
    assert cold.config.mppi.num_samples == fast.config.mppi.num_samples == 256
    assert cold.config.mppi.temperature == 0.5 and fast.config.mppi.temperature == RaceSpec().config.mppi.temperature
    assert fast.speed == 9.0 and cold.speed == RaceSpec().speed


def test_a_product_makes_every_combination_named_by_its_values(tmp_path):
    cells = read_grid_file(_write(tmp_path, """
experiment = "cells"
out = "runs/x"
[product]
speed = [8.0, 9.5]
"config.mppi.temperature" = [0.5, 1.0]
""")).cells
    assert [c.name for c in cells] == ["speed8_temperature0.5", "speed8_temperature1", "speed9.5_temperature0.5",
                                       "speed9.5_temperature1"]
    assert [(c.spec.speed, c.spec.config.mppi.temperature) for c in cells] == [(8.0, 0.5), (8.0, 1.0), (9.5, 0.5),
                                                                               (9.5, 1.0)]


@pytest.mark.parametrize("text, message", [
    ('experiment = "fronteer"', "unknown experiment 'fronteer'"),
    ('laps = 3', "names no experiment"),
    ('experiment = "cells"\nout = "x"\nlapz = 3\n[[cell]]\nname = "a"', "unknown key 'lapz'"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\n"config.mppi.temprature" = 1.0',
     "unknown setting config.mppi.temprature"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\n"confg.mppi.temperature" = 1.0',
     "unknown setting confg.mppi.temperature"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\nspeed = -1.0', "speed must be a "),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\nseed = 3', "sets seed"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nspeed = 8.0', "cell 1 has no name"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\n[[cell]]\nname = "a"', "cell names repeat: a"),
    ('experiment = "cells"\nout = "x"\n[[cell]]\nname = "a"\n[product]\nspeed = [8.0]', "either [[cell]]"),
    ('experiment = "cells"\nout = "x"\n[product]\nspeed = 8.0', "[product] speed must be a list"),
    ('experiment = "cells"\nout = "x"\nlaps = 0\n[[cell]]\nname = "a"', "laps must be an integer of at least 1"),
    ('experiment = "frontier"\nout = "x"\nlapz = 3', "unknown key 'lapz' for experiment frontier"),
    ('experiment = "frontier"\nout = "x"\nlaps = 0', "laps"),
    ('experiment = "frontier"\nout = "x"\nspeeds = [8.0]', "speeds: needs at least 2 different speeds"),
    ('experiment = "frontier"\nout = "x"\nquick = 1', "quick is a switch"),
    ('experiment = "frontier"\nout = "x"\nworkers = 2', "give --workers on the command line"),
    ('experiment = "frontier"\nout = "x"\ncells = "some"', "cells"),
    ('experiment = "frontier"\nlaps = 2', "required: out"),
    ('experiment = "cells"\n[[cell]]\nname = "a"', "names no output folder"),
    ('experiment = [', "is not TOML"),
])
def test_a_bad_grid_file_is_refused_whole_in_one_line(tmp_path, text, message):
    with pytest.raises(ValueError) as err:
        _checked(_write(tmp_path, text))
    assert message in str(err.value) and "grid file" in str(err.value) and "\n" not in str(err.value)


def test_the_command_names_a_bad_grid_file_in_one_line_and_flies_nothing(tmp_path, capsys):
    path = _write(tmp_path, 'experiment = "cells"\nout = "%s"\n[[cell]]\nname = "a"\n"config.mppi.temprature" = 1.0'
                  % (tmp_path / "out"))
    assert cli.main(["experiment", "run", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pixelmpc: error: grid file") and "config.mppi.temprature" in err and "\n" not in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as exit_:  # a file that is not there is refused as the argument is parsed
        cli.main(["experiment", "run", str(tmp_path / "missing.toml")])
    assert exit_.value.code == 2 and "no grid file" in capsys.readouterr().err


@pytest.mark.parametrize("engine, workers, message", [
    ("ray://x:1", None, "unknown executor"), ("dask-local:0", None, "positive number of workers"),
    ("dask://host", None, "dask://HOST:PORT"), ("dask-local:2", 3, "--workers is for the local pool")])
def test_a_malformed_executor_is_refused(engine, workers, message):
    with pytest.raises(ValueError, match=message):
        ex.make_executor(engine, workers)


def test_a_dask_engine_without_dask_installed_names_the_extra(monkeypatch, capsys):
    import importlib.util
    import sys

    grid = str(Path(__file__).resolve().parent.parent / "experiments" / "grids" / "frontier.toml")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: None)
    parser = cli.build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["experiment", "run", grid, "--executor", "dask-local:2"])
    assert "pixelmpc-jax[cluster]" in capsys.readouterr().err
    assert parser.parse_args(["experiment", "run", grid, "--executor", "local"]).executor == "local"  # needs nothing
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    with pytest.raises(ImportError, match=r"pixelmpc-jax\[cluster\]"):
        ex.make_executor("dask-local:2")


def test_one_local_worker_flies_in_process_and_the_default_is_one_per_core():
    assert isinstance(ex.make_executor("local", 1), ex.InProcess)
    default = ex.make_executor()
    cores = len(ex.usable_cpus())
    assert isinstance(default, ex.InProcess) if cores == 1 else default.workers == cores


def test_the_local_pool_yields_each_outcome_and_a_failure_as_one_line():
    """Two spawned, pinned workers: every task's result comes back, a task that raises comes back as its error."""
    with ex.LocalPool(2) as pool:
        done = {c.task: (c.result, c.error) for c in pool.run(math.sqrt, [4.0, -1.0, 9.0])}
    assert done[4.0] == (2.0, None) and done[9.0] == (3.0, None)
    assert done[-1.0] == (None, "ValueError: math domain error")


@pytest.fixture
def fake_laps(monkeypatch):
    """race.run_laps replaced by a fake that fails the cells named in ``fail`` and is interrupted in those of
    ``interrupt``; ``flown`` lists the cells it flew (by target speed)."""
    state = {"flown": [], "fail": set(), "interrupt": set()}

    def run_laps(spec, batch_size=1, progress=True, dof_params=None):
        state["flown"].append(spec.speed)
        if spec.speed in state["fail"]:
            raise ValueError(f"no lap at {spec.speed:g} m/s\nsecond line")
        laps = [{"success": True, "lap_time_s": 30.0 / spec.speed, "seed": spec.seed + i} for i in range(spec.laps)]
        interrupted = spec.speed in state["interrupt"]
        return {"laps": laps[:0] if interrupted else laps, "aggregate": {"success_rate": 1.0}, "seed": spec.seed,
                "interrupted": interrupted, "trajectories": [np.zeros((2, 10))] * spec.laps, "covariances": [],
                "measure": MEASURE, "ticks": [], "camera": None, "race": spec.record(), "key": spec.key()}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return state


CELLS = [F.nominal_cell(speed) for speed in (6.0, 7.0, 8.0)]


def test_a_failed_cell_is_named_and_the_others_are_written(tmp_path, fake_laps):
    fake_laps["fail"] = {7.0}
    with pytest.raises(RuntimeError) as err:
        grid.run_grid(CELLS, tmp_path, laps=2, progress=False, executor=ex.InProcess())
    assert "1 of 3 cell(s) failed (nominal_7)" in str(err.value)
    assert "ValueError: no lap at 7 m/s second line" in str(err.value)
    results = grid.load_results(tmp_path)
    assert sorted(results) == ["nominal_6", "nominal_8"]
    assert all((tmp_path / f"trajectories_{name}.npz").exists() for name in results)
    assert results["nominal_6"]["laps"][0]["lap_time_s"] == 5.0 and results["nominal_6"]["config"]["speed"] == 6.0
    fake_laps["fail"], fake_laps["flown"] = set(), []
    grid.run_grid(CELLS, tmp_path, laps=2, progress=False, executor=ex.InProcess())
    assert fake_laps["flown"] == [7.0]  # resumed: only the failed cell flies again


def test_without_an_executor_a_failure_stops_the_grid_as_before(tmp_path, fake_laps):
    fake_laps["fail"] = {6.0}
    with pytest.raises(ValueError, match="no lap at 6"):
        grid.run_grid(CELLS, tmp_path, laps=2, progress=False)
    assert fake_laps["flown"] == [6.0]


@pytest.mark.parametrize("executor", [None, ex.InProcess()], ids=["in-process", "executor"])
def test_an_interrupted_grid_keeps_its_finished_cells_and_resumes(tmp_path, fake_laps, executor):
    fake_laps["interrupt"] = {7.0}
    with pytest.raises(KeyboardInterrupt, match="interrupted in cell nominal_7"):
        grid.run_grid(CELLS, tmp_path, laps=2, progress=False, executor=executor)
    assert sorted(grid.load_results(tmp_path)) == ["nominal_6"]
    fake_laps["interrupt"], fake_laps["flown"] = set(), []
    results = grid.run_grid(CELLS, tmp_path, laps=2, progress=False, executor=executor)
    assert fake_laps["flown"] == [7.0, 8.0] and sorted(results) == ["nominal_6", "nominal_7", "nominal_8"]


def test_ctrl_c_in_the_parent_stops_the_pool_and_keeps_the_written_cells(tmp_path, fake_laps):
    """A KeyboardInterrupt while the parent writes a cell (Ctrl-C, SIGTERM under `pixelmpc`) closes the executor,
    keeps what was written and is raised again."""
    closed = []

    class Interrupting(ex.InProcess):
        def close(self):
            closed.append(True)

    calls = {"n": 0}
    write = grid._write_flown

    def write_then_interrupt(*args):
        write(*args)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("signal SIGTERM")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(grid, "_write_flown", write_then_interrupt)
        with pytest.raises(KeyboardInterrupt):
            grid.run_grid(CELLS, tmp_path, laps=2, progress=False, executor=Interrupting())
    assert closed and sorted(grid.load_results(tmp_path)) == ["nominal_6", "nominal_7"]


def test_a_real_tiny_race_flies_on_an_executor_as_in_process(tmp_path):
    """Real laps (tests/standard_race.py's nominal MPPI, a batch of two) through the executor path write what the
    in-process path writes."""
    cell = grid.Cell("nominal_8", standard_race.NOMINAL.replace(speed=8.0))
    laps = standard_race.BATCH
    here = grid.run_grid([cell], tmp_path / "here", laps=laps, progress=False, batch_size=laps)
    on = grid.run_grid([cell], tmp_path / "on", laps=laps, progress=False, batch_size=laps, executor=ex.InProcess())
    assert on[cell.name]["laps"] == here[cell.name]["laps"] and on[cell.name]["config"] == here[cell.name]["config"]
    for folder in ("here", "on"):
        assert {p.name for p in (tmp_path / folder).iterdir()} >= {"results.json", "trajectories_nominal_8.npz",
                                                                   "ticks_nominal_8.npz", "ticks_compact.npz"}
    assert grid.is_current(grid.load_results(tmp_path / "on")[cell.name], cell.race(laps, 0, None))


TINY_GRID = """
experiment = "cells"
laps = 1
seed = 0
[base]
course = "straight"
max_time_s = 3.0
[[cell]]
name = "nominal_8"
speed = 8.0
[[cell]]
name = "nominal_9"
speed = 9.0
[[cell]]
name = "pixelmpc_projection_8"
controller = "pixelmpc"
speed = 8.0
"config.pixel_model" = "projection"
"""


@pytest.mark.slow
def test_a_tiny_grid_on_a_local_dask_cluster_flies_the_laps_of_the_in_process_run(tmp_path):
    """`pixelmpc experiment run GRID --executor dask-local:2` (two nominal speeds and a PixelMPC cell, 3 s of the
    straight course) and the same grid flown in this process (--workers 1): the same cells, the same laps (lap
    times, gates, visibility), and the report of them."""
    pytest.importorskip("distributed")
    path = _write(tmp_path, TINY_GRID)
    assert cli.main(["experiment", "run", str(path), "--out", str(tmp_path / "dask"),
                     "--executor", "dask-local:2"]) == 0
    assert cli.main(["experiment", "run", str(path), "--out", str(tmp_path / "here"), "--workers", "1"]) == 0
    dask, here = (grid.load_results(tmp_path / folder) for folder in ("dask", "here"))
    assert sorted(dask) == sorted(here) == ["nominal_8", "nominal_9", "pixelmpc_projection_8"]
    for name in here:
        assert dask[name]["laps"] == here[name]["laps"], name
        assert dask[name]["config"] == here[name]["config"], name
    assert "| pixelmpc_projection_8 | 1 |" in (tmp_path / "dask" / "REPORT.md").read_text()
