"""pixelmpc reproduce: part selection, resuming, the combined report."""

import json

import pytest

from pixelmpc_jax.apps.experiments import reproduce as R


def test_aliases_expand_in_canonical_order_without_repeats():
    assert R.resolve_parts(["all"]) == ["frontier", "table2", "table4", "dof", "bench"]
    assert R.resolve_parts(["all"], quick=True) == R.resolve_parts(["all"])
    assert R.resolve_parts(["fig9", "table1", "table3", "fig6"]) == ["table2", "table4", "bench"]
    assert R.resolve_parts(["projection", "all"])[-1] == "table2_projection"  # not in all, runs last
    assert R.resolve_parts(["robustness", "table4"]) == ["table4", "robustness"]  # not in all either
    assert set(R.RUNNERS) == set(R.PARTS) and set(R.TITLES) == set(R.PARTS)
    with pytest.raises(ValueError, match="unknown part 'table9'"):
        R.resolve_parts(["table9"])


def test_finished_parts_are_kept_and_an_interrupted_part_is_rerun(tmp_path, monkeypatch):
    calls = []

    def fake_runners():
        def make(part, fail=False):
            def run(folder, quick, progress):
                calls.append(part)
                if fail:
                    raise KeyboardInterrupt
                (folder / "REPORT.md").write_text(f"# {part} results\n\n![plot](figure.png)\n")
                return "REPORT.md"
            return run
        return {"bench": make("bench"), "dof": make("dof"), "table2": make("table2"),
                "table2_projection": make("table2_projection"),
                "table4": lambda folder, quick, progress: make("table4", fail_table4[0])(folder, quick, progress)}

    fail_table4 = [True]
    monkeypatch.setattr(R, "RUNNERS", fake_runners())
    with pytest.raises(KeyboardInterrupt):
        R.reproduce(["table1", "table2", "table4"], tmp_path, quick=True, progress=False)
    state = json.loads((tmp_path / "reproduce.json").read_text())
    assert set(state) == {"table2"}  # table4 was interrupted: not recorded, and the run stopped there
    assert calls == ["table2", "table4"]
    # an interrupted part that left a report of its finished cells appears, marked unfinished
    (tmp_path / "table4" / "REPORT.md").write_text("# table4 so far\n")
    R.write_report(tmp_path, state)
    written = (tmp_path / "REPORT.md").read_text()
    assert "no: interrupted, resume with `pixelmpc reproduce table4" in written
    assert "not run yet: `pixelmpc reproduce bench" in written and "not run yet: `pixelmpc reproduce dof" in written

    fail_table4[0] = False
    R.reproduce(["table1", "table2", "table4"], tmp_path, quick=True, progress=False)
    assert calls == ["table2", "table4", "table4", "bench"]  # the finished part was not recomputed
    report = (tmp_path / "REPORT.md").read_text()
    for part in ("bench", "table2", "table4"):
        assert f"## {R.TITLES[part]}" in report
        assert f"({part}/figure.png)" in report  # image links point into the part's folder
    # a full run does not accept the quick results as finished
    R.reproduce(["table2"], tmp_path, quick=False, progress=False)
    assert calls[-1] == "table2"
    assert json.loads((tmp_path / "reproduce.json").read_text())["table2"]["quick"] is False


def test_cli_rejects_an_unknown_part():
    from pixelmpc_jax.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["reproduce", "table9"])
    assert exc.value.code == 2


def test_a_resumed_grid_part_reports_the_wall_time_of_all_its_cells(tmp_path):
    import json

    from pixelmpc_jax.apps.experiments import reproduce as R

    assert R._part_wall_time(tmp_path, 12.0) == 12.0  # no grid in the folder: this run's time
    (tmp_path / "results.json").write_text(json.dumps({"a": {"wall_time_s": 100.0}, "b": {"wall_time_s": 200.0}}))
    assert R._part_wall_time(tmp_path, 12.0) == 300.0
    assert R._part_wall_time(tmp_path, 400.0) == 400.0


def test_the_report_opens_with_the_presets_and_the_measured_pace(tmp_path):
    """The overview prints our nominal lap at each recorded pace beside the paper's, and where this run's own
    frontier puts the paper's lap (linear between the nominal points)."""
    from pixelmpc_jax.apps.racing.presets import PAPER_PACE_SPEEDS

    nominal = [{"speed": 8.0, "lap_time_s": 33.0, "lap_time_two_sigma_s": 1.0},
               {"speed": PAPER_PACE_SPEEDS[14.0], "lap_time_s": 31.0, "lap_time_two_sigma_s": 0.5},
               {"speed": 10.0, "lap_time_s": 27.0, "lap_time_two_sigma_s": 0.5}]
    (tmp_path / "frontier").mkdir()
    (tmp_path / "frontier" / "frontier.json").write_text(json.dumps({"nominal": nominal}))
    text = "\n".join(R._overview(tmp_path))
    assert "`best`:" in text and "`paper`:" in text and "`racing`:" in text
    # 31.8 s lies between 33.0 s (8 m/s) and 31.0 s (8.5 m/s): 8 + 0.5 * 1.2 / 2 = 8.30 m/s
    assert "| 14 m/s | 31.8 | 8.5 m/s | 31.0 ± 0.5 | 8.30 m/s |" in text
    assert "| 20 m/s | - (straight lane) | 10.3 m/s | - | - |" in text


def test_a_part_report_titled_as_its_section_shows_the_title_once(tmp_path):
    folder = tmp_path / "frontier"
    folder.mkdir()
    (folder / "REPORT.md").write_text(f"# {R.TITLES['frontier']}\n\n## Nominal MPPI\n\nrows\n")
    state = {"frontier": {"quick": False, "wall_time_s": 60.0, "finished": "then", "report": "REPORT.md"}}
    report = R.write_report(tmp_path, state).read_text()
    assert report.count(R.TITLES["frontier"]) == 2  # the overview's row and the section's heading
    assert f"## {R.TITLES['frontier']}" in report and "### Nominal MPPI" in report
