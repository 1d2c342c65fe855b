"""The onboard video (the paper's Fig. 1): camera frames with the MPC-predicted target-pixel trajectory
(green) and the pixel's actual future trajectory (red), written as MP4 (OpenCV) or an animated GIF."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pixelmpc_jax import devices, timing
from pixelmpc_jax.sim.episode import EpisodeLog
from pixelmpc_jax.world import camera as camera_lib
from pixelmpc_jax.world import render as render_lib

PREDICTED = (40, 220, 40)
ACTUAL = (230, 40, 40)


def _polyline(image: np.ndarray, uv: np.ndarray, colour, scale: int) -> None:
    h, w = image.shape[:2]
    points = np.round(uv * np.asarray([w, h])).astype(np.int32).reshape(-1, 1, 2)
    if len(points) >= 2:
        cv2.polylines(image, [points], isClosed=False, color=colour, thickness=max(scale // 2, 1),
                      lineType=cv2.LINE_AA)
    if len(points):
        cv2.circle(image, tuple(int(v) for v in points[0, 0]), max(scale, 2), colour, -1, lineType=cv2.LINE_AA)


def annotated_frames(track, log: EpisodeLog, camera: camera_lib.Camera | None = None, every: int = 2,
                     scale: int = 3, max_frames: int | None = None) -> list[np.ndarray]:
    """Rendered onboard frames (upscaled by ``scale``) with the predicted and actual target-pixel paths.

    The actual path is where the detector saw the same target over the next steps the prediction covers.
    """
    camera = camera or camera_lib.default_camera()
    n = int(log.num_ticks)
    states = np.asarray(log.states)
    detected = np.asarray(log.detected)
    detection_uv = np.asarray(log.detection_uv)
    predicted = np.asarray(log.predicted_uv)
    target = np.asarray(log.target)
    horizon = predicted.shape[1]
    frames = []
    ticks = range(0, n, every)
    if max_frames is not None:
        ticks = list(ticks)[:max_frames]
    render = devices.compiled(render_lib.render, ("supersample",))
    for k in ticks:
        frame = render(track, states[k], camera, supersample=1)
        rgb = np.asarray(frame.rgb)
        rgb = cv2.resize(rgb, (camera.width * scale, camera.height * scale), interpolation=cv2.INTER_NEAREST)
        if detected[k]:
            window = np.arange(k, min(k + horizon, n))
            same = window[(target[window] == target[k]) & detected[window]]
            _polyline(rgb, detection_uv[same], ACTUAL, scale)
            _polyline(rgb, predicted[k], PREDICTED, scale)
        cv2.putText(rgb, f"t={k * timing.CONTROL_DT:5.2f}s gate {int(target[k]) + 1}", (6, 16),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        frames.append(rgb)
    return frames


def write_onboard_video(track, log: EpisodeLog, path: Path, camera: camera_lib.Camera | None = None,
                        every: int = 2, scale: int = 2, max_frames: int | None = None) -> Path:
    """Write the annotated onboard frames at real time (``every`` ticks per frame): MP4 for a ``.mp4`` path
    (compact: the rendered textures make GIFs large), otherwise an animated GIF."""
    frames = annotated_frames(track, log, camera, every, scale, max_frames)
    if not frames:
        raise ValueError("the episode has no ticks to draw")
    path = Path(path)
    if path.suffix.lower() == ".mp4":
        h, w = frames[0].shape[:2]
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), timing.CONTROL_HZ / every, (w, h))
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV cannot write MP4 here; use a .gif path instead of {path}")
        for frame in frames:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        writer.release()
        return path
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(every * timing.CONTROL_DT * 1000)),
                   loop=0, optimize=True)
    return path
