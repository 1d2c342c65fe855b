"""Flown laps for open-loop replays of the ESKF (``tests/test_eskf.py``).

A geometric tracking controller flies the simulated vehicle (``sim/plant.py``: rate loop, motors, process and IMU
noise) along the course's desired path on the true state, and each tick records what the environment would hand
an estimator (``sim/env.py``): the tick's preintegrated IMU and the target gate's geometric detection from the
true pose, with pixel noise. A filter is then replayed on them with whatever bias, false detection or delay a test
injects. The controller is a stand-in for MPPI that costs nothing to compile: it tracks a point of the path at
``speed`` (reached at 5 m/s^2 from rest), its thrust along the wanted acceleration, its camera towards the path
6 m ahead.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pixelmpc_jax import timing
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.perception import detector as detector_lib
from pixelmpc_jax.sim import plant as plant_lib
from pixelmpc_jax.world import track as track_lib

LOOK_AHEAD_M = 6.0  # where the camera points, along the path
WINDOW_M = 12.0  # path searched around the last progress
GAINS = (2.0, 3.0, 6.0)  # position (1/s), velocity (1/s), attitude (1/s)


class Flight(NamedTuple):
    """A flown lap, ticks 0..T (leading batch axes under vmap).

    Attributes:
        states: (T+1, 10) true state at each tick.
        imu: TickIMU, leaves (T+1, ...): the IMU over the tick that led to tick k (tick 0: a hover tick, as the
            environment's first).
        detections: Detection, leaves (T+1, ...): the target gate seen from the true state at tick k.
        target: (T+1,) int32 the target gate.
    """

    states: jax.Array
    imu: plant_lib.TickIMU
    detections: detector_lib.Detection
    target: jax.Array


def _path_at(track: track_lib.Track, s: jax.Array) -> tuple[jax.Array, jax.Array]:
    i = jnp.clip(jnp.round(s / track.path_spacing).astype(jnp.int32), 0, track.num_path_points - 1)
    return track.path_points[i], track.path_tangents[i]


def track_command(track: track_lib.Track, x: jax.Array, progress: jax.Array, t: jax.Array, speed: float,
                  params: plant_lib.PlantParams) -> tuple[jax.Array, jax.Array]:
    """The command ``[wx, wy, wz, thrust]`` (4,) that tracks the path at ``speed``, and the progress (m)."""
    k_p, k_v, k_r = GAINS
    p, v = x[quadrotor.POS], x[quadrotor.VEL]
    length = int(WINDOW_M / track_lib.PATH_SPACING) + 2
    window = track_lib.PathWindow(start=jnp.floor((progress - 2.0) / track.path_spacing).astype(jnp.int32),
                                  length=length)
    query = track_lib.path_query(track, p, window)
    v_ref = jnp.minimum(speed, 0.5 + 5.0 * t)
    _, tangent_ahead = _path_at(track, query.progress_s + 1.0)
    curvature = tangent_ahead - query.tangent  # d tangent / ds over 1 m
    accel = k_v * (v_ref * query.tangent + k_p * (query.closest_point - p) - v) + v_ref**2 * curvature
    norm = jnp.linalg.norm(accel)
    accel = accel * jnp.minimum(1.0, 20.0 / jnp.maximum(norm, 1e-6))
    drag = params.drag_coefficient * jnp.linalg.norm(v) * v / params.mass
    force = accel + jnp.asarray([0.0, 0.0, params.gravity]) + drag
    thrust = params.mass * jnp.linalg.norm(force)
    z_b = force / jnp.linalg.norm(force)
    look, _ = _path_at(track, query.progress_s + LOOK_AHEAD_M)
    heading = look - p
    x_c = jnp.stack([heading[0], heading[1], 0.0]) / jnp.maximum(jnp.linalg.norm(heading[:2]), 1e-6)
    y_b = jnp.cross(z_b, x_c)
    y_b = y_b / jnp.linalg.norm(y_b)
    R_des = jnp.stack([jnp.cross(y_b, z_b), y_b, z_b], axis=1)
    R = quadrotor.rotation_matrix(quadrotor.normalize_quat(x[quadrotor.QUAT]))
    E = R_des.T @ R - R.T @ R_des
    rates = jnp.clip(-0.5 * k_r * jnp.stack([E[2, 1], E[0, 2], E[1, 0]]), -6.0, 6.0)
    return jnp.concatenate([rates, jnp.clip(thrust, 0.0, 30.0)[None]]).astype(x.dtype), query.progress_s


def fly(track: track_lib.Track, camera, key: jax.Array, ticks: int, speed: float = 8.5,
        pixel_noise_px: float = 2.0) -> Flight:
    """``ticks`` ticks of the tracking controller from the course's start (pure: jit with ``ticks`` and ``speed``
    static, vmap over keys)."""
    params = plant_lib.PlantParams()
    num_gates = track.num_gates

    def target_of(progress):
        return jnp.minimum(jnp.sum(track.path_gate_s < progress), num_gates - 1).astype(jnp.int32)

    def detect(x, target, key_detect):
        return detector_lib.detect_from_geometry(track.gate(target), x, camera, key_detect, pixel_noise_px, 0.0,
                                                 target)

    def tick(carry, k):
        plant, progress, key = carry
        key, key_plant, key_detect = jax.random.split(key, 3)
        u, progress = track_command(track, plant.x, progress, k * timing.CONTROL_DT, speed, params)
        plant, _, imu = plant_lib.plant_tick(plant, u, key_plant, params)
        target = target_of(progress)
        return (plant, progress, key), (plant.x, imu, detect(plant.x, target, key_detect), target)

    x0 = track.start
    key, key_first = jax.random.split(key)
    plant = plant_lib.init_plant(x0, params)
    _, (states, imus, detections, targets) = jax.lax.scan(tick, (plant, jnp.asarray(0.0), key), jnp.arange(ticks))
    first = (x0, plant_lib.hover_tick_imu(timing.CONTROL_DT), detect(x0, jnp.asarray(0, jnp.int32), key_first),
             jnp.asarray(0, jnp.int32))
    stacked = jax.tree_util.tree_map(lambda a, rest: jnp.concatenate([jnp.asarray(a, rest.dtype)[None], rest]), first,
                                     (states, imus, detections, targets))
    return Flight(*stacked)


def with_imu_bias(imu: plant_lib.TickIMU, accel_bias: jax.Array, gyro_bias: jax.Array) -> plant_lib.TickIMU:
    """The tick's IMU (one tick) read by an IMU with constant biases (3,) each: ``sim.faults.corrupt_imu``'s bias,
    for biases that are arrays (drawn per replay)."""
    dt = imu.dt
    return imu._replace(accel=imu.accel + accel_bias, gyro=imu.gyro + gyro_bias,
                        delta_q=quadrotor.normalize_quat(quadrotor.quat_multiply(imu.delta_q,
                                                                                 quadrotor.quat_exp(gyro_bias, dt))),
                        delta_v=imu.delta_v + accel_bias * dt, delta_p=imu.delta_p + 0.5 * accel_bias * dt * dt)
