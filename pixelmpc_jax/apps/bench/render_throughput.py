"""Render throughput: frames per second of the ray-caster at 204 x 153, batched, on the default device.

Poses are spread along the AlphaPilot desired path (heading along its tangent). Each configuration is
timed with the harness's ``measure`` (compilation and warm-up outside the timed region, every call
blocked until ready).
Baselines in the same run: one frame per call (``render``) and no anti-aliasing (``supersample=1``).

    pixelmpc bench render [--batch 8 32] [--repeats 10] [--supersample 3]
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import devices
from pixelmpc_jax.apps.bench.measure import measure
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import course as course_lib
from pixelmpc_jax.world import render


def path_poses(track, count: int) -> jax.Array:
    """(count, 10) level poses along the desired path, heading along its tangent."""
    index = np.linspace(0, track.num_path_points - 1, count).astype(int)
    points, tangents = np.asarray(track.path_points)[index], np.asarray(track.path_tangents)[index]
    yaw = np.arctan2(tangents[:, 1], tangents[:, 0])
    quats = np.stack([np.asarray(quadrotor.quat_from_yaw(y)) for y in yaw])
    return jnp.asarray(np.concatenate([points, quats, np.zeros((count, 3))], axis=1), jnp.float32)


def report(label: str, frames_per_call: int, stats: dict) -> dict:
    """Print and return frames per second from a ``measure`` result (median call time)."""
    fps = frames_per_call / (stats["median_ms"] / 1e3)
    print(f"{label:34s} {fps:8.2f} frames/s   median {stats['median_ms']:8.1f} ms/call "
          f"(mean {stats['mean_ms']:.1f} +- {stats['two_sigma_ms']:.1f}, min {stats['min_ms']:.1f}, "
          f"max {stats['max_ms']:.1f}, n={stats['repeats']})")
    return {"label": label, "fps": fps, **stats}


def run_render_throughput(batches=(8, 32), repeats: int = 10, supersample: int = 3) -> list[dict]:
    """Frames per second of one frame per call (``supersample`` and 1) and of each batch size in ``batches``;
    prints a line each and returns them."""
    print(f"device: {device_line()} | load avg {os.getloadavg()[0]:.1f}")
    track = course_lib.load_course()
    camera = camera_lib.default_camera()
    print(
        f"image {camera.width} x {camera.height}, supersample {supersample} "
        f"({camera.width * camera.height * supersample**2} rays/frame), {track.num_gates} gates"
    )
    render_one = devices.compiled(render.render, ("supersample",))
    render_batch = devices.compiled(render.render_batch, ("supersample", "chunk"))
    results = []
    single = path_poses(track, 1)[0]
    for s in sorted({1, supersample}):
        stats = measure(lambda s=s: render_one(track, single, camera, supersample=s), repeats=repeats)
        results.append(report(f"render, 1 frame/call, ss {s}", 1, stats))
    for batch in batches:
        poses = path_poses(track, batch)
        stats = measure(lambda p=poses: render_batch(track, p, camera, supersample=supersample),
                        repeats=repeats)
        results.append(report(f"render_batch, B={batch}, ss {supersample}", batch, stats))
    return results
