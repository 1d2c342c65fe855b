"""The pixelmpc command: help, version, the demo, and clear errors for bad arguments."""

import json

import pytest

from pixelmpc_jax import cli


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "version" in out and "demo" in out


def test_version(capsys):
    from pixelmpc_jax import __version__

    assert cli.main(["version"]) == 0
    assert __version__ in capsys.readouterr().out


def test_demo_reaches_the_waypoint_and_writes_results(tmp_path, capsys):
    code = cli.main(["demo", "--seconds", "3", "--samples", "256", "--out", str(tmp_path)])
    assert code == 0
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["final_error_m"] < 0.3
    assert (tmp_path / "demo.png").stat().st_size > 1000


def test_unwritable_output_directory_is_rejected_before_running(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(SystemExit) as exc:
        cli.main(["demo", "--out", str(blocker / "sub")])
    assert exc.value.code == 2
    assert "cannot be written" in capsys.readouterr().err
