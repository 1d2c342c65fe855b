"""The render figure (the paper's Figs. 2-3 in spirit): a frame, its exact flow and Farneback's flow."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pixelmpc_jax import devices, timing  # noqa: E402
from pixelmpc_jax.perception import flow as flow_lib  # noqa: E402
from pixelmpc_jax.world import camera as camera_lib  # noqa: E402
from pixelmpc_jax.world import render as render_lib  # noqa: E402


def render_figure(
    track,
    x_robot,
    x_next,
    camera: camera_lib.Camera | None = None,
    out_path: str | Path = "render.png",
    supersample: int = 3,
) -> dict:
    """Render ``x_robot`` and ``x_next`` (one frame apart), and save frame | exact flow | Farneback flow.

    Both flows are colour-coded with ``flow.flow_to_rgb`` on one magnitude scale (the exact flow's 99th
    percentile); a colour wheel shows the code. Pixels whose exact flow leaves the image are grey.

    Returns:
        ``{"path": Path, "aee_px": float, "max_flow_px": float, "valid_fraction": float}``; the AEE is
        Farneback against the exact flow over the valid pixels.
    """
    camera = camera or camera_lib.default_camera()
    render_batch = devices.compiled(render_lib.render_batch, ("supersample", "chunk"))
    frames = render_batch(track, np.stack([np.asarray(x_robot), np.asarray(x_next)]), camera, supersample=supersample)
    exact, valid = devices.compiled(render_lib.exact_flow)(x_robot, x_next, frames.depth[0], camera)
    exact, valid = np.asarray(exact), np.asarray(valid)
    measured = flow_lib.farneback(
        np.asarray(frames.grey[0]), np.asarray(frames.grey[1]), shape=(camera.height, camera.width)
    )
    aee = flow_lib.average_endpoint_error(measured, exact, valid) if valid.any() else float("nan")
    magnitude = np.hypot(exact[..., 0], exact[..., 1])[valid]
    scale = float(np.percentile(magnitude, 99)) if magnitude.size else 1.0
    exact_rgb = flow_lib.flow_to_rgb(exact, scale)
    exact_rgb[~valid] = 128
    measured_rgb = flow_lib.flow_to_rgb(measured, scale)

    fig = plt.figure(figsize=(13.5, 3.6))
    grid = fig.add_gridspec(1, 4, width_ratios=[1, 1, 1, 0.42], wspace=0.06)
    panels = [
        (np.asarray(frames.rgb[0]), "rendered frame"),
        (exact_rgb, "exact flow"),
        (measured_rgb, f"Farneback flow (AEE {aee:.2f} px)"),
    ]
    for k, (image, title) in enumerate(panels):
        ax = fig.add_subplot(grid[0, k])
        ax.imshow(image, interpolation="nearest")
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    ax = fig.add_subplot(grid[0, 3])
    ax.imshow(flow_lib.colour_wheel(101), extent=(-scale, scale, scale, -scale))
    ax.set_title(f"flow (px / frame)\nrim = {scale:.1f} px", fontsize=9)
    ax.set_xlabel("dx", fontsize=8)
    ax.set_ylabel("dy", fontsize=8)
    ax.tick_params(labelsize=7)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return {
        "path": out_path,
        "aee_px": float(aee),
        "max_flow_px": float(magnitude.max()) if magnitude.size else 0.0,
        "valid_fraction": float(valid.mean()),
    }


# Standard motion cases of the render figure set: (name, speed m/s, body rates rad/s), frames 1/40 s apart.
FIGURE_CASES = (
    ("forward_10ms", 10.0, (0.0, 0.0, 0.0)),
    ("forward_10ms_yaw_right_2rads", 10.0, (0.0, 0.0, -2.0)),
    ("roll_2rads", 0.0, (2.0, 0.0, 0.0)),
)


def write_render_figures(
    out_dir: str | Path, track=None, camera: camera_lib.Camera | None = None, gate_index: int = 2, distance: float = 6.0
) -> dict:
    """The render figure for each of ``FIGURE_CASES`` from ``distance`` m before gate ``gate_index`` of
    ``track`` (default the AlphaPilot course), written as ``out_dir/render_<case>.png``.

    Returns:
        ``{case: render_figure's dict}``.
    """
    if track is None:
        from pixelmpc_jax.world import course as course_lib
        track = course_lib.load_course()
    camera = camera or camera_lib.default_camera()
    x0 = render_lib.pose_before_gate(track.gate(gate_index), distance, lateral=0.5, height=0.3)
    results = {}
    for name, speed, rates in FIGURE_CASES:
        x1 = render_lib.advance_pose(x0, timing.CONTROL_DT, speed, rates)
        results[name] = render_figure(track, x0, x1, camera, Path(out_dir) / f"render_{name}.png")
    return results
