"""DOF data collection (Algorithm 1, first loop): lap files, flow conventions, resume, interrupt, checksums,
excitation, and the collected files through the loaders."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import standard_race
from conftest import made_once_per_run

from pixelmpc_jax.learn import collect as C
from pixelmpc_jax.learn import dataset as D
from pixelmpc_jax.learn import train as T
from pixelmpc_jax.learn.dataset import FlowData
from pixelmpc_jax.learn.dof_spec import DOFConfig
from pixelmpc_jax.perception import flow as flow_lib
from pixelmpc_jax.sim import policies

H, W = 153, 204
# Two 1 s laps (40 ticks each) with a small MPPI: lap 0 train at 6 m/s, lap 1 test at 14 m/s. Its nominal MPPI is
# tests/standard_race.py's, the episode the suite compiles once.
TINY = C.CollectConfig(laps=2, max_lap_time_s=standard_race.MAX_TIME_S, num_samples=standard_race.SAMPLES,
                       test_laps=(1,), render_batch=16)
FRAMES = 40


def collect_tiny(root) -> None:
    """The tiny dataset, as tests/test_evaluate.py collects it too (made once per run: conftest.made_once_per_run)."""
    assert C.collect(root, TINY, progress=False)["complete"]


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny") / "dof_data"
    shutil.copytree(made_once_per_run("tiny_collection", collect_tiny), root)  # the tests below change it
    return root


def test_config_speeds_split_and_paper_size():
    config = C.CollectConfig(laps=10)
    assert config.speeds()[0] == 6.0 and config.speeds()[-1] == 14.0
    assert np.allclose(np.diff(config.speeds()), 8.0 / 9.0)
    assert config.test_indices() == [2, 7]  # interior speeds, one per block of five
    assert C.CollectConfig(laps=4).test_indices() == [2]
    assert C.CollectConfig(laps=2).test_indices() == [1]  # none by the rule: the last lap
    assert C.CollectConfig(laps=1).test_indices() == []
    paper = C.CollectConfig.paper()
    assert (paper.laps, paper.max_lap_time_s) == (10, 30.0)
    assert paper.seeds() == list(range(10))
    for bad in (dict(laps=0), dict(speed_min=10.0, speed_max=6.0), dict(supersample=2), dict(exact_flow="x"),
                dict(laps=2, test_laps=(2,))):
        with pytest.raises(ValueError):
            C.CollectConfig(**bad)


def test_lap_files_hold_the_expected_arrays(tiny_dir):
    manifest = json.loads((tiny_dir / D.MANIFEST).read_text())
    assert manifest["split"] == {"train": [0], "test": [1]}
    assert manifest["frames"] == {"train": FRAMES, "test": FRAMES}
    assert [e["speed"] for e in manifest["laps"]] == [6.0, 14.0]
    assert [e["seed"] for e in manifest["laps"]] == [0, 1]
    assert manifest["config"] == TINY.to_json()
    assert "jax" in manifest["versions"] and "opencv" in manifest["versions"]
    with np.load(tiny_dir / "lap_000.npz") as lap:
        assert lap["flow"].dtype == np.float16 and lap["flow"].shape == (FRAMES, H, W, 2)
        assert lap["q"].dtype == np.float32 and lap["q"].shape == (FRAMES, 4)
        assert lap["u"].dtype == np.float32 and lap["u"].shape == (FRAMES, 4)
        assert lap["states"].shape == (FRAMES + 1, 10) and lap["target"].shape == (FRAMES + 1,)
        assert lap["target"].dtype == np.int32
        np.testing.assert_array_equal(lap["q"], lap["states"][:FRAMES, 3:7])
        assert np.all(lap["u"][:, 3] > 0)  # thrust
        assert "exact_flow" not in lap.files  # train lap: Farneback only
        assert np.all(np.isfinite(lap["flow"].astype(np.float32)))
    with np.load(tiny_dir / "lap_001.npz") as lap:
        assert lap["exact_flow"].dtype == np.float16 and lap["exact_flow"].shape == (FRAMES, H, W, 2)
        assert lap["exact_valid"].dtype == bool and lap["exact_valid"].shape == (FRAMES, H, W)
        assert lap["exact_valid"].mean() > 0.5


def test_farneback_agrees_with_the_exact_flow(tiny_dir):
    """Same convention (flow[y, x] = (du, dv), frame t -> t + 1): Farneback is far closer to the exact flow
    than zero flow or the axis-swapped field, on the later (faster) frames of the 14 m/s lap."""
    lap = D.load_laps(tiny_dir, "test")[0]
    sl = slice(20, FRAMES)
    fb = lap.flow[sl].astype(np.float32)
    exact, valid = lap.exact_flow[sl].astype(np.float32), lap.exact_valid[sl]
    error = flow_lib.average_endpoint_error(fb, exact, valid)
    zero = flow_lib.average_endpoint_error(np.zeros_like(exact), exact, valid)
    swapped = flow_lib.average_endpoint_error(fb[..., ::-1], exact, valid)
    assert zero > 1.0
    assert error < 0.4 * zero
    assert error < 0.5 * swapped


def test_load_dataset_round_trip(tiny_dir):
    train = D.load_dataset(tiny_dir, "train")
    assert isinstance(train, FlowData)
    assert train.q.shape == (FRAMES, 4) and train.flow.shape == (FRAMES, H, W, 2)
    assert train.flow.dtype == np.float16
    with np.load(tiny_dir / "lap_000.npz") as lap:
        np.testing.assert_array_equal(train.flow, lap["flow"])
        np.testing.assert_array_equal(train.u, lap["u"])
    both = D.load_dataset(tiny_dir, "all")
    test = D.load_dataset(tiny_dir, "test")
    np.testing.assert_array_equal(both.flow[FRAMES:], test.flow)
    laps = D.load_laps(tiny_dir, "test", with_flow=False)
    assert laps[0].flow is None and laps[0].states.shape == (FRAMES + 1, 10)
    assert laps[0].info["speed"] == 14.0 and laps[0].info["split"] == "test"


def test_second_collect_skips_and_a_deleted_lap_is_recollected(tiny_dir):
    before = {p.name: p.stat().st_mtime_ns for p in tiny_dir.glob("lap_*.npz")}
    manifest = C.collect(tiny_dir, TINY, progress=False)
    assert manifest["complete"] and manifest["wall_s_this_call"] < 5.0 and not manifest["interrupted"]
    assert {p.name: p.stat().st_mtime_ns for p in tiny_dir.glob("lap_*.npz")} == before
    flow_before = D.load_dataset(tiny_dir, "test").flow
    (tiny_dir / "lap_001.npz").unlink()
    manifest = C.collect(tiny_dir, TINY, progress=False)
    assert manifest["complete"] and manifest["frames"]["test"] == FRAMES
    assert (tiny_dir / "lap_000.npz").stat().st_mtime_ns == before["lap_000.npz"]
    np.testing.assert_array_equal(D.load_dataset(tiny_dir, "test").flow, flow_before)  # seeded: the same lap
    with pytest.raises(ValueError, match="another config"):
        C.collect(tiny_dir, C.CollectConfig(laps=3, max_lap_time_s=1.0, num_samples=64), progress=False)


def test_interrupt_keeps_finished_laps(tmp_path, monkeypatch):
    fly = C.fly_lap
    calls = []

    def fly_then_interrupt(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return fly(*args, **kwargs)

    monkeypatch.setattr(C, "fly_lap", fly_then_interrupt)
    config = TINY  # the runner compiled for the fixture is reused
    manifest = C.collect(tmp_path, config, progress=False)
    assert not manifest["complete"] and manifest["interrupted"]  # (pixelmpc collect exits 130)
    assert [e["lap"] for e in manifest["laps"]] == [0]
    assert sorted(os.listdir(tmp_path)) == ["lap_000.npz", D.MANIFEST]  # no temp files left
    assert json.loads((tmp_path / D.MANIFEST).read_text())["complete"] is False


def _corrupt_middle(path):
    """Flip 64 bytes in the middle of a file (same size: a truncation check would not see it)."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(b ^ 0xFF for b in data[middle:middle + 64])
    path.write_bytes(bytes(data))


