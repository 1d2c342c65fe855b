"""Execution.sample_devices: one step's samples split over (forced) CPU devices give the one-device step, and
the `pixelmpc` command splits the CPU into devices where it should."""

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

from pixelmpc_jax import devices, host
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi

SCRIPT = r"""
import json, sys
from pixelmpc_jax import devices, host
count = host.split_host_cpu(2)  # before JAX starts
import jax, jax.numpy as jnp, numpy as np
from pixelmpc_jax.apps.bench import problems
from pixelmpc_jax.sim import episode as E
from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi
from pixelmpc_jax.world import course as C
from pixelmpc_jax.sim import env as env_lib

out = {"devices": count, "usable_512": devices.usable_sample_devices(512),
       "usable_63": devices.usable_sample_devices(63)}
steps = {}
for k in (1, 2):
    p = problems.pixelmpc_problem(64, 12, 0.15, sample_devices=k)
    state, rows = p.state, []
    for _ in range(3):
        u, state, info = p.ctrl.step(state, p.x0, p.params)
        rows.append({"u": np.asarray(u).tolist(), "plan": np.asarray(state.plan).tolist(),
                     "costs": np.asarray(info.costs).tolist()})
    steps[k] = rows
    if k == 2:
        out["costs_shard_shape"] = list(info.costs.sharding.shard_shape(info.costs.shape))
        out["compilations"] = p.ctrl.num_compilations()
out["steps"] = steps
try:  # 63 samples do not split over two devices
    devices.compile_controller(make_mppi(MPPIConfig(num_samples=63, horizon=4, noise_sigma=(1.0,)),
                                         lambda x, u, p: x + u, lambda x, u, t, p: x[0] ** 2),
                               devices.Execution(sample_devices=2))
except ValueError as err:
    out["uneven"] = str(err)
sys.path.insert(0, TESTS)
import standard_race  # its nominal MPPI: on one device, the episode the suite compiles anyway

spec = standard_race.NOMINAL
world = env_lib.make_world(C.load_course(), target_speed=spec.speed)
log = E.make_runner(spec.policy(sample_devices=2), spec.episode_config()).single(world, jax.random.PRNGKey(3))
out["lap"] = {"states": np.asarray(log.states).tolist(), "ticks": int(log.num_ticks)}
print(json.dumps(out))
"""


@functools.cache
def two_devices() -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env["XLA_FLAGS"] = xla_flags_for()
    script = f"TESTS = {str(Path(__file__).resolve().parent)!r}\n" + SCRIPT
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_split_host_cpu_makes_devices_and_the_step_splits_its_samples_over_them():
    out = two_devices()
    assert out["devices"] == 2
    assert out["usable_512"] == 2 and out["usable_63"] == 1  # 63 samples do not split over two
    assert out["costs_shard_shape"] == [32]  # each device holds (and computed) half of the 64 samples' costs
    assert out["compilations"] == 1


def test_samples_over_two_devices_give_the_one_device_step():
    one, two = (two_devices()["steps"][k] for k in ("1", "2"))
    for a, b in zip(one, two):  # the same samples, so the same costs; the plan up to float rounding
        np.testing.assert_allclose(b["costs"], a["costs"], rtol=1e-6)
        np.testing.assert_allclose(b["plan"], a["plan"], atol=1e-5)
        np.testing.assert_allclose(b["u"], a["u"], atol=1e-5)


def test_a_lap_with_its_samples_over_two_devices_flies_the_one_device_lap():
    """The standard nominal lap with its samples over two devices (in a process of two) against the same lap on one
    device, flown here."""
    import jax

    from pixelmpc_jax.sim import env as env_lib
    from pixelmpc_jax.sim import episode as E
    from pixelmpc_jax.world import course as C

    spec = standard_race.NOMINAL
    world = env_lib.make_world(C.load_course(), target_speed=spec.speed)
    one = E.make_runner(spec.policy(), spec.episode_config()).single(world, jax.random.PRNGKey(3))
    two = two_devices()["lap"]
    assert int(one.num_ticks) == two["ticks"] == standard_race.TICKS
    np.testing.assert_allclose(np.asarray(two["states"])[:21], np.asarray(one.states)[:21], atol=1e-3)


def test_sample_devices_is_checked_before_anything_runs():
    assert "does not split evenly over sample_devices=2" in two_devices()["uneven"]
    with pytest.raises(ValueError, match="positive integer"):
        devices.Execution(sample_devices=0)
    import jax

    present = len(jax.local_devices())
    config = MPPIConfig(num_samples=8 * (present + 1), horizon=4, noise_sigma=(1.0,))
    ctrl = make_mppi(config, lambda x, u, p: x + u, lambda x, u, t, p: x[0] ** 2)
    with pytest.raises(ValueError, match="split_host_cpu"):
        devices.compile_controller(ctrl, devices.Execution(sample_devices=present + 1))


