"""The paper's Table I (runtime of the perception models), every row, on this device.

Rows: our image detector at 204 x 153 (the stand-in for YOLOv3); the DOF network at one pixel with 1 / 512
samples and 1 / 80 sequential steps; the DOF on every pixel of a 204 x 153 image (1 sample, 1 and 80 steps;
512 samples); a SpyNet-sized whole-image flow network (random weights, the architecture is what is timed)
at 192 x 160 with batch 1 and 512. A row whose arrays would not fit is not attempted: it is reported as
``OOM (needs X GB)`` from a prediction of its peak bytes, as the paper reports OOM.
"""

from __future__ import annotations

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pixelmpc_jax import devices, timing
from pixelmpc_jax.apps.bench.measure import make_row, measure, run_in_child
from pixelmpc_jax.apps.bench.problems import bench_dof_params
from pixelmpc_jax.dynamics import dof as dof_lib
from pixelmpc_jax.dynamics import quadrotor
from pixelmpc_jax.world.camera import PAPER_HEIGHT, PAPER_WIDTH

GROUP = "table1"
IMAGE_WH = (PAPER_WIDTH, PAPER_HEIGHT)
SPYNET_WH = (192, 160)
DT = timing.CONTROL_DT

# The paper's Table I, ms: (mean, 2 sigma, max), None for OOM.
PAPER = {
    "detector": (14.9, 5.6, 21.1),
    ("dof", 1, 1, 1): (1.5, 0.4, 2.1),
    ("dof", 1, 1, 80): (6.7, 2.9, 10.1),
    ("dof", 1, 512, 1): (1.6, 0.7, 2.8),
    ("dof", 1, 512, 80): (8.6, 3.0, 11.9),
    ("dof", 31212, 1, 1): (6.9, 1.5, 9.4),
    ("dof", 31212, 1, 80): (327.0, 10.6, 340.3),
    ("dof", 31212, 512, 1): None,
    ("spynet", 1): (3.3, 0.5, 4.0),
    ("spynet", 512): None,
}


