"""Experiment grids and the race specification: which finished cells a rerun keeps (settings, seed, laps, DOF
weights), the cache key of a RaceSpec."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from pixelmpc_jax.apps.racing import grid, race
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.dynamics.dof import packaged_dof_hash
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash
from pixelmpc_jax.perception.eskf import ESKFConfig
from pixelmpc_jax.sim import ticks as ticks_lib
from pixelmpc_jax.sim import ticks_compact
from pixelmpc_jax.sim.metrics import MEASURE
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib

CELLS = [grid.Cell("nominal"), grid.Cell("dof", RaceSpec("pixelmpc")),
         grid.Cell("projection", RaceSpec("pixelmpc", ControllerConfig(pixel_model="projection")))]


@pytest.fixture
def flown(monkeypatch):
    """Replace race.run_laps by a fake that records which cells it flies, with which seed and weights."""
    calls = []

    def run_laps(spec, dof_params=None, **kwargs):
        spec.check_weights(dof_params)  # the grid names the weights it passes
        calls.append((spec.controller, spec.config.pixel_model, spec.seed, dof_params))
        return {"laps": [{"success": True, "seed": spec.seed + i} for i in range(spec.laps)], "aggregate": {},
                "seed": spec.seed, "interrupted": False, "trajectories": [np.zeros((2, 10))] * spec.laps,
                "covariances": [], "measure": MEASURE}

    monkeypatch.setattr(race, "run_laps", run_laps)
    return calls


def _names(calls):
    """The cells flown, by name (each cell of CELLS has its own controller and pixel model)."""
    return sorted("nominal" if controller == "mppi" else model for controller, model, _, _ in calls)


def _run(calls, tmp_path, **kwargs):
    calls.clear()
    grid.run_grid(CELLS, tmp_path, progress=False, batch_size=1, **{"laps": 2, **kwargs})
    return _names(calls)


def test_other_seeds_laps_or_weights_fly_the_cell_again(tmp_path, flown):
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    assert _run(flown, tmp_path) == ["dof", "nominal", "projection"]
    assert _run(flown, tmp_path) == []  # the same run: every cell kept
    assert _run(flown, tmp_path, seed=1) == ["dof", "nominal", "projection"]
    assert all(seed == 1 for _, _, seed, _ in flown)
    assert _run(flown, tmp_path, seed=1, dof_params=other) == ["dof"]  # only the cell that uses the DOF
    assert _run(flown, tmp_path, seed=1, dof_params=other) == []
    assert _run(flown, tmp_path, seed=1) == ["dof"]  # back to the packaged weights
    assert _run(flown, tmp_path, seed=1, laps=3) == ["dof", "nominal", "projection"]

    saved = json.loads((tmp_path / "results.json").read_text())
    assert {entry["seed"] for entry in saved.values()} == {1}
    assert saved["dof"]["dof_weights_sha256"] == packaged_dof_hash()
    assert saved["nominal"]["dof_weights_sha256"] is None and saved["projection"]["dof_weights_sha256"] is None


def test_the_weights_hash_follows_the_values():
    packaged = dof.load_packaged_dof()
    assert dof_weights_hash(packaged) == dof_weights_hash(dof.load_packaged_dof())
    changed = jax.tree_util.tree_map(lambda a: a, packaged).replace(input_mean=packaged.input_mean + 1e-3)
    assert dof_weights_hash(changed) != dof_weights_hash(packaged)
    assert len(dof_weights_hash(packaged)) == 16


def test_results_without_seed_or_hash_count_as_the_defaults(tmp_path, flown):
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    _run(flown, tmp_path)
    path = tmp_path / "results.json"
    old = {name: {k: v for k, v in entry.items() if k not in ("seed", "dof_weights_sha256")}
           for name, entry in json.loads(path.read_text()).items()}
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path) == []  # seed 0, packaged weights: what older files were flown with
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path, dof_params=other) == ["dof"]
    path.write_text(json.dumps(old))
    assert _run(flown, tmp_path, seed=3) == ["dof", "nominal", "projection"]


def test_results_of_another_visibility_measure_are_flown_again(tmp_path, flown):
    """Results recorded before the measure counted from the target (no ``measure``, or another) are not current:
    the same race, measured otherwise, is flown again."""
    _run(flown, tmp_path)
    path = tmp_path / "results.json"
    saved = json.loads(path.read_text())
    path.write_text(json.dumps({name: {k: v for k, v in entry.items() if k != "measure"} for name, entry in
                                saved.items()}))
    assert _run(flown, tmp_path) == ["dof", "nominal", "projection"]
    assert _run(flown, tmp_path) == []
    saved = json.loads(path.read_text())
    path.write_text(json.dumps({**saved, "nominal": {**saved["nominal"], "measure": "after-first-seen"}}))
    assert _run(flown, tmp_path) == ["nominal"]


def test_the_apps_cells_find_the_results_a_run_of_them_recorded(flown, tmp_path):
    """The cells the reproduce parts and the frontier define are the ones the results a run of them wrote answer (each
    read back as its race), so a resumed `pixelmpc reproduce all` keeps them and flies nothing; another seed is
    another race."""
    from pixelmpc_jax.apps.experiments import frontier, paper
    from pixelmpc_jax.apps.racing import presets

    runs = {"frontier": [frontier.nominal_cell(v) for v in frontier.DEFAULT_SPEEDS]
            + list(frontier.preset_cells(presets.PAPER_PACE_SPEED)),
            "table2": paper.table_cells("dof")}
    for folder, cells in runs.items():
        grid.run_grid(cells, tmp_path / folder, laps=1, seed=200, progress=False, batch_size=1)
        results = grid.load_results(tmp_path / folder)
        assert sorted(results) == sorted(c.name for c in cells), folder
        for cell in cells:
            assert grid.recorded_race(results[cell.name]).key() == cell.race(1, 200, None).key(), cell.name
            assert grid.flies_race(results[cell.name], cell.race(1, 200, None)), cell.name
            assert not grid.flies_race(results[cell.name], cell.race(1, 201, None)), cell.name
        flown.clear()
        grid.run_grid(cells, tmp_path / folder, laps=1, seed=200, progress=False, batch_size=1)
        assert flown == [], folder


def test_current_results_are_the_cells_a_rerun_keeps(flown, tmp_path):
    """After a run, current_results gives every cell for the same seed and weights, none for another seed,
    and only the weight-free cells for other DOF weights (what the frontier reports after an interruption)."""
    _run(flown, tmp_path)
    assert sorted(grid.current_results(CELLS, tmp_path, laps=2)) == ["dof", "nominal", "projection"]
    assert grid.current_results(CELLS, tmp_path, laps=2, seed=5) == {}
    assert grid.current_results(CELLS, tmp_path, laps=3) == {}
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    assert sorted(grid.current_results(CELLS, tmp_path, laps=2, dof_params=other)) == ["nominal", "projection"]


# --------------------------------------------------------------------------------------------------
# The race specification's cache key.
# --------------------------------------------------------------------------------------------------


BORDER = ControllerConfig(pixel_cost="border", border_margin=0.2)


def test_identical_races_have_one_key_and_any_difference_another():
    spec = RaceSpec("pixelmpc", BORDER, speed=8.0, laps=4, seed=2)
    # the same race spelled otherwise: an int for a float, the MPPI config built another way
    mppi = paper_mppi_config()
    same = RaceSpec("pixelmpc", ControllerConfig(mppi=mppi, border_margin=0.2, pixel_cost="border", t_f=1), speed=8,
                    laps=4, seed=2)
    assert same == spec and same.key() == spec.key()
    assert RaceSpec.from_record(json.loads(json.dumps(spec.record()))).key() == spec.key()  # read back from JSON
    # the packaged weights named by their fingerprint are the packaged weights
    assert spec.replace(dof_weights=packaged_dof_hash()).key() == spec.key()
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    changes = {"controller": "mppi", "seed": 3, "laps": 5, "dof_weights": dof_weights_hash(other), "speed": 8.5,
               "course": "straight", "perturb": True, "detector": "image", "estimator": "pf", "max_time_s": 30.0}
    settings = {"pixel_model": "projection", "t_f": 2.0, "c_pixel": 3e6, "pixel_cost": "l1", "border_margin": 0.1,
                "mppi": dataclasses.replace(BORDER.mppi, temperature=100.0),
                "racing": dataclasses.replace(BORDER.racing, heading_weight=0.5)}
    keys = {name: spec.replace(**{name: value}).key() for name, value in changes.items()}
    keys.update({name: spec.replace(config=dataclasses.replace(BORDER, **{name: value})).key()
                 for name, value in settings.items()})
    assert spec.key() not in keys.values() and len(set(keys.values())) == len(keys)


def test_a_record_holds_every_setting_and_reads_back_as_its_race():
    """A record writes every setting of the race (the whole configuration); read back from JSON it is the same race
    with the same key. A setting the race does not know is refused, naming it."""
    spec = RaceSpec("pixelmpc", BORDER, speed=8.0, laps=4, seed=2, estimator="eskf", eskf=ESKFConfig(map_sigma_m=0.0))
    recorded = json.loads(json.dumps(spec.record()))
    assert recorded == json.loads(json.dumps(dataclasses.asdict(spec)))
    assert recorded["eskf"]["map_sigma_m"] == 0.0 and recorded["detector"] == "clipped" and "faults" in recorded
    assert RaceSpec.from_record(recorded) == spec and RaceSpec.from_record(recorded).key() == spec.key()
    recorded["config"]["mppi"]["sample_devices"] = 1  # how a step ran: not a setting of the race
    with pytest.raises(ValueError, match="unknown setting config.mppi.sample_devices"):
        RaceSpec.from_record(recorded)


def test_the_loops_defaults_and_the_settings_that_fly_nothing():
    """The clipped detector, the surveyed map and the estimated switch are the defaults; the ideal projection, the
    known map and the truth's switch are other races. Where a setting flies nothing it keeps its default: the map
    without a perturbation, the switch on the true state; nominal MPPI on the true state uses no detection: one key
    for both geometric ones."""
    perturbed = RaceSpec("pixelmpc", estimator="pf", perturb=True)
    assert (perturbed.detector, perturbed.map, perturbed.gate_switch) == ("clipped", "surveyed", "estimate")
    assert perturbed.record()["map"] == "surveyed" and perturbed.record()["gate_switch"] == "estimate"
    earlier = RaceSpec("pixelmpc", estimator="pf", perturb=True, detector="ideal", map="known", gate_switch="truth")
    assert earlier.key() != perturbed.key()
    assert RaceSpec.from_record(json.loads(json.dumps(earlier.record()))) == earlier
    plain = RaceSpec("pixelmpc", map="known", gate_switch="truth")
    assert (plain.map, plain.gate_switch) == ("surveyed", "estimate") and plain == RaceSpec("pixelmpc")
    nominal = RaceSpec("mppi")
    assert nominal.detector == "clipped" and nominal.key() == nominal.replace(detector="ideal").key()
    assert nominal.replace(detector="image").key() != nominal.key()
    on_filter = nominal.replace(estimator="pf")
    assert on_filter.detector == "clipped" and on_filter.key() != on_filter.replace(detector="ideal").key()
    for bad in ({"detector": "geometry"}, {"map": "atlas"}, {"gate_switch": "gps"}):
        with pytest.raises(ValueError, match="must be one of"):
            RaceSpec("pixelmpc", **bad)


def test_a_perturbed_race_keeps_the_nominal_map_in_the_controller_and_the_filter():
    """On the surveyed map (the default) each lap's world flies its perturbed gates while the map, all the controller
    and the filter read (``World.track``), stays the nominal course; on the known map the map is the perturbed
    course. Without a perturbation the map is the course."""
    from pixelmpc_jax.sim import env as env_lib
    from pixelmpc_jax.world import course as course_lib

    nominal = course_lib.load_course()
    base = env_lib.make_world(nominal)
    seeds = [0, 1]
    surveyed = race.lap_worlds(base, seeds, perturb=True)
    known = race.lap_worlds(base, seeds, perturb=True, map="known")
    for lane in range(len(seeds)):
        np.testing.assert_array_equal(surveyed.track.gates.centre[lane], nominal.gates.centre)
        np.testing.assert_array_equal(surveyed.track.path_points[lane], nominal.path_points)
        np.testing.assert_array_equal(surveyed.course.gates.centre[lane], known.track.gates.centre[lane])
        assert np.abs(np.asarray(surveyed.course.gates.centre[lane] - nominal.gates.centre)).max() > 0.05
    assert known.course is None and race.lap_worlds(base, seeds, perturb=False).course is None
    assert RaceSpec("pixelmpc", perturb=True).episode_config().gate_switch == "estimate"


def test_a_nominal_race_has_no_pixel_settings():
    """Nominal MPPI flies only the config's MPPI and racing settings: its PixelMPC fields make no other race."""
    nominal = RaceSpec("mppi", BORDER)
    assert nominal == RaceSpec("mppi") and nominal.key() == RaceSpec("mppi").key()
    hotter = dataclasses.replace(BORDER.mppi, temperature=100.0)
    assert RaceSpec("mppi", ControllerConfig(mppi=hotter)).key() != nominal.key()  # its MPPI settings do