def test_split_host_cpu_after_jax_started_changes_nothing():
    import jax

    before = len(jax.devices("cpu"))
    assert host.split_host_cpu(before + 3) == before
    with pytest.raises(ValueError):
        host.split_host_cpu(0)


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env["XLA_FLAGS"] = xla_flags_for()
    return subprocess.run([sys.executable, "-m", "pixelmpc_jax.cli", *args], env=env, capture_output=True,
                          text=True, timeout=300)


def test_the_command_splits_the_cpu_on_request_and_refuses_a_bad_count():
    out = _cli("--cpu-devices", "2", "version")
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("CpuDevice") == 2
    out = _cli("version")  # not a command that splits by default
    assert out.returncode == 0 and out.stdout.count("CpuDevice") == 1
    out = _cli("--cpu-devices", "0", "version")
    assert out.returncode == 2 and "--cpu-devices" in out.stderr


def test_cpu_matmul_auto_takes_ynnpack_on_one_cpu_device_only_and_gives_the_same_step():
    import jax

    from pixelmpc_jax.apps.bench import problems
    from pixelmpc_jax.control import pixelmpc as pixelmpc_lib
    from pixelmpc_jax.sim.controllers import make_policy

    assert devices.compiler_options("auto", 1) == devices.YNNPACK_MATMULS  # the tests run on a CPU
    assert devices.compiler_options("auto", 2) is None and devices.compiler_options("xla", 1) is None
    assert devices.compiler_options("ynnpack", 2) == devices.YNNPACK_MATMULS
    with pytest.raises(ValueError, match="cpu_matmul"):
        devices.Execution(cpu_matmul="mkl")
    steps = {}
    for matmul in ("xla", "auto"):
        problem = problems.pixelmpc_problem(64, 12, 0.15)
        ctrl = devices.compile_controller(pixelmpc_lib.make_pixelmpc(problem.config),
                                          devices.Execution(cpu_matmul=matmul))
        state = ctrl.init(jax.random.PRNGKey(0), np.asarray([0.0, 0.0, 0.0, 9.81], np.float32))
        steps[matmul] = ctrl.step(state, problem.x0, problem.params)
        assert ctrl.compiler_options == devices.compiler_options(matmul, 1)
        assert ctrl.step_options() == ctrl.compiler_options  # 64 x 128 x 128: below AUTO_XLA_FROM_MACS
    (u_x, s_x, i_x), (u_y, s_y, i_y) = steps["xla"], steps["auto"]
    np.testing.assert_allclose(u_y, u_x, atol=1e-5)
    np.testing.assert_allclose(i_y.costs, i_x.costs, rtol=1e-5)
    np.testing.assert_allclose(s_y.plan, s_x.plan, atol=1e-5)
    small = pixelmpc_lib.paper_mppi_config(num_samples=64, horizon=12)
    policy = make_policy("pixelmpc", pixelmpc_lib.ControllerConfig(mppi=small, t_f=0.15))
    assert policy.compiler_options == devices.YNNPACK_MATMULS  # the episode's jit compiles with them


def test_cpu_matmul_auto_keeps_xlas_kernels_where_the_steps_largest_product_is_large():
    """"auto" reads the traced step at its first call: a product of AUTO_XLA_FROM_MACS multiply-adds or more (inside
    the rollout's scan and the samples' vmap) keeps XLA's kernels, the plain jit's own options; a smaller one takes
    YNNPACK's. Either way the step computes what the plain jit does."""
    import jax
    import jax.numpy as jnp

    from pixelmpc_jax.control.mppi import MPPIConfig, make_mppi

    width = 128
    weights = jnp.eye(width, dtype=jnp.float32) * 0.5

    def dynamics(x, u, params):  # one sample: a (width,) state through a width x width product
        return jnp.tanh(x @ weights) + u[0]

    def cost(x, u, t, params):
        return jnp.sum(x**2)

    x0 = jnp.ones(width, jnp.float32)
    for num_samples, kernels in ((devices.AUTO_XLA_FROM_MACS // width**2, None), (64, devices.YNNPACK_MATMULS)):
        config = MPPIConfig(num_samples=num_samples, horizon=3, noise_sigma=(0.5,), u_min=(-1.0,), u_max=(1.0,))
        ctrl = make_mppi(config, dynamics, cost)
        state = ctrl.init(jax.random.PRNGKey(0), jnp.zeros(1))
        assert devices.largest_product(jax.make_jaxpr(ctrl.step)(state, x0, None)) == num_samples * width * width
        compiled = devices.compile_controller(ctrl)
        with pytest.raises(ValueError, match="first call"):
            compiled.step_options()
        u, _, _ = compiled.step(state, x0, None)
        assert compiled.step_options() == kernels and compiled.num_compilations() == 1
        u_plain, _, _ = jax.jit(ctrl.step)(state, x0, None)
        np.testing.assert_allclose(u, u_plain, atol=1e-5)
    assert devices.largest_product(jax.make_jaxpr(lambda x: x + 1.0)(x0)) == 0