def available_bytes() -> int:
    """MemAvailable of this machine (bytes), or 8 GB where /proc/meminfo cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 8 << 30


def memory_budget() -> int:
    """Bytes a single row may allocate: half of what is free (the machine is shared), overridable with
    ``PIXELMPC_BENCH_MEMORY_GB``."""
    override = os.environ.get("PIXELMPC_BENCH_MEMORY_GB")
    return int(float(override) * (1 << 30)) if override else available_bytes() // 2


def _paper_fields(key) -> dict:
    if key not in PAPER:
        return {}
    paper = PAPER[key]
    if paper is None:
        return {"paper": "OOM"}
    return {"paper_mean_ms": paper[0], "paper_two_sigma_ms": paper[1], "paper_max_ms": paper[2]}


# --------------------------------------------------------------------------------------------------
# DOF rows.
# --------------------------------------------------------------------------------------------------


def dof_rollout_fn(dof_params, num_pixels: int, num_samples: int, steps: int):
    """A jitted multi-step pixel prediction: for every (sample, pixel) pair, ``steps`` sequential Euler steps
    uv <- uv + dt * DOF(q, uv, u_t) (Eq. 12), the orientation q and the controls u_t per sample.

    Returns ``(fn, args)``; ``fn(*args)`` -> (num_samples, num_pixels, 2) final pixels.
    """
    key_q, key_u = jax.random.split(jax.random.PRNGKey(1))
    q = quadrotor.normalize_quat(jnp.asarray([1.0, 0.0, 0.0, 0.0]) + 0.1 * jax.random.normal(key_q, (num_samples, 4)))
    hover = quadrotor.hover_control(quadrotor.QuadParams())
    u = hover + jax.random.normal(key_u, (num_samples, steps, 4)) * jnp.asarray([0.2, 0.2, 0.3, 2.2])
    if num_pixels == 1:
        uv = jnp.full((1, 2), 0.5, jnp.float32)
    else:
        w, h = IMAGE_WH
        gu, gv = jnp.meshgrid((jnp.arange(w) + 0.5) / w, (jnp.arange(h) + 0.5) / h)
        uv = jnp.stack([gu.ravel(), gv.ravel()], axis=-1)  # (P, 2)

    def one_pixel(uv, q, controls):  # (2,), (4,), (steps, 4) -> (2,)
        def body(uv, u_t):
            return uv + DT * dof_lib.pixel_velocity(dof_params, q, uv, u_t), None

        return jax.lax.scan(body, uv, controls)[0]

    over_pixels = jax.vmap(one_pixel, in_axes=(0, None, None))
    fn = jax.jit(jax.vmap(over_pixels, in_axes=(None, 0, 0)))
    return fn, (uv, q, u)


def dof_peak_bytes(rows: int) -> int:
    """Peak bytes of one DOF evaluation over ``rows`` inputs: two live (rows, 128) float32 activations plus
    the (rows, 10) features and the (rows, 2) state."""
    return rows * (2 * max(dof_lib.HIDDEN_SIZES) + dof_lib.INPUT_DIM + 2 * 2) * 4


PAPER_DOF_SIZE = (1, 512, 80)  # the DOF row the controller runs: one pixel, 512 samples, 80 sequential steps


def dof_rows(dof_params=None, smoke: bool = False, repeats: int = 30, cases=None) -> list[dict]:
    """The DOF rows of Table I, or only ``cases`` (each (pixels, samples, steps))."""
    dof_params = bench_dof_params() if dof_params is None else dof_params
    pixels_full = IMAGE_WH[0] * IMAGE_WH[1]
    if cases is None:
        cases = [(1, 1, 1), (1, 1, 80), (1, 512, 1), PAPER_DOF_SIZE,
                 (pixels_full, 1, 1), (pixels_full, 1, 80), (pixels_full, 512, 1)]
        if smoke:
            cases = [(1, 1, 1), (1, 16, 8)]
    rows = []
    for pixels, samples, steps in cases:
        label = "1x1" if pixels == 1 else f"{IMAGE_WH[0]}x{IMAGE_WH[1]}"
        name = f"DOF {label}, {samples} sample(s), {steps} step(s)"
        extra = {"n_pixel": label, "evaluations": pixels * samples * steps, **_paper_fields(("dof", pixels, samples,
                                                                                            steps))}
        need = dof_peak_bytes(pixels * samples)
        if need > memory_budget():
            rows.append(make_row(GROUP, name, samples, steps, None, status=f"OOM (needs {need / 2**30:.1f} GB)",
                                 **extra))
            continue
        if pixels * samples >= ISOLATE_ROWS:  # might not fit after all: a failed allocation aborts the process
            ok, stats = run_in_child("pixelmpc_jax.apps.bench.table1", "_dof_stats", [pixels, samples, steps, repeats])
        else:
            ok, stats = _measure_or_oom(lambda p=pixels, n=samples, t=steps: _dof_stats(p, n, t, repeats, dof_params))
        if not ok:
            rows.append(make_row(GROUP, name, samples, steps, None, status=f"OOM ({stats})", **extra))
            continue
        rows.append(make_row(GROUP, name, samples, steps, stats, **extra))
    return rows


# Rows with at least this many (sample, pixel) pairs, or this many images, run in a child process.
ISOLATE_ROWS = 100_000
ISOLATE_IMAGES = 2


def _measure_or_oom(run) -> tuple[bool, object]:
    try:
        return True, run()
    except (MemoryError, RuntimeError) as err:  # XLA raises RuntimeError (RESOURCE_EXHAUSTED) on OOM
        return False, type(err).__name__


def _dof_stats(pixels: int, samples: int, steps: int, repeats: int, dof_params=None) -> dict:
    """Timing of one DOF rollout case (runs in a child process for the large cases)."""
    dof_params = bench_dof_params() if dof_params is None else dof_params
    fn, args = dof_rollout_fn(dof_params, pixels, samples, steps)
    return measure(lambda: fn(*args), repeats=repeats)


# --------------------------------------------------------------------------------------------------
# The detector row.
# --------------------------------------------------------------------------------------------------


def detector_row(repeats: int = 30) -> dict:
    """Our colour detector on one rendered 204 x 153 frame with the first gate 6 m ahead."""
    from pixelmpc_jax.perception import detector
    from pixelmpc_jax.world import camera as camera_lib
    from pixelmpc_jax.world import course as course_lib
    from pixelmpc_jax.world import render
    track = course_lib.load_course()
    camera = camera_lib.default_camera()
    gate = jax.tree_util.tree_map(lambda a: a[0], track.gates)
    frame = devices.compiled(render.render, ("supersample",))(track, render.pose_before_gate(gate, 6.0), camera)
    rgb = np.asarray(frame.rgb)
    found = bool(detector.detect_from_image(rgb, 0, camera).found)
    stats = measure(lambda: detector.detect_from_image(rgb, 0, camera), repeats=repeats)
    return make_row(GROUP, "detector (ours, OpenCV) in place of YOLOv3", 1, 1, stats, n_pixel="204x153",
                    note=f"gate found: {found}; numpy/OpenCV on the CPU, not JAX", **_paper_fields("detector"))


# --------------------------------------------------------------------------------------------------
# SpyNet (Ranjan and Black 2017), architecture only.
# --------------------------------------------------------------------------------------------------

SPYNET_LEVELS = 5
SPYNET_CHANNELS = (32, 64, 32, 16, 2)
SPYNET_KERNEL = 7


class SpyNetLevel(nn.Module):
    """One pyramid level's CNN: [img1, warped img2, upsampled flow] (8 ch) -> residual flow (2 ch)."""

    @nn.compact
    def __call__(self, x):
        for i, width in enumerate(SPYNET_CHANNELS):
            x = nn.Conv(width, (SPYNET_KERNEL, SPYNET_KERNEL), padding="SAME")(x)
            if i < len(SPYNET_CHANNELS) - 1:
                x = nn.relu(x)
        return x


