"""The racing camera's data and the models trained on it: a collection through a camera tilted up on its mount (the
same laps as the untilted one's, seen otherwise), the flags that ask for it, datasets collected before the tilt was
recorded, and the weights' records that say which camera they serve (a race refuses weights for another camera)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import made_once_per_run
from test_collect import TINY, collect_tiny  # the dataset tests/test_collect.py collects

from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.dynamics import dof, network_weights, vdof
from pixelmpc_jax.learn import collect as C
from pixelmpc_jax.learn import dataset as D
from pixelmpc_jax.learn import rotation_augment
from pixelmpc_jax.learn import train as T
from pixelmpc_jax.learn.dof_spec import DOFConfig
from pixelmpc_jax.learn.vdof_spec import VDOFConfig
from pixelmpc_jax.sim import env as env_lib

TILT_DEG = 30.0
# TINY's laps (same seeds, speeds and runner: its compiled program) seen through the camera tilted up 30 degrees
TILTED = dataclasses.replace(TINY, camera_tilt_deg=TILT_DEG)


def collect_tilted(root) -> None:
    assert C.collect(root, TILTED, progress=False)["complete"]


@pytest.fixture(scope="module")
def tiny_dir():
    return made_once_per_run("tiny_collection", collect_tiny)  # read only: copied before a test changes it


@pytest.fixture(scope="module")
def tilted_dir():
    return made_once_per_run("tilted_collection", collect_tilted)


def test_a_tilted_camera_is_a_value_of_the_world_and_flies_tinys_program():
    """The tilt is a leaf of the world, not a new shape or a static setting: the lap compiled for TINY flies it."""
    flat, tilted = env_lib.make_world(camera=TINY.camera()), env_lib.make_world(camera=TILTED.camera())
    assert float(tilted.camera.tilt) == pytest.approx(math.radians(TILT_DEG)) and float(flat.camera.tilt) == 0.0
    assert jax.tree_util.tree_structure(flat) == jax.tree_util.tree_structure(tilted)
    assert [(jnp.shape(leaf), jnp.result_type(leaf)) for leaf in jax.tree_util.tree_leaves(flat)] == \
        [(jnp.shape(leaf), jnp.result_type(leaf)) for leaf in jax.tree_util.tree_leaves(tilted)]
    for lap in range(TINY.laps):
        assert C._lap_runners(TILTED, None)(lap) is C._lap_runners(TINY, None)(lap)  # one cached runner


def test_a_tilted_collection_records_its_tilt_and_sees_the_laps_through_the_tilted_camera(tilted_dir, tiny_dir):
    manifest = D.read_manifest(tilted_dir)
    assert manifest["config"] == TILTED.to_json() and manifest["config"]["camera_tilt_deg"] == TILT_DEG
    assert D.camera_tilt_deg(manifest) == TILT_DEG and D.camera_tilt_deg(D.read_manifest(tiny_dir)) == 0.0
    assert float(D.dataset_camera(manifest).tilt) == pytest.approx(math.radians(TILT_DEG))
    _, world = D.load_test_laps(tilted_dir, manifest, with_flow=False)
    assert float(world.camera.tilt) == pytest.approx(math.radians(TILT_DEG))  # evaluation sees through it too
    tilted_world = env_lib.make_world(camera=TILTED.camera())
    for split in ("train", "test"):
        tilted, flat = D.load_laps(tilted_dir, split)[0], D.load_laps(tiny_dir, split)[0]
        # the same flight (nominal MPPI on the true state sees no image), other frames
        np.testing.assert_array_equal(tilted.states, flat.states)
        difference = np.abs(tilted.flow.astype(np.float32) - flat.flow.astype(np.float32)).mean()
        assert difference > 0.1, f"{split}: mean flow difference {difference:.3f} px/frame"
        # the stored detections are the tilted camera's: the gate sits lower in an image tilted up
        expected = C.lap_detections(tilted_world, tilted.states, tilted.target)
        for key, value in expected.items():
            np.testing.assert_allclose(tilted.detections[key], value, atol=1e-5, err_msg=key)
        both = tilted.detections["gate_found"] & flat.detections["gate_found"]
        assert both.sum() > 10
        v_lower = tilted.detections["gate_centre"][both, 1] - flat.detections["gate_centre"][both, 1]
        assert np.all(v_lower > 0.05), v_lower.min()


def test_the_command_takes_the_racing_pace_and_the_tilt_and_refuses_them_out_of_range(capsys, monkeypatch, tmp_path):
    from pixelmpc_jax import cli
    from pixelmpc_jax.learn import collect as collect_module

    calls = []
    monkeypatch.setattr(collect_module, "run_collect", lambda out, **kwargs: calls.append(kwargs) or {})
    assert cli.main(["collect", "--out", str(tmp_path / "d"), "--speed-min", "12", "--speed-max", "16",
                     "--camera-tilt", "30"]) == 0
    assert {k: calls[0][k] for k in ("speed_min", "speed_max", "camera_tilt_deg")} == \
        {"speed_min": 12.0, "speed_max": 16.0, "camera_tilt_deg": 30.0}
    assert cli.main(["collect", "--out", str(tmp_path / "e")]) == 0 and "camera_tilt_deg" not in calls[1]
    for argv, message in ((["--camera-tilt", "61"], "argument --camera-tilt: must be a finite number in [0, 60] deg"),
                          (["--camera-tilt", "-5"], "argument --camera-tilt: must be"),
                          (["--speed-max", "19"], "argument --speed-max: must be a finite number in (0, 18] m/s"),
                          (["--speed-min", "0"], "argument --speed-min: must be"),
                          (["--speed-min", "15"], "argument --speed-min: must be at most --speed-max")):
        with pytest.raises(SystemExit) as exit_:
            cli.main(["collect", "--out", str(tmp_path / "f"), *argv])
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_.value.code == 2 and message in err[-1] and "Traceback" not in "\n".join(err), err
    assert len(calls) == 2 and not (tmp_path / "f").exists()  # refused before anything ran
    for bad in (dict(camera_tilt_deg=61.0), dict(camera_tilt_deg=float("nan")), dict(speed_max=19.0),
                dict(speed_min=0.0)):
        with pytest.raises(ValueError, match="CollectConfig.(camera_tilt_deg|speed_m..) must be"):
            C.CollectConfig(**bad)
    assert C.CollectConfig(speed_max=16.0, camera_tilt_deg=TILT_DEG).speeds()[-1] == 16.0


def test_a_dataset_collected_before_the_tilt_was_recorded_resumes_untilted(tiny_dir, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(tiny_dir, old)
    manifest = D.read_manifest(old)
    del manifest["config"]["camera_tilt_deg"]
    (old / D.MANIFEST).write_text(json.dumps(manifest))
    assert D.camera_tilt_deg(manifest) == 0.0 and float(D.dataset_camera(manifest).tilt) == 0.0
    assert DOFConfig().with_data(manifest).camera_tilt_deg == 0.0
    before = {p.name: p.stat().st_mtime_ns for p in old.glob("lap_*.npz")}
    assert C.collect(old, TINY, progress=False)["complete"]  # the same config: nothing flown again
    assert {p.name: p.stat().st_mtime_ns for p in old.glob("lap_*.npz")} == before
    with pytest.raises(ValueError, match="another config"):
        C.collect(old, TILTED, progress=False)


def test_training_takes_the_datasets_camera_and_its_record_states_it(tmp_path):
    from test_dataset import write_dataset  # a small dataset as collect writes it

    write_dataset(tmp_path / "data", frames=(6, 4))
    manifest = D.read_manifest(tmp_path / "data")
    manifest["config"]["camera_tilt_deg"] = TILT_DEG
    (tmp_path / "data" / D.MANIFEST).write_text(json.dumps(manifest))
    vdof_config = VDOFConfig().with_data(manifest)
    assert vdof_config.camera_tilt_deg == TILT_DEG
    assert float(vdof_config.camera().tilt) == pytest.approx(math.radians(TILT_DEG))
    out = tmp_path / "out"
    record = T.run_train(tmp_path / "data", out, T.TrainConfig(DOFConfig(steps=2, batch_size=64), progress=False))
    assert record["camera_tilt_deg"] == TILT_DEG and record["train_config"]["model"]["camera_tilt_deg"] == TILT_DEG
    _, saved = dof.load_checkpoint(out / "dof_weights.msgpack")
    for written in (saved, network_weights.weights_record(out / "dof_weights.msgpack")):
        assert network_weights.trained_camera_tilt_deg(written) == TILT_DEG
    assert "camera_tilt_deg" not in record["calls"][-1]  # a fact of the data, not a setting to repeat
    assert network_weights.trained_camera_tilt_deg(network_weights.weights_record(dof.PACKAGED_WEIGHTS)) == 0.0


def test_turned_rows_turn_the_datasets_camera():
    """Rotation augmentation turns the camera the data were seen through: the same turn moves a pixel otherwise
    through a camera tilted up (the rows of the untilted camera are those it turned before)."""
    n = 64
    key, key_u, key_i, key_j = jax.random.split(jax.random.key(0), 4)
    u = jnp.concatenate([jax.random.uniform(key_u, (n, 3), minval=-2, maxval=2), jnp.full((n, 1), 9.0)], 1)
    i, j = jax.random.randint(key_i, (n,), 0, 204), jax.random.randint(key_j, (n,), 0, 153)
    flow = jnp.zeros((n, 2), jnp.float32)

    def turned(tilt_deg: float):
        config = DOFConfig(input="flown", rotation_augment=1.0, camera_tilt_deg=tilt_deg)
        return rotation_augment.turn_training_rows(key, u, i, j, flow, config)

    (w_flat, flow_flat), (w_tilted, flow_tilted) = turned(0.0), turned(TILT_DEG)
    np.testing.assert_array_equal(w_flat, w_tilted)  # the same turn
    assert float(jnp.abs(flow_tilted - flow_flat).max()) > 0.1  # seen through another camera


def _weights_for(tmp_path, name: str, model_path, tilt_deg: float):
    """A copy of packaged weights whose record says they were trained for the camera tilted ``tilt_deg``."""
    path = tmp_path / name
    shutil.copyfile(model_path, path)
    record = {**network_weights.weights_record(model_path), "camera_tilt_deg": tilt_deg}
    path.with_suffix(".json").write_text(json.dumps(record))
    return path, record


@pytest.mark.parametrize("model", ["dof", "vdof"])
def test_a_race_flies_weights_on_the_camera_their_record_states_and_refuses_another(model, tmp_path):
    packaged = vdof.PACKAGED_VDOF if model == "vdof" else dof.PACKAGED_WEIGHTS
    tilted_variant = f"{'vdof' if model == 'vdof' else 'paper'}_tilt30"
    path, record = _weights_for(tmp_path, f"{model}_weights.msgpack", packaged, TILT_DEG)
    race = RaceSpec("pixelmpc", ControllerConfig(pixel_model=model), camera_tilt_deg=TILT_DEG)
    flat = race.replace(camera_tilt_deg=0.0)
    # the packaged weights for each camera: the untilted camera's on it, the racing camera's (30 deg) on that one
    flat.check_weights(None)
    race.check_weights(None)
    assert race.packaged_variant() == tilted_variant and flat.packaged_variant() != tilted_variant
    # at a tilt no packaged weights were trained for, the default (the untilted camera's) is refused
    with pytest.raises(ValueError, match="trained for the untilted camera: with camera_tilt_deg=20"):
        race.replace(camera_tilt_deg=20.0).check_weights(None)
    # packaged weights named, whose record states 30 degrees: refused on the untilted camera
    with pytest.raises(ValueError, match="trained for the camera tilted up 30 deg: with camera_tilt_deg=0"):
        flat.replace(dof_weights=tilted_variant).check_weights(None)
    # weights passed with their record (a file): the same rule; the record read beside the file agrees
    params = vdof.load_vdof(path)[0] if model == "vdof" else dof.load_checkpoint(path)[0]
    named = network_weights.dof_weights_hash(params)
    race.replace(dof_weights=named).check_weights(params, record)
    with pytest.raises(ValueError, match="weights were trained for the camera tilted up 30 deg"):
        flat.replace(dof_weights=named).check_weights(params, record)
    race.replace(controller="mppi").check_weights(None)  # nominal MPPI flies no pixel model


def test_the_race_command_reads_a_weights_files_record_for_its_camera(tmp_path):
    """`pixelmpc race --dof-weights FILE` flies the file's weights on the camera the weights' own record states."""
    from pixelmpc_jax import cli
    from pixelmpc_jax.commands import race as race_command

    out = tmp_path / "out"
    T.export_weights(DOFConfig().spec(), out / "dof_weights.msgpack", dof.load_packaged_dof(),
                     {**network_weights.weights_record(dof.PACKAGED_WEIGHTS), "camera_tilt_deg": TILT_DEG})
    parser = cli.build_parser()
    argv = ["race", "--controller", "pixelmpc", "--pixel-model", "dof", "--dof-weights",
            str(out / "dof_weights.msgpack"), "--camera-tilt"]
    race_command._check_race(parser.parse_args([*argv, "30"]))
    with pytest.raises(ValueError, match="trained for the camera tilted up 30 deg"):
        race_command._check_race(parser.parse_args([*argv, "0"]))