def test_a_lap_file_with_corrupted_bytes_is_flown_again(tiny_dir, tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny_dir, copy)
    original = (tiny_dir / "lap_000.npz").read_bytes()
    recorded = {e["lap"]: e["sha256"] for e in D.read_manifest(tiny_dir)["laps"]}
    assert recorded[0] == D.file_sha256(tiny_dir / "lap_000.npz")
    _corrupt_middle(copy / "lap_000.npz")
    with pytest.raises(ValueError, match="lap_000.npz: damaged lap file .its sha256 differs"):  # loaders refuse it
        D.load_dataset(copy, "train")
    manifest = C.collect(copy, TINY, progress=False)
    assert "lap_000.npz: damaged (its checksum does not match); flying lap 0 again" in capsys.readouterr().err
    assert manifest["complete"] and (copy / "lap_000.npz").read_bytes() == original  # seeded: the same lap
    assert [e["sha256"] for e in manifest["laps"]] == [recorded[0], recorded[1]]
    # Without a recorded checksum (a lap saved just before an interruption), the archive's CRC check decides.
    _corrupt_middle(copy / "lap_001.npz")
    stored = json.loads((copy / D.MANIFEST).read_text())
    stored["laps"] = stored["laps"][:1]
    (copy / D.MANIFEST).write_text(json.dumps(stored))
    assert D.intact_lap_sha256(copy / "lap_001.npz") is None
    assert D.intact_lap_sha256(tiny_dir / "lap_001.npz") == recorded[1]


