"""The commands (``pixelmpc_jax/commands/``, one module each) and the jobs of ``pixelmpc experiment``, ``pixelmpc
bench`` and ``pixelmpc tune``: one parser lists every job, each argument is checked as parsed, each job calls its
library function, and every script in ``experiments/`` and ``benchmarks/`` is a thin call of one of them."""

import argparse
import ast
import dataclasses
import re
from pathlib import Path

import pytest

from pixelmpc_jax import cli
from pixelmpc_jax.apps.racing import presets
from pixelmpc_jax.commands import EXIT_USAGE

ROOT = Path(__file__).resolve().parent.parent
JOBS = {"experiment": ("table2", "table4", "robustness", "fault-curves", "frontier", "margin-probe", "speed-probe",
                       "lap-picture"),
        "bench": ("suite", "device", "mppi-step", "closed-loop", "pf-step", "eskf-step", "render")}


def test_the_help_lists_every_job(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    unwrapped = re.sub(r"-\n\s+", "-", text)  # argparse wraps a long help after a hyphen
    for command in ("race", "tune", "reproduce", "course", "demo", "render", "collect", "train", "evaluate", "report",
                    *JOBS):
        assert f"    {command} " in text
    for jobs in JOBS.values():
        for job in jobs:
            assert job in unwrapped


def test_each_command_lives_in_its_own_module_and_the_cli_defines_none():
    parser = cli.build_parser()
    names = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert len(names) == 13
    assert [add.__module__ for add in cli.COMMANDS] == [f"pixelmpc_jax.commands.{name}" for name in names]
    tree = ast.parse(Path(cli.__file__).read_text())
    defined = [node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
               and node.attr in ("add_parser", "set_defaults")]
    assert defined == [], "cli.py adds a command of its own"


def _script_argv(path: Path) -> list[str]:
    """The fixed arguments a thin script hands to ``cli.main`` (its only call of it)."""
    calls = [node for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.Call)
             and getattr(node.func, "id", None) == "main"]
    assert len(calls) == 1, f"{path.name} should call pixelmpc_jax.cli.main once"
    return [elt.value for elt in calls[0].args[0].elts if isinstance(elt, ast.Constant)]


@pytest.mark.parametrize("path", sorted([*ROOT.glob("experiments/*.py"), *ROOT.glob("benchmarks/*.py")]),
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_script_is_a_thin_call_of_a_job(path, capsys):
    tree = ast.parse(path.read_text())
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
                for alias in node.names}
    assert imported <= {"sys", "main"}, f"{path.name} imports {imported}: a script only calls the command"
    command, job = _script_argv(path)
    assert job in JOBS[command]
    with pytest.raises(SystemExit) as done:
        cli.main([command, job, "--help"])
    assert done.value.code == 0 and f"pixelmpc {command} {job}" in capsys.readouterr().out


def test_the_robustness_script_names_every_set_of_levers():
    from pixelmpc_jax.apps.experiments.robustness import LEVER_SETS

    doc = ast.get_docstring(ast.parse((ROOT / "experiments" / "robustness.py").read_text()))
    line = next(line for line in doc.splitlines() if line.startswith("--levers:"))
    assert re.findall(r"[a-z-]+", line.partition(":")[2].partition("(")[0]) == list(LEVER_SETS)