def test_an_unknown_setting_is_refused_with_its_name():
    record = RaceSpec("pixelmpc").record()
    for path, message in ((("config", "mppi", "temprature"), "unknown setting config.mppi.temprature"),
                          (("config", "t_ff"), "unknown setting config.t_ff: ControllerConfig has the fields"),
                          (("speeed",), "unknown setting speeed: RaceSpec has the fields")):
        bad = json.loads(json.dumps(record))
        node = bad
        for name in path[:-1]:
            node = node[name]
        node[path[-1]] = 1.0
        with pytest.raises(ValueError, match=message):
            RaceSpec.from_record(bad)
    with pytest.raises(ValueError, match="pixel_cost must be one of"):  # a known setting, checked by its config
        RaceSpec.from_record({"controller": "pixelmpc", "config": {"pixel_cost": "l2"}})


def test_the_dof_weights_count_only_for_a_race_that_flies_the_dof():
    other = dof_weights_hash(jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof()))
    for spec in (RaceSpec("mppi"), RaceSpec("pixelmpc", ControllerConfig(pixel_model="projection"))):
        named = spec.replace(dof_weights=other)
        assert named.key() == spec.key() and named.dof_weights is None
    dof_race = RaceSpec("pixelmpc")
    assert dof_race.replace(dof_weights=other).key() != dof_race.key()


