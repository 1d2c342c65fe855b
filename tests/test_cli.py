"""The pixelmpc command: help, version, the demo, and clear errors for bad arguments."""

import dataclasses
import functools
import json

import numpy as np
import pytest
import standard_race

from pixelmpc_jax import cli
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.costs import RacingCostConfig
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash


def _reject(constant):
    raise AssertionError(f"non-strict JSON: {constant}")


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
    summary = json.loads((tmp_path / "demo.json").read_text(), parse_constant=_reject)  # strict JSON
    assert summary["final_error_m"] < 0.3
    assert (tmp_path / "demo.png").stat().st_size > 1000


def test_unwritable_output_directory_is_rejected_before_running(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(SystemExit) as exc:
        cli.main(["demo", "--out", str(blocker / "sub")])
    assert exc.value.code == 2
    assert "cannot be written" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["race", "--controller", "pid"], "invalid choice"),
        (["race", "--speed", "-14"], "argument --speed: must be a finite number in (0, 50] m/s, got -14"),
        (["race", "--laps", "0"], "argument --laps: must be an integer in [1, inf), got 0"),
        (["race", "--laps", "two"], "expected an integer"),
        (["race", "--pixel-cost", "l2"], "invalid choice"),
        (["race", "--border-margin", "0"], "argument --border-margin: must be a finite number in (0, 0.5]"),
        (["race", "--noise-exponent", "nan"], "argument --noise-exponent: must be a finite number in [0, 4]"),
        (["race", "--heading-weight", "2"], "argument --heading-weight: must be a finite number in [0, 1]"),
    ],
)
def test_race_rejects_bad_arguments_before_running(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_interrupted_race_keeps_the_finished_laps(tmp_path, monkeypatch):
    from pixelmpc_jax.apps.racing import race
    from pixelmpc_jax.sim import metrics

    calls = {"n": 0}
    real = metrics.lap_metrics

    def interrupt_on_second_batch(log, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == standard_race.BATCH + 1:
            raise KeyboardInterrupt
        return real(log, *args, **kwargs)

    monkeypatch.setattr(race.metrics_lib, "lap_metrics", interrupt_on_second_batch)
    spec = standard_race.NOMINAL.replace(laps=3, seed=4)
    results = race.run_laps(spec, out=tmp_path, batch_size=standard_race.BATCH, progress=False)
    assert [lap["seed"] for lap in results["laps"]] == [4, 5] and results["interrupted"]  # the first batch
    saved = json.loads((tmp_path / "metrics.json").read_text(), parse_constant=_reject)  # strict JSON
    assert len(saved["laps"]) == 2 and saved["interrupted"] is True
    assert set(metrics.LAP_KEYS) <= set(saved["laps"][0])
    assert saved["aggregate"]["num_laps"] == 2 and "success_rate" in saved["aggregate"]


def test_race_flags_make_the_race_spec(monkeypatch, tmp_path):
    """Every race flag lands in the RaceSpec (each controller flag in its field of the configuration); execution
    flags beside it."""
    from pixelmpc_jax.apps.racing import compare, presets

    seen = {}

    def fake_run_compare(spec, controllers, **kwargs):
        seen.update(kwargs, spec=spec, controllers=controllers)
        return {"controllers": {}, "interrupted": False}

    monkeypatch.setattr(compare, "run_compare", fake_run_compare)
    cli.main(["race", "--out", str(tmp_path), "--pixel-cost", "border", "--border-margin", "0.2",
              "--noise-exponent", "1", "--heading-weight", "0.5", "--speed", "9", "--laps", "3", "--seed", "5",
              "--course", "straight", "--estimator", "pf", "--detector", "image", "--pixel-model", "projection",
              "--t-f", "0.5", "--c-pixel", "3e6", "--max-time", "20", "--temperature", "100", "--perturb",
              "--samples", "256", "--batch", "2", "--video", "--clearance", "0.2"])
    mppi = dataclasses.replace(paper_mppi_config(num_samples=256, temperature=100.0), noise_exponent=1.0)
    racing = RacingCostConfig(heading_weight=0.5, vehicle_radius=0.2)
    best = presets.preset("best").config  # what no flag names stays the default preset's
    config = ControllerConfig(mppi=mppi, racing=racing, pixel_model="projection",
                            t_f=0.5, c_pixel=3e6, pixel_cost="border", border_margin=0.2,
                            target_prior=best.target_prior, look_ahead=best.look_ahead,
                            look_ahead_from=best.look_ahead_from, partial_target=best.partial_target)
    assert seen["spec"] == RaceSpec("pixelmpc", config, speed=9.0, laps=3, seed=5, perturb=True, course="straight",
                                    detector="image", estimator="pf", max_time_s=20.0)
    assert seen["batch_size"] == 2 and seen["video"] is True and seen["out"] == tmp_path
    assert seen["dof_params"] is None and seen["preset"] == "best" and seen["controllers"] == ("pixelmpc", "mppi")


def test_a_preset_is_the_race_and_one_flag_overrides_one_field(monkeypatch, tmp_path):
    from pixelmpc_jax.apps.racing import compare, presets

    seen = {}
    monkeypatch.setattr(compare, "run_compare", lambda spec, controllers, **kwargs: seen.update(
        spec=spec, controllers=controllers, **kwargs) or {"controllers": {}, "interrupted": False})
    for argv, expected in ((["--preset", "paper"], presets.preset("paper")),
                           ([], presets.preset("best")),
                           (["--c-pixel", "1e7", "--laps", "2"],
                            presets.preset("best").replace(laps=2, config=dataclasses.replace(
                                presets.preset("best").config, c_pixel=1e7))),
                           (["--preset", "paper", "--dof-weights", "turned"],
                            presets.preset("paper").replace(dof_weights="turned")),
                           (["--preset", "racing"], presets.preset("racing")),
                           (["--camera-tilt", "30", "--speed", "14"],
                            presets.preset("racing")),  # best on the racing camera at 14 m/s: the racing preset
                           (["--controller", "mppi"], presets.preset("best"))):
        cli.main(["race", "--out", str(tmp_path), *argv])
        assert seen["spec"] == expected and seen["spec"].key() == expected.key()
    assert seen["controllers"] == ("mppi",)
    assert presets.preset("paper").config.pixel_cost == "l1" and presets.preset("paper").dof_weights is None
    assert presets.preset("best").config.pixel_cost == "border" and presets.preset("best").speed == 8.5


def test_the_onboard_loop_sets_its_settings_and_a_flag_still_overrides_one(monkeypatch, tmp_path):
    from pixelmpc_jax.apps.racing import compare, presets

    seen = {}
    monkeypatch.setattr(compare, "run_compare", lambda spec, controllers, **kwargs: seen.update(
        spec=spec, **kwargs) or {"controllers": {}, "interrupted": False})
    cli.main(["race", "--out", str(tmp_path), "--loop", "onboard", "--perturb"])
    onboard = presets.preset("best").replace(detector="image", estimator="eskf", perturb=True)
    assert seen["spec"] == onboard and (onboard.gate_switch, onboard.map) == ("estimate", "surveyed")
    cli.main(["race", "--out", str(tmp_path), "--loop", "onboard", "--perturb", "--map", "known", "--detector",
              "clipped", "--gate-switch", "truth"])
    assert seen["spec"] == onboard.replace(detector="clipped", map="known", gate_switch="truth")
    cli.main(["race", "--out", str(tmp_path), "--preset", "paper", "--loop", "truth"])
    assert seen["spec"] == presets.preset("paper")


def test_each_race_flag_names_one_field_of_the_race():
    from pixelmpc_jax.commands.race import RACE_FLAGS

    fields = [flag.field for flag in RACE_FLAGS if flag.field is not None]
    assert len(fields) == len(set(fields))  # one flag per field
    for field in fields:
        node = RaceSpec()
        for name in field.split("."):
            assert name in {f.name for f in dataclasses.fields(node)}, f"{field}: no field {name}"
            node = getattr(node, name)
    parser = cli._command_parser(cli.build_parser(), cli.build_parser().parse_args(["race"]))
    assert {flag.dest for flag in RACE_FLAGS} <= {action.dest for action in parser._actions}


def test_the_race_flags_set_their_fields_together(tmp_path):
    """A saved race on the projection pixel model, flown with vdof and the projection look-ahead: set one at a time,
    the projection would have reset the look-ahead model to its own before vdof replaced it."""
    from pixelmpc_jax.apps.racing import presets
    from pixelmpc_jax.commands.race import race_spec

    best = presets.preset("best")
    saved = tmp_path / "projection.json"
    saved.write_text(json.dumps(best.with_fields({"config.pixel_model": "projection"}).record()))
    args = cli.build_parser().parse_args(["race", "--config", str(saved), "--pixel-model", "vdof",
                                          "--look-ahead-model", "projection", "--temperature", "50"])
    spec, _ = race_spec(args)
    mppi = dataclasses.replace(best.config.mppi, temperature=50.0)
    assert spec.config == dataclasses.replace(best.config, mppi=mppi, box_size_limit=None)  # the projection dropped it
    assert spec.config.look_ahead_model == "projection" and spec.key() != best.key()


def test_the_last_smaller_batch_is_padded_so_the_batched_episode_compiles_once(monkeypatch):
    """3 laps in batches of 2: both batches reach the vmapped runner with 2 lanes; the copy is dropped."""
    from pixelmpc_jax.apps.racing import race

    shapes = []
    make_runner = race.episode_lib.make_runner

    def recording_runner(*args, **kwargs):
        runner = make_runner(*args, **kwargs)

        def batch(worlds, keys):
            shapes.append((keys.shape, worlds.target_speed.shape))
            return runner.batch(worlds, keys)

        return runner._replace(batch=batch)

    monkeypatch.setattr(race.episode_lib, "make_runner", recording_runner)
    monkeypatch.setattr(race, "_runner", functools.lru_cache(race._runner.__wrapped__))  # this test's runners only
    spec = standard_race.NOMINAL.replace(laps=3, seed=4)
    results = race.run_laps(spec, batch_size=2, progress=False)
    assert [lap["seed"] for lap in results["laps"]] == [4, 5, 6] and len(results["trajectories"]) == 3
    assert len(shapes) == 2 and shapes[0] == shapes[1] and shapes[0][0][0] == 2
    shapes.clear()
    race.run_laps(spec.replace(laps=2), batch_size=4, progress=False)
    assert [s[0][0] for s in shapes] == [2]  # a run shorter than a batch is not padded


def test_races_that_differ_only_in_their_worlds_fly_one_compiled_runner(monkeypatch):
    """A race at another speed, seed and course (what the world holds) takes the runner an earlier race of its
    configuration compiled, and flies the laps a runner of its own flies; another configuration builds its own."""
    from pixelmpc_jax.apps.racing import race

    monkeypatch.setattr(race, "_runner", functools.lru_cache(race._runner.__wrapped__))  # this test's runners only
    spec = standard_race.NOMINAL.replace(seed=4)
    other = spec.replace(speed=9.0, seed=7, course="straight")
    first = race.prepare(spec)
    assert race.prepare(other).flight.runner is first.flight.runner
    assert race.prepare(other, batch_size=2).flight.runner is first.flight.runner  # a batch's shape: jit's own cache
    assert race.prepare(other.replace(estimator="eskf")).flight.runner is not first.flight.runner
    fewer = other.replace(config=ControllerConfig(mppi=paper_mppi_config(num_samples=16)))
    assert race.prepare(fewer).flight.runner is not first.flight.runner
    faster = spec.replace(speed=11.0, seed=5, laps=standard_race.BATCH)
    shared = race.run_laps(faster, batch_size=standard_race.BATCH, progress=False)
    race._runner.cache_clear()
    own = race.run_laps(faster, batch_size=standard_race.BATCH, progress=False)
    np.testing.assert_array_equal(shared["trajectories"][0], own["trajectories"][0])
    assert shared["laps"] == own["laps"]


def test_race_dof_weights_option(monkeypatch, tmp_path, capsys):
    """--dof-weights picks a packaged variant (named in the spec) or a file (its weights passed, its fingerprint
    in the spec); a missing file is refused before anything runs."""
    import jax

    from pixelmpc_jax.apps.racing import race
    from pixelmpc_jax.dynamics import dof

    seen = {}

    class Prepared(Exception):
        """Raised where the race is built, once its spec and weights are seen: nothing flies."""

    def prepare(spec, batch_size=1, dof_params=None):
        seen.update(spec=spec, dof_params=dof_params)
        raise Prepared

    monkeypatch.setattr(race, "prepare", prepare)
    with pytest.raises(Prepared):
        cli.main(["race", "--out", str(tmp_path), "--preset", "paper", "--controller", "pixelmpc", "--dof-weights",
                  "flown"])
    assert seen["dof_params"] is None and seen["spec"].dof_weights == "flown"  # the race loads packaged weights
    flown = dof.load_packaged_dof("flown")
    assert seen["spec"].dof_fingerprint() == dof_weights_hash(flown)
    file = tmp_path / "weights.msgpack"
    dof.save_checkpoint(file, flown, {"what": "test"})
    with pytest.raises(Prepared):
        cli.main(["race", "--out", str(tmp_path), "--preset", "paper", "--controller", "pixelmpc", "--dof-weights",
                  str(file)])
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(lambda a, b: bool((a == b).all()), seen["dof_params"], flown))
    assert seen["spec"].dof_weights == dof_weights_hash(flown)  # the spec names the weights it flies
    with pytest.raises(Prepared):
        cli.main(["race", "--out", str(tmp_path), "--preset", "paper", "--controller", "pixelmpc", "--dof-weights",
                  "paper"])
    assert seen["dof_params"] is None and seen["spec"].dof_weights is None
    code = cli.main(["race", "--out", str(tmp_path / "new"), "--dof-weights", str(tmp_path / "missing.msgpack")])
    assert code == 2 and "missing.msgpack" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    with pytest.raises(ValueError, match="unknown packaged DOF weights"):
        dof.load_packaged_dof("best")


@pytest.mark.parametrize("argv, kept", [(["race"], True), (["--release-memory", "bench", "suite"], False),
                                        (["demo"], False)])
def test_the_command_keeps_freed_memory_for_race_bench_reproduce_unless_told_not_to(argv, kept, monkeypatch):
    """`pixelmpc race|bench|reproduce` has glibc keep freed memory before the command starts (here it is stopped
    right after); --release-memory and the other commands leave the allocator alone."""
    from pixelmpc_jax import host

    class Stop(Exception):
        """Stops the command where the test has seen what it needs."""

    calls = []
    monkeypatch.setattr(host, "keep_host_memory", lambda keep=True: calls.append(keep) or True)
    monkeypatch.setattr(cli, "_command_parser", lambda *args: (_ for _ in ()).throw(Stop()))
    with pytest.raises(Stop):
        cli.main(argv, split_cpu=True)
    assert calls == ([True] if kept else [])


def test_a_generated_course_file_is_a_race_course_keyed_by_its_contents(tmp_path, capsys):
    from pixelmpc_jax.world.course import make_course

    first, second = tmp_path / "a" / "course.json", tmp_path / "b.json"
    assert cli.main(["course", "--seed", "3", "--out", str(first)]) == 0
    assert cli.main(["course", "--seed", "4", "--gates", "5", "--out", str(second)]) == 0
    assert make_course(str(second)).num_gates == 5
    spec = RaceSpec("mppi", course=str(first))
    assert spec.key() != spec.replace(course=str(second)).key() != RaceSpec("mppi").key()
    copy = tmp_path / "copy.json"
    copy.write_bytes(first.read_bytes())
    assert spec.replace(course=str(copy)).key() == spec.key()  # the contents, not the path
    bad = tmp_path / "bad.json"
    bad.write_text('{"race": {"gate_order": ["G1"]}, "gates": {}}')
    capsys.readouterr()
    assert cli.main(["race", "--course", str(bad), "--out", str(tmp_path / "never")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "gate_order" in err and not (tmp_path / "never").exists()
    with pytest.raises(SystemExit) as exit_info:  # argparse refuses a missing file as it parses
        cli.main(["race", "--course", str(tmp_path / "missing.json"), "--out", str(tmp_path)])
    assert exit_info.value.code == 2
