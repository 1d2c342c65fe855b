"""The controller step: PixelMPC (DOF pixel model over t_f = 1 s) and nominal MPPI at the paper's sizes,
scaling over N and T, and the step's fraction of this device's matmul rate.

Every timed call is the compiled step (:func:`~pixelmpc_jax.devices.compile_controller`) with the MPPI state carried
from call to call.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.apps.bench import problems, roofline
from pixelmpc_jax.apps.bench.measure import make_row, measure
from pixelmpc_jax.devices import usable_sample_devices
from pixelmpc_jax.dynamics import dof as dof_lib
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import course as course_lib

GROUP = "controller"
SCALING_SAMPLES = (128, 512, 2048, 8192, 32768)
SCALING_HORIZONS = (20, 40, 80, 160)
PIXELMPC_NAME = "PixelMPC step (DOF, t_f=1 s)"
NOMINAL_NAME = "nominal MPPI step (quadrotor + racing cost)"


def _rates(row: dict) -> dict:
    n, t, median = row["num_samples"], row["horizon"], row["median_ms"]
    return {"samples_per_s": n / (median / 1e3), "sample_steps_per_s": n * t / (median / 1e3)}


ONE_DEVICE = ", one device"  # the suffix of a row whose step runs on one device where more are present


def devices_name(name: str, sample_devices: int, auto: int) -> str:
    """A row's name with ``ONE_DEVICE`` where it runs on fewer devices than the harness's default ``auto`` (every
    local device over which N splits evenly: :func:`usable_sample_devices`; the cores under ``pixelmpc bench``)."""
    if sample_devices == auto:
        return name
    return f"{name}{ONE_DEVICE}" if sample_devices == 1 else f"{name}, {sample_devices} devices"


def pixelmpc_row(num_samples: int, horizon: int, t_f: float = 1.0, repeats: int = 30, group: str = GROUP,
                 track=None, dof_params=None, sample_devices: int | None = None, pixel_model: str = "dof") -> dict:
    auto = usable_sample_devices(num_samples)
    devices = auto if sample_devices is None else sample_devices
    problem = problems.pixelmpc_problem(num_samples, horizon, t_f, track=track, dof_params=dof_params,
                                        sample_devices=devices, pixel_model=pixel_model)
    stats = measure(problems.control_loop_call(problem), repeats=repeats)
    name = PIXELMPC_NAME if t_f > 0 else "PixelMPC step without pixel model (t_f=0)"
    if pixel_model != "dof":
        name = name.replace("(DOF,", f"({pixel_model},")
    row = make_row(group, devices_name(name, devices, auto), num_samples, horizon, stats,
                   t_f=t_f, pixel_steps=problem.config.pixel_steps, sample_devices=devices)
    row.update(_rates(row))
    return row


def nominal_row(num_samples: int, horizon: int, repeats: int = 30, group: str = GROUP, track=None,
                sample_devices: int | None = None) -> dict:
    auto = usable_sample_devices(num_samples)
    devices = auto if sample_devices is None else sample_devices
    problem = problems.nominal_problem(num_samples, horizon, track=track, sample_devices=devices)
    stats = measure(problems.control_loop_call(problem), repeats=repeats)
    row = make_row(group, devices_name(NOMINAL_NAME, devices, auto), num_samples, horizon, stats,
                   sample_devices=devices)
    row.update(_rates(row))
    return row


def dof_part_row(num_samples: int, pixel_steps: int, dof_params, repeats: int = 30) -> dict:
    """The pixel model alone as the step runs it: n_f sequential steps of the DOF over N samples (state
    carried, q and u per sample and step), i.e. the DOF part of the step without the robot and the costs."""
    key_q, key_u = jax.random.split(jax.random.PRNGKey(3))
    q = quadrotor.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.1 * jax.random.normal(key_q, (num_samples, 4)))
    u = quadrotor.hover_control(quadrotor.QuadParams()) + jax.random.normal(key_u, (num_samples, pixel_steps, 4))
    uv = jnp.full((num_samples, 2), 0.5, jnp.float32)

    def one(uv, q, controls):
        def body(uv, u_t):
            return uv + timing.CONTROL_DT * dof_lib.pixel_velocity(dof_params, q, uv, u_t), None
        return jax.lax.scan(body, uv, controls)[0]

    fn = jax.jit(jax.vmap(one))
    stats = measure(lambda: fn(uv, q, u), repeats=repeats)
    return make_row(GROUP, "DOF part alone (n_f sequential steps over N samples)", num_samples, pixel_steps, stats)


def paper_size_rows(repeats: int = 30, smoke: bool = False) -> list[dict]:
    """PixelMPC at N=512, T=80, t_f=1 (first); the same without the pixel model; nominal MPPI; the DOF part
    alone; and the roofline rows (flops, matmul rate, fractions)."""
    n, t = (16, 8) if smoke else (512, 80)
    t_f = 0.1 if smoke else 1.0
    track = course_lib.load_course()
    dof_params = problems.bench_dof_params()
    full = pixelmpc_row(n, t, t_f, repeats, track=track, dof_params=dof_params)
    without = pixelmpc_row(n, t, 0.0, repeats, track=track, dof_params=dof_params)
    nominal = nominal_row(n, t, repeats, track=track)
    dof_alone = dof_part_row(n, full["pixel_steps"], dof_params, repeats)
    vdof = pixelmpc_row(n, t, t_f, repeats, track=track, pixel_model="vdof")
    rows = [full, without, nominal, dof_alone, vdof]
    if full["sample_devices"] > 1:  # the same steps on one device, measured in the same run
        rows += [pixelmpc_row(n, t, t_f, repeats, track=track, dof_params=dof_params, sample_devices=1),
                 nominal_row(n, t, repeats, track=track, sample_devices=1)]

    matmuls = roofline.matmul_rows(smoke=smoke, repeats=repeats)
    rate = roofline.matmul_rate(matmuls)
    rate_best = max(r["gflops_per_s_best"] for r in matmuls) * 1e9
    problem = problems.pixelmpc_problem(16, t, t_f, track=track, dof_params=dof_params)
    per_step = roofline.per_sample_step_flops(problem)
    flops = roofline.step_flops(n, t, full["pixel_steps"], per_step)
    step_s = full["median_ms"] / 1e3
    dof_marginal_s = max(full["median_ms"] - without["median_ms"], 1e-9) / 1e3
    dof_alone_s = dof_alone["median_ms"] / 1e3
    summary = {
        "matmul_rate_gflops": rate / 1e9,
        "flops": flops,
        "per_sample_step_flops": per_step,
        "step_gflops_per_s": flops["total"] / step_s / 1e9,
        "step_fraction_of_matmul_rate": flops["total"] / step_s / rate,
        "dof_marginal_ms": dof_marginal_s * 1e3,
        "dof_fraction_in_step": flops["dof_matmul"] / dof_marginal_s / rate,
        "dof_alone_fraction": flops["dof_matmul"] / dof_alone_s / rate,
        # the same from the fastest call of each row (the machine is shared: the min is the least disturbed)
        "step_fraction_of_matmul_rate_min": flops["total"] / (full["min_ms"] / 1e3) / rate_best,
        "dof_alone_fraction_min": flops["dof_matmul"] / (dof_alone["min_ms"] / 1e3) / rate_best,
        "matmul_rate_best_gflops": rate_best / 1e9,
    }
    rows += matmuls
    rows.append(make_row(roofline.GROUP, "PixelMPC step vs matmul rate", n, t, None, status="derived",
                         **summary))
    return rows


def scaling_rows(repeats: int = 30, max_seconds_per_row: float = 10.0, samples=SCALING_SAMPLES,
                 horizons=SCALING_HORIZONS) -> list[dict]:
    """PixelMPC (t_f = 1 s) over the N x T grid. Rows whose calls take long get fewer repeats so each row spends
    about ``max_seconds_per_row`` timing (at least 5 calls; the row's ``repeats`` says how many)."""
    track = course_lib.load_course()
    dof_params = problems.bench_dof_params()
    grid = [(n, t) for t in horizons for n in samples]
    rows = []
    for n, t in grid:
        devices = usable_sample_devices(n)
        problem = problems.pixelmpc_problem(n, t, 1.0, track=track, dof_params=dof_params, sample_devices=devices)
        stats = measure(problems.control_loop_call(problem), repeats=repeats, budget_s=max_seconds_per_row)
        row = make_row("scaling", PIXELMPC_NAME, n, t, stats, pixel_steps=problem.config.pixel_steps,
                       sample_devices=devices)
        row.update(_rates(row))
        rows.append(row)
    return rows