def test_a_race_flies_only_the_weights_it_names():
    packaged = dof.load_packaged_dof()
    other = jax.tree_util.tree_map(lambda a: a * 2, packaged)
    spec = RaceSpec("pixelmpc")
    spec.check_weights(None)
    spec.check_weights(packaged)
    with pytest.raises(ValueError, match="fingerprint"):
        spec.check_weights(other)
    named = spec.replace(dof_weights=dof_weights_hash(other))
    named.check_weights(other)
    with pytest.raises(ValueError, match="pass them as dof_params"):
        named.check_weights(None)
    with pytest.raises(ValueError, match="fingerprint"):
        race.run_laps(spec, dof_params=other, progress=False)  # refused before anything flies


def test_a_spec_refuses_bad_settings_and_a_cell_its_run_fields():
    for bad, match in (({"controller": "lqr"}, "unknown controller"), ({"course": "moon"}, "unknown course"),
                       ({"speed": 0.0}, "speed must be"), ({"speed": float("inf")}, "speed must be"),
                       ({"laps": 0}, "laps must be")):
        with pytest.raises(ValueError, match=match):
            RaceSpec(**bad)
    for run_field in ({"laps": 3}, {"seed": 1}, {"dof_weights": "0" * 16}):
        with pytest.raises(ValueError, match="takes them from the run"):
            grid.Cell("c", RaceSpec("pixelmpc", **run_field))