def _warp(image, flow):
    """Backward-warp image (H, W, C) by flow (H, W, 2) in pixels, bilinear, edge-clamped."""
    h, w = image.shape[:2]
    rows, cols = jnp.meshgrid(jnp.arange(h, dtype=image.dtype), jnp.arange(w, dtype=image.dtype), indexing="ij")
    coords = [rows + flow[..., 1], cols + flow[..., 0]]
    return jnp.stack([jax.scipy.ndimage.map_coordinates(image[..., c], coords, order=1, mode="nearest")
                      for c in range(image.shape[-1])], axis=-1)


class SpyNet(nn.Module):
    """The SpyNet coarse-to-fine flow network: a 5-level image pyramid, at each level the flow so far is
    upsampled (x2), the second image warped by it, and a small CNN adds a residual. 1,200,250 parameters."""

    @nn.compact
    def __call__(self, img1, img2):  # (B, H, W, 3) each -> (B, H, W, 2)
        pyramid = [(img1, img2)]
        for _ in range(SPYNET_LEVELS - 1):
            a, b = pyramid[-1]
            pyramid.append((nn.avg_pool(a, (2, 2), (2, 2)), nn.avg_pool(b, (2, 2), (2, 2))))
        batch, h, w, _ = pyramid[-1][0].shape
        flow = jnp.zeros((batch, h, w, 2), img1.dtype)
        for level in range(SPYNET_LEVELS - 1, -1, -1):
            a, b = pyramid[level]
            if flow.shape[1:3] != a.shape[1:3]:
                flow = 2.0 * jax.image.resize(flow, (batch, *a.shape[1:3], 2), "bilinear")
            warped = jax.vmap(_warp)(b, flow)
            flow = flow + SpyNetLevel(name=f"level_{level}")(jnp.concatenate([a, warped, flow], axis=-1))
        return flow