# --------------------------------------------------------------------------------------------------
# Flown rates, old datasets, excitation.
# --------------------------------------------------------------------------------------------------


def test_lap_files_store_the_rates_flown_over_each_frame(tiny_dir):
    manifest = json.loads((tiny_dir / D.MANIFEST).read_text())
    assert manifest["format_version"] == 2 and "w_flown" in manifest["flown_rates"]
    assert manifest["excited_laps"] == []
    with np.load(tiny_dir / "lap_001.npz") as lap:
        w, rates, u = lap["w_flown"], lap["rates"], lap["u"]
        assert w.shape == (FRAMES, 3) and rates.shape == (FRAMES + 1, 3)
        np.testing.assert_allclose(w, D.flown_rates(lap["states"]), atol=1e-6)
    # The mean rate over a tick lies between the true rates at its two ends (the rate loop is smooth).
    trapezoid = 0.5 * (rates[:-1] + rates[1:])
    assert np.max(np.abs(w - trapezoid)) < 0.05 + 0.05 * np.max(np.abs(trapezoid))
    assert np.max(np.abs(w - u[:, :3])) > 0.05  # and it is not the command
    test = D.load_dataset(tiny_dir, "test", input="flown")
    np.testing.assert_array_equal(test.u[:, :3], w)
    np.testing.assert_array_equal(test.u[:, 3], u[:, 3])  # the commanded thrust
    np.testing.assert_array_equal(D.load_dataset(tiny_dir, "test", input="command").u, u)
    assert D.load_laps(tiny_dir, "test")[0].info["w_flown_source"] == "stored"
    with pytest.raises(ValueError, match="input"):
        D.load_dataset(tiny_dir, "test", input="gyro")


def _strip_to_format_1(src, dst):
    """A copy of a dataset as format 1 wrote it: no flown rates in the lap files, no excitation fields."""
    dst.mkdir()
    manifest = json.loads((src / D.MANIFEST).read_text())
    manifest["format_version"] = 1
    for key in [k for k in manifest["config"] if k.startswith("excitation")]:
        del manifest["config"][key]
    for key in ("flown_rates", "excited_laps"):
        manifest.pop(key)
    for entry in manifest["laps"]:
        entry.pop("excited")
        entry.pop("sha256")  # format 1 recorded no checksums
        with np.load(src / entry["file"]) as data:
            arrays = {k: data[k] for k in data.files if k not in D.FLOWN_KEYS and k != "meta_excited"}
        np.savez_compressed(dst / entry["file"], **arrays)
        entry["bytes"] = (dst / entry["file"]).stat().st_size
    (dst / D.MANIFEST).write_text(json.dumps(manifest))
    return manifest


