"""Render throughput: frames per second of the ray-caster at 204 x 153, batched, on the default device.

Poses are spread along the AlphaPilot desired path (heading along its tangent). Each configuration is
compiled and warmed up outside the timed region; every timed call ends in ``block_until_ready``.
Baselines in the same run: one frame per call (``render``) and no anti-aliasing (``supersample=1``).

    python benchmarks/render_throughput.py [--batch 8 32] [--repeats 10] [--supersample 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import render
from pixelmpc_jax.world import track as track_lib


def path_poses(track, count: int) -> jax.Array:
    """(count, 10) level poses along the desired path, heading along its tangent."""
    index = np.linspace(0, track.num_path_points - 1, count).astype(int)
    points, tangents = np.asarray(track.path_points)[index], np.asarray(track.path_tangents)[index]
    yaw = np.arctan2(tangents[:, 1], tangents[:, 0])
    quats = np.stack([np.asarray(quadrotor.quat_from_yaw(y)) for y in yaw])
    return jnp.asarray(np.concatenate([points, quats, np.zeros((count, 3))], axis=1), jnp.float32)


def time_calls(fn, repeats: int, warmup: int = 2) -> list[float]:
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return times


def report(label: str, frames_per_call: int, times: list[float]) -> dict:
    median = statistics.median(times)
    q = np.percentile(times, [10, 90])
    fps = frames_per_call / median
    print(
        f"{label:34s} {fps:8.2f} frames/s   median {median * 1e3:8.1f} ms/call "
        f"(p10 {q[0] * 1e3:.1f}, p90 {q[1] * 1e3:.1f}, min {min(times) * 1e3:.1f}, n={len(times)})"
    )
    return {"label": label, "fps": fps, "median_s": median, "p10_s": q[0], "p90_s": q[1]}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[8, 32])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--supersample", type=int, default=3)
    args = parser.parse_args(argv)

    device = jax.devices()[0]
    print(
        f"device: {device.platform} {device.device_kind} | jax {jax.__version__} | "
        f"{platform.processor() or platform.machine()} | {os.cpu_count()} CPU threads | "
        f"load avg {os.getloadavg()[0]:.1f}"
    )
    track = track_lib.load_course()
    camera = camera_lib.default_camera()
    print(
        f"image {camera.width} x {camera.height}, supersample {args.supersample} "
        f"({camera.width * camera.height * args.supersample**2} rays/frame), {track.num_gates} gates"
    )
    results = []
    single = path_poses(track, 1)[0]
    for s in sorted({1, args.supersample}):
        jax.block_until_ready(render.render(track, single, camera, supersample=s))  # compile
        results.append(
            report(
                f"render, 1 frame/call, ss {s}",
                1,
                time_calls(lambda s=s: render.render(track, single, camera, supersample=s), args.repeats),
            )
        )
    for batch in args.batch:
        poses = path_poses(track, batch)
        jax.block_until_ready(render.render_batch(track, poses, camera, supersample=args.supersample))
        results.append(
            report(
                f"render_batch, B={batch}, ss {args.supersample}",
                batch,
                time_calls(
                    lambda p=poses: render.render_batch(track, p, camera, supersample=args.supersample), args.repeats
                ),
            )
        )
    return results


if __name__ == "__main__":
    main()