def test_a_record_reads_back_as_the_race_it_was_flown_as(tmp_path, flown):
    """The recorded settings, seed, laps and weights make the same race, so the same key."""
    other = jax.tree_util.tree_map(lambda a: a * 2, dof.load_packaged_dof())
    cells = [grid.Cell("dof", RaceSpec("pixelmpc", ControllerConfig(pixel_cost="border"), speed=9.0))]
    grid.run_grid(cells, tmp_path, laps=2, seed=4, progress=False, batch_size=1, dof_params=other)
    entry = grid.load_results(tmp_path)["dof"]
    assert grid.recorded_race(entry) == cells[0].race(2, 4, dof_weights_hash(other))
    assert grid.recorded_race({**entry, "config": {**entry["config"], "wings": 4}}) is None  # unknown setting


def test_a_flat_record_of_an_older_version_is_flown_again():
    """results.json written before the spec held the controller's configuration (settings flat, options dotted):
    every committed folder was rewritten in the nested form, so such a record names no race this version knows and
    its cell is flown again, not read as another race."""
    flat = {"name": "c", "controller": "pixelmpc", "speed": 8.0, "t_f": 1.0, "c_pixel": 3e7, "pixel_model": "dof",
            "temperature": None, "num_samples": 512, "max_time_s": 60.0, "detector": "ideal",
            "options": {"pixel_cost": "border", "mppi.noise_exponent": 1.0}}
    config = ControllerConfig(c_pixel=3e7, pixel_cost="border",
                              mppi=dataclasses.replace(paper_mppi_config(), noise_exponent=1.0))
    done = {"config": flat, "laps": [{}] * 2, "seed": 3}
    assert grid.recorded_race(done) is None
    assert not grid.flies_race(done, RaceSpec("pixelmpc", config, speed=8.0, laps=2, seed=3, detector="ideal"))


