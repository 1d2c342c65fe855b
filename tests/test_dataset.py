"""The DOF dataset's loaders on small hand-written datasets: laps and frames as written, the control input
variants, format-1 files, checksums and clear errors; the flown rates; the training-frame checks."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.learn import dataset as D

W, H = 16, 12


def _lap_arrays(frames: int, rng, with_flown: bool = True) -> dict:
    q = rng.normal(size=(frames + 1, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    states = np.concatenate([rng.normal(size=(frames + 1, 3)), q, rng.normal(size=(frames + 1, 3))], 1)
    states = states.astype(np.float32)
    arrays = {"flow": rng.normal(size=(frames, H, W, 2)).astype(np.float16), "q": states[:frames, 3:7].copy(),
              "u": rng.normal(size=(frames, 4)).astype(np.float32), "states": states,
              "target": np.zeros(frames + 1, np.int32), "meta_frames": np.asarray(frames)}
    if with_flown:
        arrays["w_flown"] = D.flown_rates(states)
    return arrays


def write_dataset(root, frames=(5, 3), with_flown: bool = True, seed: int = 0) -> list[dict]:
    """A dataset as collect writes it (lap 0 train, the others test), with random arrays; returns the laps'
    arrays."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    laps, entries = [], []
    for i, n in enumerate(frames):
        arrays = _lap_arrays(n, rng, with_flown)
        path = root / D.lap_filename(i)
        np.savez_compressed(path, **arrays)
        split = "train" if i == 0 else "test"
        entries.append({"lap": i, "file": path.name, "split": split, "frames": n, "speed": 6.0 + i, "seed": i,
                        "end": "timeout", "gates_passed": 0, "sha256": D.file_sha256(path)})
        laps.append(arrays)
    manifest = {"format": D.DATASET_FORMAT, "format_version": 2 if with_flown else 1, "image_size_wh": [W, H],
                "frame_dt_s": timing.CONTROL_DT, "config": {"laps": len(frames)},
                "split": {"train": [0], "test": list(range(1, len(frames)))}, "laps": entries,
                "frames": {s: sum(e["frames"] for e in entries if e["split"] == s) for s in ("train", "test")}}
    (root / D.MANIFEST).write_text(json.dumps(manifest))
    return laps


def test_load_dataset_and_laps_give_the_written_arrays(tmp_path):
    laps = write_dataset(tmp_path / "data", frames=(5, 3, 4))
    train = D.load_dataset(tmp_path / "data", "train")
    assert isinstance(train, D.FlowData) and train.flow.dtype == np.float16 and train.q.dtype == np.float32
    np.testing.assert_array_equal(train.q, laps[0]["q"])
    np.testing.assert_array_equal(train.flow, laps[0]["flow"])
    test = D.load_dataset(tmp_path / "data", "test")
    np.testing.assert_array_equal(test.u, np.concatenate([laps[1]["u"], laps[2]["u"]]))  # laps in order
    every = D.load_dataset(tmp_path / "data", "all")
    np.testing.assert_array_equal(every.flow, np.concatenate([lap["flow"] for lap in laps]))
    loaded = D.load_laps(tmp_path / "data", "test", with_flow=False)
    assert [lap.flow for lap in loaded] == [None, None]
    np.testing.assert_array_equal(loaded[1].states, laps[2]["states"])
    np.testing.assert_array_equal(loaded[1].w_flown, laps[2]["w_flown"])
    assert loaded[1].info["speed"] == 8.0 and loaded[1].info["frames"] == 4
    assert loaded[1].info["w_flown_source"] == "stored"


def test_the_control_input_is_the_command_or_the_flown_rates_with_the_thrust(tmp_path):
    laps = write_dataset(tmp_path / "data")
    flown = D.load_dataset(tmp_path / "data", "train", input="flown")
    np.testing.assert_array_equal(flown.u[:, :3], laps[0]["w_flown"])
    np.testing.assert_array_equal(flown.u[:, 3], laps[0]["u"][:, 3])  # the commanded thrust
    np.testing.assert_array_equal(D.load_dataset(tmp_path / "data", "train", input="command").u, laps[0]["u"])
    lap = D.load_laps(tmp_path / "data", "train")[0]
    np.testing.assert_array_equal(D.lap_input(lap, "flown"), flown.u)
    for call in (lambda: D.control_input(lap.u, lap.w_flown, "gyro"),
                 lambda: D.load_dataset(tmp_path / "data", "train", input="gyro")):
        with pytest.raises(ValueError, match="input must be one of"):
            call()


def test_format_1_laps_get_their_flown_rates_from_the_states(tmp_path):
    laps = write_dataset(tmp_path / "old", with_flown=False)
    lap = D.load_laps(tmp_path / "old", "train")[0]
    assert lap.info["w_flown_source"] == "states"
    np.testing.assert_array_equal(lap.w_flown, D.flown_rates(laps[0]["states"]))


