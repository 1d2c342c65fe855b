"""DOF data collection (Algorithm 1, first loop): lap files, flow conventions, resume, interrupt, loading."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from pixelmpc_jax.learn import dataset as D
from pixelmpc_jax.learn.train import FlowData
from pixelmpc_jax.perception import flow as flow_lib

H, W = 153, 204
# Two 1 s laps (40 ticks each) with a small MPPI: lap 0 train at 6 m/s, lap 1 test at 14 m/s.
TINY = D.CollectConfig(laps=2, max_lap_time_s=1.0, num_samples=64, test_laps=(1,), render_batch=16)
FRAMES = 40


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("dof_data")
    manifest = D.collect(root, TINY, progress=False)
    assert manifest["complete"]
    return root


def test_config_speeds_split_and_paper_size():
    config = D.CollectConfig(laps=10)
    assert config.speeds()[0] == 6.0 and config.speeds()[-1] == 14.0
    assert np.allclose(np.diff(config.speeds()), 8.0 / 9.0)
    assert config.test_indices() == [2, 7]  # interior speeds, one per block of five
    assert D.CollectConfig(laps=4).test_indices() == [2]
    assert D.CollectConfig(laps=2).test_indices() == [1]  # none by the rule: the last lap
    assert D.CollectConfig(laps=1).test_indices() == []
    paper = D.CollectConfig.paper()
    assert (paper.laps, paper.max_lap_time_s) == (10, 30.0)
    assert paper.seeds() == list(range(10))
    for bad in (dict(laps=0), dict(speed_min=10.0, speed_max=6.0), dict(supersample=2), dict(exact_flow="x"),
                dict(laps=2, test_laps=(2,))):
        with pytest.raises(ValueError):
            D.CollectConfig(**bad)


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
    manifest = D.collect(tiny_dir, TINY, progress=False)
    assert manifest["complete"] and manifest["wall_s_this_call"] < 5.0
    assert {p.name: p.stat().st_mtime_ns for p in tiny_dir.glob("lap_*.npz")} == before
    flow_before = D.load_dataset(tiny_dir, "test").flow
    (tiny_dir / "lap_001.npz").unlink()
    manifest = D.collect(tiny_dir, TINY, progress=False)
    assert manifest["complete"] and manifest["frames"]["test"] == FRAMES
    assert (tiny_dir / "lap_000.npz").stat().st_mtime_ns == before["lap_000.npz"]
    np.testing.assert_array_equal(D.load_dataset(tiny_dir, "test").flow, flow_before)  # seeded: the same lap
    with pytest.raises(ValueError, match="another config"):
        D.collect(tiny_dir, D.CollectConfig(laps=3, max_lap_time_s=1.0, num_samples=64), progress=False)


def test_interrupt_keeps_finished_laps(tmp_path, monkeypatch):
    fly = D.fly_lap
    calls = []

    def fly_then_interrupt(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return fly(*args, **kwargs)

    monkeypatch.setattr(D, "fly_lap", fly_then_interrupt)
    config = TINY  # the runner compiled for the fixture is reused
    manifest = D.collect(tmp_path, config, progress=False)
    assert not manifest["complete"]
    assert [e["lap"] for e in manifest["laps"]] == [0]
    assert sorted(os.listdir(tmp_path)) == ["lap_000.npz", D.MANIFEST]  # no temp files left
    assert json.loads((tmp_path / D.MANIFEST).read_text())["complete"] is False


def test_clear_errors_for_missing_or_damaged_data(tiny_dir, tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        D.load_dataset(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="manifest.json is missing"):
        D.load_dataset(tmp_path)
    with pytest.raises(ValueError, match="split"):
        D.load_dataset(tiny_dir, "validation")
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / D.MANIFEST).write_text((tiny_dir / D.MANIFEST).read_text())
    (damaged / "lap_000.npz").write_bytes((tiny_dir / "lap_000.npz").read_bytes()[:1000])
    with pytest.raises(ValueError, match="lap_000.npz: damaged lap file"):
        D.load_dataset(damaged, "train")
    with pytest.raises(FileNotFoundError, match="lap_001.npz"):
        D.load_dataset(damaged, "test")
