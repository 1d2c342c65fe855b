"""The one atomic file writer: a complete new file or the old one, never a half-written one."""

from __future__ import annotations

import json
import stat

import numpy as np
import pytest

from pixelmpc_jax import strict_json


def test_write_atomic_writes_the_whole_file_readable_by_all(tmp_path):
    path = tmp_path / "lap.npz"
    strict_json.write_atomic(path, lambda f: np.savez_compressed(f, a=np.arange(5)))
    with np.load(path) as data:
        np.testing.assert_array_equal(data["a"], np.arange(5))
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["lap.npz"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path):
    path = tmp_path / "results.json"
    strict_json.write_json_atomic(path, {"laps": 3})

    def half_then_fail(f):
        f.write(b'{"laps": ')
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        strict_json.write_atomic(path, half_then_fail)
    assert json.loads(path.read_text()) == {"laps": 3}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_json_files_are_written_as_before(tmp_path):
    """The JSON writer's bytes: ``json.dumps`` of the strict-safe data (NaN as null), indented."""
    data = {"speed": float("nan"), "laps": [1, 2.5]}
    strict_json.write_json_atomic(tmp_path / "a.json", data)
    assert (tmp_path / "a.json").read_text() == json.dumps({"speed": None, "laps": [1, 2.5]}, indent=2)
