"""Scale-out: batched episodes split over 4 (forced) CPU devices equal the single-device run."""

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import standard_race
from conftest import xla_flags_for


def episodes() -> dict:
    """tests/standard_race.py's nominal MPPI, a batch of its laps at two speeds, on the devices this process has: its
    device count, states and ticks."""
    import jax
    import jax.numpy as jnp
    import standard_race

    from pixelmpc_jax.sim import env as env_lib
    from pixelmpc_jax.sim import episode as E
    from pixelmpc_jax.world import course as C

    nominal = standard_race.NOMINAL
    runner = E.make_runner(nominal.policy(), nominal.episode_config())
    worlds = env_lib.stack_worlds([env_lib.make_world(C.load_course(), target_speed=v) for v in (9.0, 12.0)])
    logs = runner.batch(worlds, jax.vmap(jax.random.PRNGKey)(jnp.arange(standard_race.BATCH)))
    return {"devices": jax.device_count(), "states": np.asarray(logs.states).tolist(),
            "ticks": np.asarray(logs.num_ticks).tolist()}


def script(function: str) -> str:
    """Python that prints this file's ``function()`` as JSON, for a process of its own (its devices set before JAX
    starts)."""
    return (f"import json, sys\nsys.path.insert(0, {str(Path(__file__).resolve().parent)!r})\n"
            f"from test_sharding import {function}\nprint(json.dumps({function}()))\n")


@functools.cache
def on_devices(function: str, device_count: int) -> dict:
    """This file's ``function()`` on ``device_count`` CPU devices: in this process where it has them (one, as a test
    process starts), else in a process of its own."""
    import jax

    if jax.device_count() == device_count:
        return globals()[function]()
    env = dict(os.environ)
    env["XLA_FLAGS"] = xla_flags_for(device_count)
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run([sys.executable, "-c", script(function)], env=env, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(device_count: int) -> dict:
    """:func:`episodes` on ``device_count`` CPU devices."""
    return on_devices("episodes", device_count)


def run_two_processes(devices_per_process: int = 2) -> list[dict]:
    """The same script as two JAX processes (jax.distributed on localhost), as on two hosts."""
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    init = ("from pixelmpc_jax.cli import _initialize_distributed\n_initialize_distributed()\n")
    procs = []
    for pid in range(2):
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"localhost:{port}",
                   JAX_NUM_PROCESSES="2", JAX_PROCESS_ID=str(pid),
                   XLA_FLAGS=xla_flags_for(devices_per_process))
        procs.append(subprocess.Popen([sys.executable, "-c", init + script("episodes")], env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, stderr[-2000:]
        outs.append(json.loads(stdout.strip().splitlines()[-1]))
    return outs


def test_four_device_run_equals_one_device_run():
    one, four = run(1), run(4)
    assert one["devices"] == 1 and four["devices"] == 4
    assert one["ticks"] == four["ticks"] == [standard_race.TICKS] * 2  # padded to 4 over 4 devices, cut back
    np.testing.assert_allclose(np.asarray(four["states"]), np.asarray(one["states"]), atol=1e-4)


@pytest.mark.slow  # ~22 s: the four-device run above covers the sharding, test_reliability the two processes
def test_two_processes_of_two_devices_equal_one_device_run():
    one = run(1)
    for out in run_two_processes(2):  # every process gets every episode back
        assert out["devices"] == 4 and out["ticks"] == one["ticks"]
        np.testing.assert_allclose(np.asarray(out["states"]), np.asarray(one["states"]), atol=1e-4)


def training() -> dict:
    """Six steps of DOF training on random flow, split over the devices this process has: its device count, the
    split, the losses and the weights."""
    import jax

    from pixelmpc_jax.learn import train as T
    from pixelmpc_jax.learn.dataset import FlowData
    from pixelmpc_jax.learn.dof_spec import DOFConfig

    rng = np.random.default_rng(0)
    n, W, H = 16, 16, 12
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    u = rng.normal(size=(n, 4)).astype(np.float32)
    flow = rng.normal(size=(n, H, W, 2)).astype(np.float16)
    model = DOFConfig(steps=6, batch_size=256, learning_rate=1e-3, schedule="constant", width=W, height=H, dt=0.025,
                      probe_size=64, eval_chunk_pixels=512)
    config = T.TrainConfig(model, log_every=1, checkpoint_every=0, progress=False)
    params, history = T.train(config, FlowData(q, u, flow))
    leaves = [np.asarray(x).ravel().tolist() for x in jax.tree_util.tree_leaves(params.weights)]
    return {"devices": jax.device_count(), "split": T.data_parallel_devices(256), "loss": history["loss"],
            "weights": leaves}


def test_dof_training_split_over_four_devices_equals_one_device():
    one, four = on_devices("training", 1), on_devices("training", 4)
    assert (one["devices"], one["split"]) == (1, 1) and (four["devices"], four["split"]) == (4, 4)
    np.testing.assert_allclose(four["loss"], one["loss"], rtol=1e-4)
    for a, b in zip(four["weights"], one["weights"]):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
