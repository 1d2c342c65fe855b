"""Bad input gets one clear line, never a traceback or a silent wrong answer (issue 19).

The CLI rejects bad arguments before anything runs or is written (exit 2, one line naming the argument and
its range); library errors reaching the CLI print one line; interrupted work exits 130; the library rejects
what float32 cannot carry and wrong shapes with a ValueError; inside jit a non-finite plan is reset and
flagged; every JSON file the project writes is strict JSON.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

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
