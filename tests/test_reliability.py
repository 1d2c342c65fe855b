"""Bad input gets one clear line, never a traceback or a silent wrong answer (issue 19).

The CLI rejects bad arguments before anything runs or is written (exit 2, one line naming the argument and
its range); library errors reaching the CLI print one line; interrupted work exits 130; the library rejects
what float32 cannot carry and wrong shapes with a ValueError; inside jit a non-finite plan is reset and
flagged; every JSON file the project writes is strict JSON.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------------------------------
# --distributed from the command line.
# --------------------------------------------------------------------------------------------------


def test_importing_the_cli_and_building_its_parser_starts_no_jax_backend():
    code = ("import pixelmpc_jax.cli as cli\ncli.build_parser()\n"
            "from jax._src import xla_bridge\nprint(sorted(xla_bridge._backends))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, JAX_PLATFORMS="cpu"), cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_distributed_version_runs_as_two_local_processes():
    """The real command, ``pixelmpc --distributed version``, as two processes on the loopback interface."""
    port = _free_port()
    procs = []
    for pid in range(2):
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
                   JAX_NUM_PROCESSES="2", JAX_PROCESS_ID=str(pid))
        procs.append(subprocess.Popen([sys.executable, "-m", "pixelmpc_jax.cli", "--distributed", "version"],
                                      env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = []
    try:
        for proc in procs:
            stdout, stderr = proc.communicate(timeout=120)
            outs.append((proc.returncode, stdout, stderr))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    for pid, (code, stdout, stderr) in enumerate(outs):
        assert code == 0, stderr[-2000:]
        assert f"process {pid} of 2" in stdout and "2 global device(s)" in stdout
        assert "pixelmpc-jax" in stdout


# --------------------------------------------------------------------------------------------------
# Strict JSON everywhere.
# --------------------------------------------------------------------------------------------------


def strict_loads(text: str):
    """json.loads that fails on NaN, Infinity and -Infinity (what a strict parser rejects)."""

    def reject(constant):
        raise AssertionError(f"non-strict JSON: {constant}")

    return json.loads(text, parse_constant=reject)


def test_json_writer_turns_non_finite_numbers_into_null(tmp_path):
    from pixelmpc_jax.sim import race
    from pixelmpc_jax.strict_json import dumps, write_json_atomic

    data = {"speed": float("inf"), "laps": [float("nan"), -float("inf"), np.float32("nan"), np.float64(2.5)],
            "array": np.asarray([1.0, np.nan]), 3: np.int64(7), "nested": ({"x": np.float32(np.inf)},)}
    expected = {"speed": None, "laps": [None, None, None, 2.5], "array": [1.0, None], "3": 7,
                "nested": [{"x": None}]}
    write_json_atomic(tmp_path / "a.json", data)
    assert strict_loads((tmp_path / "a.json").read_text()) == expected
    race.write_json_atomic(tmp_path / "b.json", data)  # the name the rest of the project uses
    assert strict_loads((tmp_path / "b.json").read_text()) == expected
    assert strict_loads(dumps(data)) == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json"]  # no temporary files left


def test_checkpoint_config_with_nan_is_stored_as_strict_json(tmp_path):
    import jax
    from flax import serialization

    from pixelmpc_jax.dynamics import dof

    params = dof.init_dof_params(jax.random.key(0))
    dof.save_checkpoint(tmp_path / "w.msgpack", params, {"results": {"test_aee_px": float("nan")}, "lr": 1e-3})
    payload = serialization.msgpack_restore((tmp_path / "w.msgpack").read_bytes())
    assert strict_loads(payload["config"]) == {"results": {"test_aee_px": None}, "lr": 1e-3}
    assert dof.load_checkpoint(tmp_path / "w.msgpack")[1]["results"]["test_aee_px"] is None
