"""The geometric detector against the image detector on the frames of flown laps.

The onboard loop's image detector renders each tick's frame and finds the gate in it with OpenCV; the geometric
detector (``--detector clipped``, every loop's default) projects the gate and cuts its report at the image border,
as a camera's detector reports a gate half out of view. This check renders every tick of chosen laps of per-tick
records (``ticks_*.npz``, :mod:`~pixelmpc_jax.sim.ticks`), each frame looking for the tick's target gate, and
compares the two (:func:`~pixelmpc_jax.perception.detector.image_agreement`): whether each finds the gate, and how
far apart their centres are, on every frame and on the frames with the gate partly out of view.

``pixelmpc experiment detector-agreement TICKS [TICKS ...] --laps N --out DIR`` writes ``agreement.json``,
``REPORT.md`` and ``agreement.png`` into ``DIR``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pixelmpc_jax.platform_info import device_line
from pixelmpc_jax.strict_json import write_json_atomic

CHUNK = 200  # frames rendered at once (a frame is width x height x 3 floats)


def lap_frames(record: dict, lap: int) -> tuple[np.ndarray, np.ndarray]:
    """Lap ``lap``'s flown ticks of a per-tick record: the states the loop rendered (T, 10) and each tick's target
    gate (T,)."""
    n = int(record["num_ticks"][lap])
    return np.asarray(record["states"][lap, :n]), np.asarray(record["target"][lap, :n], np.int32)


def lap_agreement(record: dict, lap: int, chunk: int = CHUNK) -> dict:
    """:func:`~pixelmpc_jax.perception.detector.image_agreement` over every flown tick of lap ``lap`` of ``record``,
    rendered ``chunk`` frames at a time, with the lap's gates and camera as flown."""
    from pixelmpc_jax.perception import detector
    from pixelmpc_jax.sim import ticks as ticks_lib
    from pixelmpc_jax.world.course import make_course

    course, gates = make_course("alphapilot"), ticks_lib.gates_of(record, lap)
    if gates.centre.shape != course.gates.centre.shape:
        raise ValueError(f"lap {lap} flew {len(gates.centre)} gates, AlphaPilot has {len(course.gates.centre)}: "
                         "the check renders the AlphaPilot hall")
    states, targets = lap_frames(record, lap)
    count = len(states)
    pad = -count % chunk  # the last chunk filled with its last frame: every chunk one shape, the render compiled once
    states = np.concatenate([states, np.repeat(states[-1:], pad, axis=0)])
    targets = np.concatenate([targets, np.repeat(targets[-1:], pad)])
    camera = ticks_lib.camera_of(record)
    parts = [detector.image_agreement(course.replace(gates=gates), states[i:i + chunk], targets[i:i + chunk], camera)
             for i in range(0, len(states), chunk)]
    return {key: np.concatenate([part[key] for part in parts])[:count] for key in parts[0]}


def summarise(frames: dict) -> dict:
    """The figures of frames ``{"found_geometry", "found_image", "partial", "centre_error_px"}`` (each (S,)):
    counts, the share where both detectors agree on found or not, and the centre error's median and 95th percentile
    (pixels) over the frames where both found the gate, all of them and those with the gate partly out of view."""
    geometry, image = np.asarray(frames["found_geometry"], bool), np.asarray(frames["found_image"], bool)
    error, partial = np.asarray(frames["centre_error_px"], float), np.asarray(frames["partial"], bool)
    both = np.isfinite(error)

    def centre(mask):
        values = error[mask]
        return {"frames": int(mask.sum()),
                "median_px": float(np.median(values)) if len(values) else None,
                "p95_px": float(np.percentile(values, 95)) if len(values) else None}

    return {"frames": int(len(geometry)), "partial_frames": int(partial.sum()),
            "found_agree": float(np.mean(geometry == image)) if len(geometry) else None,
            "found_geometry_only": int((geometry & ~image).sum()), "found_image_only": int((image & ~geometry).sum()),
            "centre": centre(both), "centre_partial": centre(both & partial)}


def run(paths, laps: int, out: Path) -> dict:
    """Compare the detectors on the first ``laps`` laps of each per-tick record in ``paths``; write
    ``agreement.json`` (the summary, per lap and over every frame), ``REPORT.md`` and ``agreement.png`` into ``out``
    and return the record."""
    from pixelmpc_jax.sim import ticks as ticks_lib

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per_lap, every = [], []
    for path in paths:
        record = ticks_lib.load(path)
        for lap in range(min(laps, len(record["seed"]))):
            frames = lap_agreement(record, lap)
            every.append(frames)
            per_lap.append({"file": Path(path).name, "seed": int(record["seed"][lap]), **summarise(frames)})
    joined = {key: np.concatenate([frames[key] for frames in every]) for key in every[0]}
    result = {"device": device_line(), "laps": per_lap, "all": summarise(joined)}
    write_json_atomic(out / "agreement.json", result)
    (out / "REPORT.md").write_text(report(result))
    _plot(joined, out / "agreement.png")
    return result


def report(result: dict) -> str:
    """The summary as Markdown: one row per lap and one over every frame."""
    lines = ["# The geometric detector against the image detector on flown laps", "",
             f"Device: {result['device']}.", "",
             "| laps | frames | partly out of view | found agree | geometry only | image only | centre median "
             "[px] | centre p95 [px] | partly out of view: median [px] | p95 [px] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    rows = [(f"{lap['file']} seed {lap['seed']}", lap) for lap in result["laps"]] + [("**all**", result["all"])]
    for name, s in rows:
        lines.append(f"| {name} | {s['frames']} | {s['partial_frames']} | {s['found_agree']:.2%} | "
                     f"{s['found_geometry_only']} | {s['found_image_only']} | {_px(s['centre']['median_px'])} | "
                     f"{_px(s['centre']['p95_px'])} | {_px(s['centre_partial']['median_px'])} | "
                     f"{_px(s['centre_partial']['p95_px'])} |")
    return "\n".join(lines) + "\n\n![centre error](agreement.png)\n"


def _px(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _plot(frames: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    error, partial = np.asarray(frames["centre_error_px"]), np.asarray(frames["partial"], bool)
    both = np.isfinite(error)
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    bins = np.linspace(0, max(6.0, float(np.nanmax(error)) if both.any() else 6.0), 60)
    ax.hist(error[both & ~partial], bins=bins, alpha=0.7, label=f"gate whole in view ({int((both & ~partial).sum())})")
    ax.hist(error[both & partial], bins=bins, alpha=0.7, label=f"partly out of view ({int((both & partial).sum())})")
    ax.set(xlabel="centre distance, geometric vs image detector [px]", ylabel="frames", yscale="log")
    ax.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)
