"""``pixelmpc bench device``, the device suite (``pixelmpc_jax/apps/bench/device.py``): its arguments refused before
anything runs, ``device.json`` rewritten after each part so an interrupted run keeps what it finished, and (slow) a
whole run at a tiny size on the CPU: the schema, every figure positive and finite, the plot written."""

import json
import math

import jax
import pytest

from pixelmpc_jax import cli
from pixelmpc_jax.apps.bench import device


@pytest.mark.parametrize("argv", [
    ["--max-samples", "1000"], ["--max-samples", "256"], ["--max-samples", "1536"], ["--max-samples", "2097152"],
    ["--max-samples", "many"], ["--repeats", "0"], ["--laps", "-1"], ["--lap-seconds", "0"],
    ["--lap-seconds", "nan"], ["--lap-seconds", "601"],
])
def test_bad_arguments_exit_2_with_one_line_before_anything_is_written(tmp_path, argv, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as done:
        cli.main(["bench", "device", "--out", str(out), *argv])
    err = capsys.readouterr().err
    assert done.value.code == cli.EXIT_USAGE and "error:" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.parametrize("field, value", [("max_samples", 768), ("max_samples", True), ("repeats", 0),
                                          ("laps", 2.0), ("lap_seconds", float("inf")), ("lap_seconds", 0.0)])
def test_the_config_refuses_what_cannot_run(field, value):
    with pytest.raises(ValueError, match=field):
        device.DeviceSuiteConfig(**{field: value})


def test_the_scaling_doubles_from_512_to_max_samples():
    assert device.DeviceSuiteConfig().samples == (512, 1024, 2048, 4096, 8192, 16384)
    assert device.DeviceSuiteConfig(max_samples=512).samples == (512,)
    assert device.DeviceSuiteConfig(max_samples=2048).samples == (512, 1024, 2048)


def test_the_command_runs_the_suite_with_the_checked_arguments(tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(device, "run_device_suite", lambda out, config: seen.update(run=(out, config)))
    out = tmp_path / "gpu"
    assert cli.main(["bench", "device", "--out", str(out)]) == 0
    assert seen["run"] == (out, device.DeviceSuiteConfig()) and out.is_dir()
    assert cli.main(["bench", "device", "--out", str(out), "--max-samples", "1024", "--repeats", "3", "--laps", "2",
                     "--lap-seconds", "1.5"]) == 0
    assert seen["run"][1] == device.DeviceSuiteConfig(max_samples=1024, repeats=3, laps=2, lap_seconds=1.5)


def _row(step, n, median_ms):
    return {"group": "table1", "name": step, "num_samples": n, "horizon": 80, "median_ms": median_ms,
            "min_ms": median_ms, "p95_ms": median_ms, "max_ms": median_ms, "step": step}


def test_an_interrupted_run_keeps_the_parts_it_finished(tmp_path, monkeypatch, capsys):
    """Each part is written as soon as it is done; Ctrl-C during the race leaves Table I and the scaling in
    device.json, marked interrupted, and the command exits 130."""
    monkeypatch.setattr(device, "table1_rows", lambda repeats, log: [_row(step, 512, 0.5 + i)
                                                                     for i, step in enumerate(device.TABLE1_STEPS)])
    monkeypatch.setattr(device, "scaling_rows", lambda config, dof, log: [dof, _row("dof", 1024, 0.8)])

    def interrupted(laps, lap_seconds, log):
        raise KeyboardInterrupt

    monkeypatch.setattr(device, "race_figures", interrupted)
    out = tmp_path / "run"
    assert cli.main(["bench", "device", "--out", str(out), "--max-samples", "1024"]) == cli.EXIT_INTERRUPTED
    written = json.loads((out / device.JSON_NAME).read_text())
    assert written["interrupted"] is True and written["parts_done"] == ["table1", "scaling"]
    assert "race" not in written and not (out / device.PLOT_NAME).exists()
    assert [r["step"] for r in written["table1"]] == list(device.TABLE1_STEPS)
    summary = written["summary"]
    assert summary["dof_step_median_ms"] == {"512": 0.5, "1024": 0.8}
    assert (summary["vdof_median_ms"], summary["nominal_median_ms"], summary["dof_network_median_ms"]) == (1.5, 2.5,
                                                                                                          3.5)
    assert summary["goals"] == {"dof_step_ms at 512 x 80 <= 1": True, "dof_step_ms at 16384 x 80 <= 2": None}
    assert summary["race_laps_finished"] is None
    assert "interrupted: the parts done (table1, scaling)" in capsys.readouterr().out


def _positive_finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


@pytest.mark.slow
def test_a_tiny_run_on_the_cpu_writes_the_schema(tmp_path, capsys):
    """Every part at its smallest: Table I at 512 x 80 with 3 repeats, the scaling at 512 and 1024, 2 laps of 1 s."""
    out = tmp_path / "device"
    assert cli.main(["bench", "device", "--out", str(out), "--max-samples", "1024", "--repeats", "3", "--laps", "2",
                     "--lap-seconds", "1"]) == 0
    printed = capsys.readouterr().out
    assert "] table1" in printed and "] scaling" in printed and "] race" in printed  # progress, part by part
    written = json.loads((out / device.JSON_NAME).read_text())
    assert (out / device.PLOT_NAME).stat().st_size > 10_000
    assert written["device"]["device_kind"] == jax.devices()[0].device_kind
    assert written["device"]["jax"] == jax.__version__
    assert written["parts_done"] == list(device.PARTS) and written["interrupted"] is False
    assert written["config"] == {"max_samples": 1024, "repeats": 3, "laps": 2, "lap_seconds": 1.0}

    assert [r["step"] for r in written["table1"]] == list(device.TABLE1_STEPS)
    scaling = written["scaling"]
    assert [r["num_samples"] for r in scaling] == [512, 1024]
    assert scaling[0]["median_ms"] == written["table1"][0]["median_ms"]  # the 512 point is Table I's DOF step
    for row in written["table1"] + scaling:
        assert (row["num_samples"] in (512, 1024) and row["horizon"] == 80 and row["status"] == "ok"
                and row["repeats"] == 3), row
        for field in ("median_ms", "mean_ms", "min_ms", "max_ms", "p95_ms", "first_call_ms"):
            assert _positive_finite(row[field]), (row["name"], field)
        assert row["min_ms"] <= row["median_ms"] <= row["p95_ms"] <= row["max_ms"]

    race = written["race"]
    assert (race["preset"], race["estimator"], race["laps"], race["batch_size"]) == ("best", "truth", 2, 2)
    # 1 s laps end at 40 ticks (a timeout) or before (a crash); none can finish the course
    assert race["laps_finished"] == 0 and race["lap_time_s_median"] is None
    assert 2 <= race["ticks"] <= 80 and race["ticks_longest_lap"] <= 40
    for field in ("wall_s", "first_flight_s", "ticks_per_s", "batch_ticks_per_s", "simulated_s", "real_time_factor"):
        assert _positive_finite(race[field]), field
    assert race["ticks_per_s"] == pytest.approx(race["ticks"] / race["wall_s"])
    assert race["real_time_factor"] == pytest.approx(race["ticks"] * 0.025 / race["wall_s"])
    assert race["first_flight_s"] > race["wall_s"]  # the first flight compiled

    summary = written["summary"]
    assert summary["dof_step_median_ms"] == {"512": scaling[0]["median_ms"], "1024": scaling[1]["median_ms"]}
    assert summary["goals"] == {"dof_step_ms at 512 x 80 <= 1": scaling[0]["median_ms"] <= 1.0,
                                "dof_step_ms at 16384 x 80 <= 2": None}
    assert summary["race_real_time_factor"] == race["real_time_factor"]
