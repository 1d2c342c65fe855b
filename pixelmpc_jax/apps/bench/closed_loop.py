"""The closed loop's tick: one lap flown as ``pixelmpc race`` flies it (the controller, the geometric detector,
the true state or a filter's estimate, and the FlightGoggles-like plant at 40 Hz), timed as a whole compiled
episode and divided by the ticks it flew.

The episode (:func:`~pixelmpc_jax.sim.episode.make_runner`) is compiled ahead of the timing (its compile time
is recorded apart), then run ``repeats`` times on the same world and key, each call blocked until ready. The
lap is the same every repeat; each repeat gives one per-tick time: its wall time / the ticks it flew.

    pixelmpc bench closed-loop [--mode full|quick|smoke] [--repeats 3]

The harness (``pixelmpc bench``) writes these rows into bench.json with ``group`` "loop". PixelMPC flies once
more on the error-state Kalman filter's estimate in the same run: its tick is at most
:data:`ESKF_OVER_TRUTH_TARGET` times the tick on the true state.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.apps.bench.measure import make_row, time_stats
from pixelmpc_jax.apps.bench.problems import bench_dof_params
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig, paper_mppi_config
from pixelmpc_jax.devices import usable_sample_devices
from pixelmpc_jax.sim import env as env_lib
from pixelmpc_jax.sim import episode as episode_lib
from pixelmpc_jax.world.course import make_course

GROUP = "loop"
TICK_TARGET_MS = 1e3 * timing.CONTROL_DT  # 25 ms: one tick of wall time per tick flown is real time
MODES = ("full", "quick", "smoke")  # loop_rows: one AlphaPilot lap; its first 2.5 s; tiny sizes
ESKF_OVER_TRUTH_TARGET = 1.10  # the closed-loop tick on the Kalman filter's estimate over the true state's
RUNNERS = ("single", "batch")  # Runner.single(world, key); Runner.batch of one lap, as ``pixelmpc race`` runs it


def loop_row(spec: RaceSpec, repeats: int = 3, runner: str = "single", dof_params=None,
             sample_devices: int = 1) -> dict:
    """Time the race ``spec``'s first lap in the closed loop.

    Args:
        spec: the race (controller, course, max_time_s, ...); its ``config`` may shrink the controller.
        repeats: timed laps after the compilation.
        runner: "single" (the jitted episode) or "batch" (the vmapped episode with a batch of one lap, the
            way ``pixelmpc race`` flies it).
        dof_params: the DOF weights for PixelMPC with the DOF (None: the packaged weights).
        sample_devices: ``Execution.sample_devices`` of the controller ("single" only): ``pixelmpc race`` flies
            a lap at a time with its samples over every device (:func:`usable_sample_devices`).

    Returns:
        a bench.json row: the per-tick ms figures (median, mean, 2 sigma, min, max, p95 over the repeats), the
        ticks flown, simulated and wall seconds of the lap (median), the real-time factor (simulated s / wall s),
        the compile time (for "batch", its first call less the median lap) and how the lap ended.
    """
    if runner not in RUNNERS:
        raise ValueError(f"runner must be one of {RUNNERS}, got {runner!r}")
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats!r}")
    if sample_devices > 1 and runner != "single":
        raise ValueError("sample_devices > 1 needs runner 'single' (a batch spreads its laps over the devices)")
    policy = spec.policy(sample_devices=sample_devices)
    runners = episode_lib.make_runner(policy, spec.episode_config())
    if spec.uses_dof and dof_params is None:
        dof_params = bench_dof_params()
    world = env_lib.make_world(track=make_course(spec.course), target_speed=spec.speed,
                                   dof=dof_params if spec.uses_dof else None)
    key = jax.random.PRNGKey(spec.seed)
    start = time.perf_counter()
    if runner == "single":
        call = runners.single.lower(world, key).compile()
        args = (world, key)
    else:
        # Runner.batch shards, runs the jitted vmap and gathers; its first call compiles (and flies one lap)
        args = (env_lib.stack_worlds([world]), key[None])
        call = runners.batch
        jax.block_until_ready(call(*args))
    first_call_s = time.perf_counter() - start

    walls, ticks = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        log = jax.block_until_ready(call(*args))
        walls.append(time.perf_counter() - start)
        ticks.append(int(np.asarray(log.num_ticks).reshape(-1)[0]))
    # the same world and key fly the same lap, so ticks are equal; each repeat is divided by its own anyway
    num_ticks = int(np.median(ticks))
    stats = time_stats(1e3 * np.asarray(walls) / np.maximum(ticks, 1))
    lap_wall_s = float(np.median(walls))
    # Runner.single is compiled ahead of time; Runner.batch's first call also flew a lap
    compile_s = first_call_s - (lap_wall_s if runner == "batch" else 0.0)
    sim_s = num_ticks * timing.CONTROL_DT
    end = int(np.asarray(log.end_cause).reshape(-1)[0])
    finished = bool(np.asarray(log.finished).reshape(-1)[0])
    mppi = policy_sizes(spec)
    controller = (f"PixelMPC ({spec.config.pixel_model}, t_f={spec.config.t_f:g} s)" if spec.controller == "pixelmpc"
                  else "nominal MPPI")
    name = f"closed-loop tick: {controller}, {spec.detector} detector, plant"
    if spec.estimator != "truth":
        name += f", on the {spec.estimator} estimate"
    if runner == "batch":
        name += ", vmapped batch of 1"
    elif sample_devices > 1:
        name += f", samples over {sample_devices} devices (as pixelmpc race)"
    return make_row(GROUP, name, mppi["num_samples"], mppi["horizon"], stats,
                    first_call_ms=1e3 * first_call_s, compile_s=compile_s, controller=spec.controller, runner=runner,
                    estimator=spec.estimator,
                    course=spec.course, max_time_s=spec.max_time_s, sample_devices=sample_devices, speed=spec.speed,
                    ticks=num_ticks, ticks_per_repeat=ticks,
                    sim_s=sim_s, lap_wall_s=lap_wall_s, real_time_factor=sim_s / lap_wall_s,
                    end_cause="finished" if finished else env_lib.END_NAMES.get(end, "flying"),
                    gates_passed=int(np.asarray(log.gates_passed).reshape(-1)[0]),
                    target_ms=TICK_TARGET_MS, meets_target=stats["median_ms"] <= TICK_TARGET_MS)


def policy_sizes(spec: RaceSpec) -> dict:
    """The MPPI samples and horizon the spec's controller plans with."""
    return {"num_samples": spec.config.mppi.num_samples, "horizon": spec.config.mppi.horizon}