def test_old_datasets_without_flown_rates_load_train_and_resume(tiny_dir, tmp_path):
    old = tmp_path / "old"
    _strip_to_format_1(tiny_dir, old)
    with zipfile.ZipFile(old / "lap_000.npz") as archive:
        assert not {"w_flown.npy", "rates.npy"} & set(archive.namelist())
    for split in ("train", "test"):
        for input in D.INPUTS:  # the flown rates are derived from the stored states: the same numbers
            np.testing.assert_array_equal(D.load_dataset(old, split, input=input).u,
                                          D.load_dataset(tiny_dir, split, input=input).u)
    assert D.load_laps(old, "train")[0].info["w_flown_source"] == "states"
    config = T.TrainConfig(DOFConfig(steps=3, batch_size=64, probe_size=64, input="flown"), log_every=1,
                           checkpoint_every=0, progress=False)
    params, history = T.train(config, D.load_dataset(old, "train", input="flown"),
                              D.load_dataset(old, "test", input="flown"))
    assert history["step"] == [1, 2, 3] and np.isfinite(history["results"]["test_aee_px"])
    # Collecting into it again with the config it was made with reuses it (the new fields at their defaults).
    before = {p.name: p.stat().st_mtime_ns for p in old.glob("lap_*.npz")}
    manifest = C.collect(old, TINY, progress=False)
    assert manifest["complete"] and manifest["format_version"] == 1
    assert {p.name: p.stat().st_mtime_ns for p in old.glob("lap_*.npz")} == before
    with pytest.raises(ValueError, match="another config"):
        C.collect(old, C.CollectConfig(**{**TINY.to_json(), "test_laps": (1,), "excitation": True}),
                  progress=False)


def _constant_policy(u):
    return policies.Policy(init=lambda key, world: jnp.zeros(()),
                              act=lambda state, obs, world: (jnp.asarray(u), state, jnp.zeros((2, 10))),
                              name="constant")


def test_excited_policy_adds_held_pulses_within_the_rate_bounds():
    base_u = jnp.asarray([5.5, 0.0, -1.0, 9.0])
    policy = C.excited_policy(_constant_policy(base_u), pulse_rad_s=1.5, hold_s=0.3, gap_s=0.5, dither_rad_s=0.0)
    state = policy.init(jax.random.key(3), None)
    act = jax.jit(lambda s: policy.act(s, None, None))
    us = []
    for _ in range(400):
        u, state, _ = act(state)
        us.append(np.asarray(u))
    us = np.stack(us)
    np.testing.assert_array_equal(us[:, 3], 9.0)  # thrust untouched
    offset = us[:, :3] - np.asarray(base_u[:3])
    assert np.all(us[:, :3] <= 6.0 + 1e-6) and np.all(us[:, :3] >= -6.0 - 1e-6)  # the MPPI's rate bounds
    for axis in (1, 2):  # unclipped axes: pulses of at most 1.5 rad/s, held for 4-12 ticks, off between
        on = np.abs(offset[:, axis]) > 1e-6
        assert 0.15 < on.mean() < 0.7
        assert np.max(np.abs(offset[:, axis])) <= 1.5 + 1e-6
        changes = np.nonzero(np.diff(offset[:, axis]))[0]
        runs = np.diff(changes)
        assert runs.min() >= 1 and np.median(runs) >= 3
    assert np.max(offset[:, 0]) <= 0.5 + 1e-6  # clipped at 6 rad/s
    dithered = C.excited_policy(_constant_policy(base_u), pulse_rad_s=0.0, dither_rad_s=0.3)
    state = dithered.init(jax.random.key(0), None)
    u, _, _ = dithered.act(state, None, None)
    assert 0 < np.max(np.abs(np.asarray(u[1:3]) - np.asarray(base_u[1:3]))) < 1.5


# ~20 s (a collection of its own): test_excited_policy_adds_held_pulses_within_the_rate_bounds covers the excitation,
# the tiny collection the rest of this file reads covers collect
@pytest.mark.slow
def test_collect_with_excitation_excites_the_train_laps_only(tmp_path):
    config = dataclasses.replace(TINY, excitation=True)  # its test lap flies TINY's runner
    assert [config.excited(i) for i in range(2)] == [True, False]
    manifest = C.collect(tmp_path, config, progress=False)
    assert manifest["excited_laps"] == [0] and [e["excited"] for e in manifest["laps"]] == [True, False]
    train = D.load_laps(tmp_path, "train", with_flow=False)[0]
    assert np.all(np.isfinite(train.w_flown)) and np.all(np.abs(train.u[:, :3]) <= 6.0 + 1e-6)