def test_flown_rates_of_a_constant_rate_rotation_are_that_rate():
    params = quadrotor.QuadParams()
    x = quadrotor.hover_state((0.0, 0.0, 2.0), yaw=0.4)
    u = jnp.asarray([0.7, -1.1, 2.5, 9.0])
    states = [np.asarray(x)]
    for _ in range(3):  # three frames of 24 substeps each, as the plant integrates the attitude
        for _ in range(timing.SUBSTEPS_PER_TICK):
            x = quadrotor.step(x, u, timing.PLANT_DT, params)
        states.append(np.asarray(x))
    w = D.flown_rates(np.stack(states), timing.CONTROL_DT)
    assert w.shape == (3, 3) and w.dtype == np.float32
    np.testing.assert_allclose(w, np.tile(np.asarray(u[:3]), (3, 1)), atol=1e-4)
    # q and -q are the same attitude: the shorter rotation is taken
    flipped = np.stack(states)
    flipped[1, 3:7] *= -1
    np.testing.assert_allclose(D.flown_rates(flipped, timing.CONTROL_DT), w, atol=1e-4)


def _corrupt_middle(path):
    """Flip 64 bytes in the middle of a file (same size: a truncation check would not see it)."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(b ^ 0xFF for b in data[middle:middle + 64])
    path.write_bytes(bytes(data))


def test_clear_errors_for_missing_foreign_or_damaged_data(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        D.load_dataset(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="manifest.json is missing"):
        D.load_dataset(tmp_path)
    (tmp_path / D.MANIFEST).write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="not a pixelmpc_jax.flow_dataset manifest"):
        D.read_manifest(tmp_path)
    root = tmp_path / "data"
    write_dataset(root)
    with pytest.raises(ValueError, match="split"):
        D.load_dataset(root, "validation")
    (root / "lap_001.npz").unlink()
    with pytest.raises(FileNotFoundError, match="lap_001.npz: lap file listed in the manifest is missing"):
        D.load_dataset(root, "test")
    _corrupt_middle(root / "lap_000.npz")
    with pytest.raises(ValueError, match="lap_000.npz: damaged lap file .its sha256 differs"):
        D.load_dataset(root, "train")
    entry = D.read_manifest(root)["laps"][0]
    (root / "lap_000.npz").write_bytes(b"not an archive")
    with pytest.raises(ValueError, match="lap_000.npz: damaged lap file"):  # without a checksum: it does not load
        D.load_lap(root / "lap_000.npz", info={k: v for k, v in entry.items() if k != "sha256"})


def test_an_intact_lap_is_known_by_its_checksum_or_its_crc(tmp_path):
    write_dataset(tmp_path)
    path = tmp_path / "lap_000.npz"
    digest = D.file_sha256(path)
    assert D.intact_lap_sha256(path, digest) == digest
    assert D.intact_lap_sha256(path) == digest
    assert D.intact_lap_sha256(path, "0" * 64) is None
    assert D.lap_meta(path) == {"frames": 5}
    _corrupt_middle(path)
    assert D.intact_lap_sha256(path, digest) is None and D.intact_lap_sha256(path) is None
    assert D.intact_lap_sha256(tmp_path / "lap_009.npz") is None


def test_training_frames_are_checked_early():
    rng = np.random.default_rng(0)
    q, u, flow = rng.normal(size=(4, 4)), rng.normal(size=(4, 4)), rng.normal(size=(4, H, W, 2)).astype(np.float16)
    data = D.as_flow_data({"q": q, "u": u, "flow": flow}, W, H)
    assert isinstance(data, D.FlowData) and data.flow.shape == (4, H, W, 2)
    with pytest.raises(ValueError, match=r"flow must have shape \(F, H, W, 2\) = \(4, 153, 204, 2\)"):
        D.as_flow_data((q, u, flow))  # the paper's size by default
    with pytest.raises(ValueError, match=r"u must have shape \(F, 4\)"):
        D.as_flow_data((q, u[:3], flow), W, H)
    with pytest.raises(ValueError, match="flow must be float16 or float32"):
        D.as_flow_data((q, u, flow.astype(np.int16)), W, H)
    q[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"q contains non-finite values in frames \[2\]"):
        D.as_flow_data((q, u, flow), W, H)


def test_pixel_uv_centres():
    uv = D.pixel_uv(jnp.asarray([0, W - 1]), jnp.asarray([0, H - 1]), W, H)
    np.testing.assert_allclose(uv, [[0.5 / W, 0.5 / H], [1 - 0.5 / W, 1 - 0.5 / H]], rtol=1e-6)