def test_a_vdof_race_names_the_packaged_vdof_weights_and_drops_the_dofs_names():
    from pixelmpc_jax.dynamics import vdof

    spec = RaceSpec("pixelmpc", ControllerConfig(pixel_model="vdof"), dof_weights="flown")  # a DOF name
    assert spec.dof_weights is None and spec.uses_dof
    assert spec.dof_fingerprint() == dof_weights_hash(vdof.load_packaged_vdof())
    assert spec.key() != RaceSpec("pixelmpc").key()
    spec.check_weights(vdof.load_packaged_vdof())
    with pytest.raises(ValueError, match="fingerprint"):
        spec.check_weights(dof.load_packaged_dof())
    assert dof_weights_hash(spec.packaged_dof()) == spec.dof_fingerprint()


def test_a_cell_another_grid_flew_is_copied_not_flown(flown, tmp_path, monkeypatch):
    """run_grid's reuse: a race finished in another folder (any cell name) is copied with its trajectories."""
    first = tmp_path / "first"
    _run(flown, first)
    renamed = [grid.Cell(f"again_{cell.name}", cell.spec) for cell in CELLS]

    def refuse(*args, **kwargs):
        raise AssertionError("flown again")

    monkeypatch.setattr(grid.race, "run_laps", refuse)
    results = grid.run_grid(renamed, tmp_path / "second", laps=2, progress=False, reuse=[first])
    assert sorted(results) == sorted(cell.name for cell in renamed)
    for cell in CELLS:
        copied = results[f"again_{cell.name}"]
        assert copied["shared_from"] == f"first/{cell.name}" and copied["wall_time_s"] == 0.0
        assert copied["laps"] == grid.load_results(first)[cell.name]["laps"]
        assert (tmp_path / "second" / f"trajectories_again_{cell.name}.npz").exists()
    with pytest.raises(AssertionError, match="flown again"):  # another seed is another race
        grid.run_grid(renamed[:1], tmp_path / "third", laps=2, seed=1, progress=False, reuse=[first])