def spynet_flops_per_image(wh=SPYNET_WH) -> int:
    """2 x MACs of the convolutions over the pyramid (the warps and resizes are not counted)."""
    widths = (8, *SPYNET_CHANNELS)
    macs_per_pixel = SPYNET_KERNEL**2 * sum(a * b for a, b in zip(widths[:-1], widths[1:]))
    pixels = sum((wh[0] >> k) * (wh[1] >> k) for k in range(SPYNET_LEVELS))
    return 2 * macs_per_pixel * pixels


def spynet_peak_bytes(batch: int, wh=SPYNET_WH) -> int:
    """Peak bytes at the finest level: the widest conv's input and output (32 + 64 channels) live at once,
    plus the 8-channel input, float32."""
    return batch * wh[0] * wh[1] * (8 + 32 + 64) * 4


def spynet_rows(smoke: bool = False, repeats: int = 30, max_call_s: float = 60.0) -> list[dict]:
    wh = (64, 32) if smoke else SPYNET_WH
    num_params = int(sum(np.size(x) for x in jax.tree_util.tree_leaves(_spynet(wh)[1])))
    rows, per_image_ms = [], None
    for batch in ((1,) if smoke else (1, 512)):
        name = f"SpyNet-sized flow network {wh[0]}x{wh[1]}, batch {batch}"
        extra = {"n_pixel": f"{wh[0]}x{wh[1]}", "num_params": num_params,
                 "gflop_per_call": batch * spynet_flops_per_image(wh) / 1e9, **_paper_fields(("spynet", batch))}
        need = spynet_peak_bytes(batch, wh)
        if need > memory_budget():
            rows.append(make_row(GROUP, name, batch, 1, None, status=f"OOM (needs {need / 2**30:.1f} GB)", **extra))
            continue
        if per_image_ms is not None and batch * per_image_ms / 1e3 > max_call_s:
            rows.append(make_row(GROUP, name, batch, 1, None, status=(
                f"not run: predicted {batch * per_image_ms / 1e3:.0f} s per call on this device "
                f"(fits: needs {need / 2**30:.1f} GB)"), **extra))
            continue
        if batch >= ISOLATE_IMAGES:  # XLA's CPU convolutions need far more than the activations
            ok, stats = run_in_child("pixelmpc_jax.apps.bench.table1", "_spynet_stats", [batch, list(wh), repeats])
        else:
            ok, stats = _measure_or_oom(lambda b=batch: _spynet_stats(b, wh, repeats))
        if not ok:
            rows.append(make_row(GROUP, name, batch, 1, None, status=f"OOM ({stats})", **extra))
            continue
        per_image_ms = stats["median_ms"] / batch
        rows.append(make_row(GROUP, name, batch, 1, stats, **extra))
    return rows


def _spynet(wh):
    """(jitted apply, variables, two input keys) of the SpyNet-sized network at image size ``wh``."""
    model = SpyNet()
    key_init, key_a, key_b = jax.random.split(jax.random.PRNGKey(2), 3)
    variables = model.init(key_init, jnp.zeros((1, wh[1], wh[0], 3)), jnp.zeros((1, wh[1], wh[0], 3)))
    return jax.jit(model.apply), variables, (key_a, key_b)


def _spynet_stats(batch: int, wh, repeats: int) -> dict:
    """Timing of the SpyNet-sized network on a batch of image pairs (a child process for large batches)."""
    apply, variables, (key_a, key_b) = _spynet(wh)
    a = jax.random.uniform(key_a, (batch, wh[1], wh[0], 3))
    b = jax.random.uniform(key_b, (batch, wh[1], wh[0], 3))
    return measure(lambda: apply(variables, a, b), repeats=repeats)


def table1_rows(smoke: bool = False, repeats: int = 30) -> list[dict]:
    """Every row of Table I (a reduced set with ``smoke``)."""
    rows = [] if smoke else [detector_row(repeats)]
    rows += dof_rows(smoke=smoke, repeats=repeats)
    if not smoke:  # compiling the 5-level network takes ~10 s even at a tiny size
        rows += spynet_rows(repeats=repeats)
    return rows
