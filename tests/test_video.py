"""The onboard video: predicted (green) and actual (red) target-pixel paths drawn on rendered frames."""

import jax.numpy as jnp
import numpy as np

from pixelmpc_jax.apps.racing.video import PREDICTED, annotated_frames, write_onboard_video
from pixelmpc_jax.sim.episode import EpisodeLog
from pixelmpc_jax.world import course as C


def make_log(track, ticks=4, horizon=5):
    x = np.tile(np.asarray(track.start), (ticks + 1, 1))
    predicted = np.zeros((ticks, horizon, 2), np.float32)
    predicted[:, :, 0] = np.linspace(0.2, 0.8, horizon)  # a horizontal line across the middle row
    predicted[:, :, 1] = 0.5
    return EpisodeLog(
        states=x, controls=np.zeros((ticks, 4)), body_rates=np.zeros((ticks + 1, 3)),
        visibility=np.ones(ticks + 1), target=np.zeros(ticks + 1, np.int32), detected=np.ones(ticks, bool),
        detection_uv=np.full((ticks, 2), 0.5, np.float32), predicted_uv=predicted,
        estimates=x[:ticks], position_cov_trace=np.zeros(ticks), num_ticks=jnp.asarray(ticks),
        gates_passed=jnp.asarray(0), end_cause=jnp.asarray(0), finished=jnp.asarray(False))


def test_predicted_path_is_drawn_where_predicted(tmp_path):
    track = C.straight_course(num_gates=2)
    frames = annotated_frames(track, make_log(track), every=1, scale=2)
    assert len(frames) == 4 and frames[0].shape == (306, 408, 3)
    row = frames[0][153]  # the middle row, where the predicted line runs from u = 0.2 to 0.8
    green = np.all(np.abs(row.astype(int) - np.asarray(PREDICTED)) < 40, axis=1)
    columns = np.nonzero(green)[0]
    assert columns.min() < 0.25 * 408 and columns.max() > 0.75 * 408
    assert not np.any(np.all(np.abs(frames[0][20].astype(int) - np.asarray(PREDICTED)) < 40, axis=1))


def test_writes_mp4_and_gif(tmp_path):
    track = C.straight_course(num_gates=2)
    log = make_log(track)
    mp4 = write_onboard_video(track, log, tmp_path / "onboard.mp4", every=1)
    gif = write_onboard_video(track, log, tmp_path / "onboard.gif", every=1)
    assert mp4.stat().st_size > 1000 and gif.stat().st_size > 1000
    from PIL import Image

    assert Image.open(gif).n_frames == 4