def loop_rows(mode: str = "full", repeats: int | None = None, dof_params=None) -> list[dict]:
    """The closed-loop rows of the harness: PixelMPC (packaged DOF) and nominal MPPI at the defaults of
    ``pixelmpc race`` (N=512, T=80, t_f=1 s, 14 m/s, geometric detector, true state), and PixelMPC once more on
    the error-state Kalman filter's estimate.

    Each controller flies with its samples over every local device (as ``pixelmpc race`` flies a lap), and,
    where there are several, once more on one device. Modes: "full": one AlphaPilot lap (max 60 s), 3 repeats,
    and PixelMPC once more in the vmapped runner (a batch of one lap); "quick": the first 2.5 s of the lap,
    3 repeats; "smoke": N=16, T=8, t_f=0.1 s, 0.25 s (10 ticks), 2 repeats.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    repeats = repeats or (2 if mode == "smoke" else 3)
    max_time_s = {"full": timing.LAP_TIME_LIMIT_S, "quick": 2.5, "smoke": 0.25}[mode]
    base = RaceSpec(controller="pixelmpc", max_time_s=max_time_s)
    if mode == "smoke":
        base = base.replace(config=ControllerConfig(mppi=paper_mppi_config(num_samples=16, horizon=8), t_f=0.1))
    devices = usable_sample_devices(base.config.mppi.num_samples)
    rows = [loop_row(base, repeats, dof_params=dof_params, sample_devices=devices),
            loop_row(base.replace(controller="mppi"), repeats, sample_devices=devices),
            loop_row(base.replace(estimator="eskf"), repeats, dof_params=dof_params, sample_devices=devices)]
    if devices > 1:
        rows += [loop_row(base, repeats, dof_params=dof_params), loop_row(base.replace(controller="mppi"), repeats)]
    if mode == "full":
        rows.append(loop_row(base, repeats, runner="batch", dof_params=dof_params))
    return rows


def run_closed_loop(mode: str = "quick", repeats: int | None = None) -> list[dict]:
    """The closed-loop rows (:func:`loop_rows`), printed one line each and as a JSON line; returns them."""
    import json

    rows = loop_rows(mode, repeats)
    for r in rows:
        print(f"{r['name']} (N={r['num_samples']}, T={r['horizon']}, {r['course']}, {r['ticks']} ticks, "
              f"{r['end_cause']}): per tick median {r['median_ms']:.2f} ms, p95 {r['p95_ms']:.2f} ms over "
              f"{r['repeats']} laps; lap {r['sim_s']:.2f} s simulated in {r['lap_wall_s']:.2f} s wall "
              f"({r['real_time_factor']:.2f}x real time); compile {r['compile_s']:.1f} s")
    print(json.dumps(rows))
    return rows