def test_each_finished_cell_adds_its_laps_to_the_folders_compact_record(monkeypatch, tmp_path):
    """A grid writes ``ticks_compact.npz`` as its cells finish (flown or copied from another grid): what a result
    folder commits, from which each lap's figures recompute."""
    gates = course_lib.load_course().gates

    def lap(seed: int) -> dict:  # 10 ticks 5 m before gate 0, its visibility 0 for the last 3
        states = np.zeros((11, 10), np.float32)
        states[:, :3] = np.asarray(gates.centre[0]) - np.asarray([5.0, 0.0, 0.0])
        states[:, 3] = 1.0
        return {"seed": seed, "num_ticks": 10, "finished": False, "target": np.zeros(11, np.int32),
                "visibility": np.r_[np.ones(8), np.zeros(3)].astype(np.float32),
                "pointed_visibility": np.ones(11, np.float32), "states": states, "estimates": states,
                **{f"gate_{f}": np.asarray(getattr(gates, f)) for f in ticks_lib.GATE_FIELDS}}

    def run_laps(spec, dof_params=None, **kwargs):
        return {"laps": [{"success": False, "seed": spec.seed + i} for i in range(spec.laps)], "aggregate": {},
                "seed": spec.seed, "interrupted": False, "trajectories": [np.zeros((2, 10))] * spec.laps,
                "covariances": [], "measure": MEASURE, "ticks": [lap(spec.seed + i) for i in range(spec.laps)],
                "camera": camera_lib.default_camera()}

    monkeypatch.setattr(race, "run_laps", run_laps)
    grid.run_grid(CELLS[:2], tmp_path / "first", laps=2, seed=5, progress=False)
    compact = ticks_compact.load(tmp_path / "first" / ticks_compact.FILE_NAME)
    assert sorted(compact) == ["dof", "nominal"]
    laps = ticks_compact.race_laps(compact["dof"])
    assert [lap["seed"] for lap in laps] == [5, 6]
    assert [lap["time_vis_below_50_s"] for lap in laps] == pytest.approx([3 * 0.025, 3 * 0.025])
    grid.run_grid([grid.Cell("again_dof", CELLS[1].spec)], tmp_path / "second", laps=2, seed=5, progress=False,
                  reuse=[tmp_path / "first"])
    assert list(ticks_compact.load(tmp_path / "second" / ticks_compact.FILE_NAME)) == ["again_dof"]
    # a folder brought back with its compact record only (the full per-tick files left where they were flown)
    (tmp_path / "first" / "ticks_nominal.npz").unlink()
    grid.run_grid([grid.Cell("again_nominal", CELLS[0].spec)], tmp_path / "third", laps=2, seed=5, progress=False,
                  reuse=[tmp_path / "first"])
    copied = ticks_compact.load(tmp_path / "third" / ticks_compact.FILE_NAME)
    assert list(copied) == ["again_nominal"] and not (tmp_path / "third" / "ticks_again_nominal.npz").exists()
    assert ticks_compact.race_laps(copied["again_nominal"]) == ticks_compact.race_laps(compact["nominal"])


def test_a_tilted_camera_is_a_race_setting_both_controllers_fly_and_the_packaged_pixel_models_refuse():
    import math

    projection = ControllerConfig(pixel_model="projection", pixel_cost="border")
    spec = RaceSpec("pixelmpc", projection, speed=8.0)
    tilted = spec.replace(camera_tilt_deg=20)
    assert spec.record()["camera_tilt_deg"] == 0.0 and tilted.record()["camera_tilt_deg"] == 20.0
    assert tilted.camera_tilt_deg == 20.0 and tilted.key() != spec.key()
    assert RaceSpec.from_record(json.loads(json.dumps(tilted.record()))) == tilted
    prepared = race.prepare(tilted)
    assert float(prepared.camera.tilt) == pytest.approx(math.radians(20.0))
    assert float(race.prepare(spec).camera.tilt) == 0.0
    from pixelmpc_jax.apps.racing.presets import nominal_of

    assert nominal_of(tilted).camera_tilt_deg == 20.0  # nominal MPPI flies the same camera
    for bad in (-1.0, 61.0, float("nan"), True):
        with pytest.raises(ValueError, match="camera_tilt_deg"):
            spec.replace(camera_tilt_deg=bad)
    for model in ("dof", "vdof"):  # refused where the learned model is flown, not where the race is written
        tilted_learned = RaceSpec("pixelmpc", ControllerConfig(pixel_model=model), camera_tilt_deg=20.0)
        with pytest.raises(ValueError, match="trained for the untilted camera"):
            tilted_learned.check_weights(None)
        with pytest.raises(ValueError, match="trained for the untilted camera"):
            race.prepare(tilted_learned)
        tilted_learned.replace(controller="mppi").check_weights(None)  # nominal MPPI flies no pixel model