@pytest.mark.parametrize("argv", [
    ["experiment"], ["bench"], ["experiment", "table2", "--laps", "0"], ["experiment", "table4", "--seed", "-1"],
    ["experiment", "robustness", "--levers", "wings"], ["experiment", "robustness", "--reuse", "{tmp}/nothing"],
    ["experiment", "robustness", "--estimators", "ekf"], ["experiment", "fault-curves", "--levers", "filter"],
    ["experiment", "fault-curves", "--estimators", "truth"],
    ["experiment", "frontier", "--out", "{tmp}/out", "--speeds", "8", "60"],
    ["experiment", "frontier", "--out", "{tmp}/out", "--speeds", "6:60:0.25"], ["experiment", "lap-picture", "{tmp}"],
    ["experiment", "margin-probe", "--out", "{tmp}/out", "--frontier", "{tmp}/nothing"],
    ["experiment", "speed-probe", "--t-f", "3"], ["experiment", "speed-probe", "--c-pixel", "0"],
    ["experiment", "speed-probe", "--dof-weights", "{tmp}/none.msgpack"], ["bench", "suite", "--quick", "--smoke"],
    ["bench", "mppi-step", "--samples", "0"], ["bench", "closed-loop", "--mode", "slow"],
    ["bench", "pf-step", "--repeats", "-2"], ["bench", "eskf-step", "--repeats", "0"],
    ["bench", "render", "--supersample", "2"],
    ["tune", "--space", "hand-tuned", "--out", "{tmp}/out", "--nominal-speeds", "8", "nan"],
    ["tune", "--space", "best", "--out", "{tmp}/out"],
])
def test_bad_arguments_exit_2_with_one_line_before_anything_is_written(tmp_path, argv, capsys):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    with pytest.raises(SystemExit) as done:
        cli.main(argv)
    err = capsys.readouterr().err
    assert done.value.code == EXIT_USAGE and "error:" in err and len(err.strip().splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


def test_each_job_calls_its_library_function_with_the_checked_arguments(tmp_path, monkeypatch, capsys):
    from pixelmpc_jax.apps.bench import mppi_step, suite
    from pixelmpc_jax.apps.experiments import estimation, frontier, paper, speed_probe

    seen = {}

    def visibility_experiment(out, **kwargs):
        seen["table2"] = kwargs
        (out / "REPORT.md").write_text("# the tables\n")

    monkeypatch.setattr(paper, "visibility_experiment", visibility_experiment)
    out = tmp_path / "tables"
    assert cli.main(["experiment", "table2", "--out", str(out), "--laps", "3", "--pixel-model", "projection"]) == 0
    assert seen["table2"] == {"laps": 3, "pixel_model": "projection", "quick": False, "seed": 200, "main": False,
                              "frontier_speeds": ()}
    assert "# the tables" in capsys.readouterr().out
    def estimation_experiment(out, **kwargs):
        seen["table4"] = kwargs
        (out / "REPORT.md").write_text("# Table IV\n")

    monkeypatch.setattr(estimation, "estimation_experiment", estimation_experiment)
    joined = [tmp_path / name for name in ("pf", "eskf")]
    for folder in joined:
        folder.mkdir()
        (folder / "results.json").write_text("{}")
    assert cli.main(["experiment", "table4", "--out", str(tmp_path / "t4"), "--quick", "--no-straight", "--estimators",
                     "eskf", "--reuse", *map(str, joined)]) == 0
    assert seen["table4"] == {"laps": 25, "quick": True, "straight": False, "seed": 200, "estimators": ("eskf",),
                              "reuse": tuple(joined), "who": ("mppi", "paper", "best"), "at_labels": True,
                              "labels": (14.0, 16.0)}
    assert cli.main(["experiment", "table4", "--out", str(tmp_path / "t4"), "--controllers", "best", "mppi"]) == 0
    assert seen["table4"]["who"] == ("best", "mppi")
    assert cli.main(["experiment", "table4", "--out", str(tmp_path / "t4"), "--estimators", "onboard",
                     "--paces-only", "--labels", "14"]) == 0
    assert seen["table4"]["estimators"] == ("onboard",) and seen["table4"]["at_labels"] is False
    assert seen["table4"]["labels"] == (14.0,)
    speeds = ["--frontier-speeds", "9", "7:8:0.5", "8"]
    assert cli.main(["experiment", "table2", "--out", str(out), "--main", *speeds]) == 0
    assert seen["table2"]["main"] and seen["table2"]["frontier_speeds"] == (7.0, 7.5, 8.0, 9.0)

    def run_frontier(speeds, cells, out, laps, seed, course=None, camera_tilt_deg=None, reuse=(), loop=None):
        seen["frontier"] = (speeds, [cell.spec.config.pixel_cost for cell in cells], laps, seed, course, reuse)
        seen["frontier_loop"] = loop
        seen["frontier_tilt"] = camera_tilt_deg
        seen["frontier_cells"] = cells
        (out / "REPORT.md").write_text("frontier\n")

    monkeypatch.setattr(frontier, "run_frontier", run_frontier)
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path / "f"), "--cells", "border", "--speeds", "9",
                     "7", "9", "--course", "straight"]) == 0
    assert seen["frontier"] == ((7.0, 9.0), ["border", "border"], 10, 0, "straight", ())
    assert seen["frontier_loop"] is None
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path / "f"), "--cells", "border", "--loop",
                     "onboard"]) == 0
    assert seen["frontier_loop"] == "onboard"
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path / "f"), "--cells", "none", "--speeds",
                     "8:8.5:0.25"]) == 0
    assert seen["frontier"][:2] == ((8.0, 8.25, 8.5), []) and seen["frontier_cells"] == ()
    assert seen["frontier_tilt"] is None
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path / "f"), "--cells", "none", "--camera-tilt",
                     "30"]) == 0
    assert seen["frontier_tilt"] == 30.0
    # --cells preset: the best preset and the exact projection flying every other setting of it
    grid_folder = tmp_path / "validation"
    grid_folder.mkdir()
    (grid_folder / "results.json").write_text("{}")
    assert cli.main(["experiment", "frontier", "--out", str(tmp_path / "g"), "--cells", "preset", "--speeds", "7",
                     "10", "--seed", "500", "--reuse", str(grid_folder)]) == 0
    best, exact = seen["frontier_cells"]
    assert best.spec == presets.preset("best")
    assert exact.spec.config.pixel_model == "projection" and best.spec.config.pixel_model == "vdof"
    # every other setting the preset's; the projection predicts the next gate's pixel as it predicts the target's
    assert dataclasses.replace(exact.spec.config, pixel_model="vdof", box_size_limit=best.spec.config.box_size_limit,
                               look_ahead_model=best.spec.config.look_ahead_model) == best.spec.config
    assert seen["frontier"][3:] == (500, None, (grid_folder,))
    with pytest.raises(SystemExit) as refused:
        cli.main(["experiment", "frontier", "--out", str(tmp_path / "h"), "--reuse", str(tmp_path)])
    assert refused.value.code == 2 and "no grid at" in capsys.readouterr().err

    def probe(out, **kwargs):
        seen["probe"] = kwargs
        (out / "REPORT.md").write_text("probe\n")

    monkeypatch.setattr(speed_probe, "speed_probe", probe)
    assert cli.main(["experiment", "speed-probe", "--out", str(tmp_path / "p"), "--c-pixel", "9e6", "3e7"]) == 0
    assert seen["probe"]["c_pixels"] == (9e6, 3e7) and seen["probe"]["speed"] == 8.0

    monkeypatch.setattr(mppi_step, "run_mppi_step", lambda *args: seen.update(mppi_step=args))
    assert cli.main(["bench", "mppi-step", "--samples", "64", "--cost", "waypoint"]) == 0
    assert seen["mppi_step"] == (64, 80, 50, "waypoint")
    monkeypatch.setattr(suite, "run_bench", lambda out, quick, smoke: seen.update(suite=(out, quick, smoke)))
    assert cli.main(["bench", "suite", "--smoke", "--out", str(tmp_path / "bench")]) == 0
    assert seen["suite"] == (tmp_path / "bench", False, True) and (tmp_path / "bench").is_dir()
