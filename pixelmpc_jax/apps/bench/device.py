"""The device suite: what a GPU is asked to show, in one prepared run built to take under 8 minutes on one card.

    pixelmpc bench device --out DIR [--max-samples N] [--repeats R] [--laps L] [--lap-seconds S]

Three parts, each written into ``DIR/device.json`` as soon as it is done (an interrupted run keeps the parts it
finished, and says ``"interrupted": true``):

1. ``table1``: at the paper's size (N = 512 samples, T = 80 steps) the PixelMPC step with the DOF pixel model, the
   same step with vdof, nominal MPPI's step (:mod:`~pixelmpc_jax.apps.bench.controller`), and the DOF network alone
   over 512 samples x 80 sequential steps, the paper's Table I row (8.6 ms on a GTX 1060;
   :mod:`~pixelmpc_jax.apps.bench.table1`).
2. ``scaling``: the DOF step from 512 samples, doubling up to ``max_samples`` (16,384), T = 80. Its 512 point is
   the ``table1`` row (one step, measured once).
3. ``race``: a batch of ``laps`` laps of the main race (the ``best`` preset, true state, seeds 0..laps-1) flown in
   one vmapped call, as ``pixelmpc race --controller pixelmpc --laps LAPS --batch LAPS`` flies them
   (:func:`~pixelmpc_jax.apps.racing.race.fly_batch`): flown once to compile, then timed once. Its figures: wall
   time, laps finished, ticks per second (the ticks every lap flew, over the wall time) and the real-time factor
   (the simulated seconds of every lap over the wall time; ``batch_ticks_per_s``: the longest lap's ticks over it).

Then ``DIR/device_scaling.png``: step time against samples on log axes, the goals marked. The goals (:data:`GOALS`):
the DOF step at most 1 ms at 512 x 80 and at most 2 ms at 16,384 x 80.

Every step is timed by :func:`~pixelmpc_jax.apps.bench.measure.measure`: compiled outside the timed region, every
call blocked until ready, ``repeats`` timed calls, median and spread.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from pixelmpc_jax import timing
from pixelmpc_jax.apps.bench import controller, table1
from pixelmpc_jax.apps.racing import race as race_lib
from pixelmpc_jax.apps.racing.presets import preset
from pixelmpc_jax.control.mppi_checks import NUM_SAMPLES_RANGE
from pixelmpc_jax.platform_info import device_description
from pixelmpc_jax.strict_json import write_json_atomic

JSON_NAME = "device.json"
PLOT_NAME = "device_scaling.png"
PAPER_SAMPLES, PAPER_HORIZON = 512, 80
MAX_SAMPLES = 16_384  # the top of the scaling, where MPPI-Generic reports 0.39 ms (T = 100, RTX 4090)
SAMPLES_LIMIT = NUM_SAMPLES_RANGE.hi  # what MPPIConfig takes
LAP_SECONDS_LIMIT = 600.0
RACE_LAPS = 64
RACE_PRESET = "best"
GOALS = {PAPER_SAMPLES: 1.0, MAX_SAMPLES: 2.0}  # samples -> the DOF step's median, ms, at most (T = 80)
PARTS = ("table1", "scaling", "race")
SCALING_ROW_BUDGET_S = 10.0  # each scaling row times about this long at most (at least 5 calls)


@dataclasses.dataclass(frozen=True)
class DeviceSuiteConfig:
    """The suite's sizes; the defaults are the GPU run's, smaller values a check on a CPU.

    Attributes:
        max_samples: the largest N of the scaling: 512 times a power of two, up to 2^20.
        repeats: timed calls of each step (fewer where one takes long: ``measure``'s rules).
        laps: laps of the race, flown in one batch.
        lap_seconds: each lap's time limit, s (a lap of the course takes 25-35 s at the preset's pace).
    """

    max_samples: int = MAX_SAMPLES
    repeats: int = 50
    laps: int = RACE_LAPS
    lap_seconds: float = timing.LAP_TIME_LIMIT_S

    def __post_init__(self):
        n = self.max_samples
        whole = isinstance(n, int) and not isinstance(n, bool)
        if not (whole and PAPER_SAMPLES <= n <= SAMPLES_LIMIT and n % PAPER_SAMPLES == 0
                and (n // PAPER_SAMPLES).bit_count() == 1):
            raise ValueError(f"max_samples must be 512 times a power of two (512, 1024, ..., {SAMPLES_LIMIT}), "
                             f"got {n!r}")
        for name in ("repeats", "laps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        seconds = self.lap_seconds
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) \
                or not timing.CONTROL_DT <= seconds <= LAP_SECONDS_LIMIT:
            raise ValueError(f"lap_seconds must be a number of seconds in [{timing.CONTROL_DT:g}, "
                             f"{LAP_SECONDS_LIMIT:g}], got {seconds!r}")

    @property
    def samples(self) -> tuple[int, ...]:
        """The scaling's N: 512, 1024, ..., max_samples."""
        return tuple(PAPER_SAMPLES << k for k in range((self.max_samples // PAPER_SAMPLES).bit_length()))


# --------------------------------------------------------------------------------------------------
# The parts.
# --------------------------------------------------------------------------------------------------


TABLE1_STEPS = ("dof", "vdof", "nominal", "dof_network")  # each table1 row's ``step``, in the order they run


def table1_rows(repeats: int, log=print) -> list[dict]:
    """At 512 x 80: the PixelMPC step with the DOF ("dof") and with vdof ("vdof"), nominal MPPI's ("nominal") and
    the DOF network alone ("dof_network", the paper's row); each row's ``step`` names it."""
    n, t = PAPER_SAMPLES, PAPER_HORIZON
    measure = {"dof": lambda: controller.pixelmpc_row(n, t, 1.0, repeats, group="table1"),
               "vdof": lambda: controller.pixelmpc_row(n, t, 1.0, repeats, group="table1", pixel_model="vdof"),
               "nominal": lambda: controller.nominal_row(n, t, repeats, group="table1"),
               "dof_network": lambda: table1.dof_rows(repeats=repeats, cases=[table1.PAPER_DOF_SIZE])[0]}
    rows = []
    for step in TABLE1_STEPS:
        log(f"  {step}, {n} x {t}")
        rows.append({**measure[step](), "step": step})
    return rows


def scaling_rows(config: DeviceSuiteConfig, dof_step: dict, log=print) -> list[dict]:
    """The DOF step at every N of ``config.samples``, T = 80; ``dof_step`` (the table1 row) is its 512 point."""
    rows = [{**dof_step, "group": "scaling", "measured_in": "table1"}]
    for n in config.samples[1:]:
        log(f"  N = {n}")
        rows += controller.scaling_rows(repeats=config.repeats, max_seconds_per_row=SCALING_ROW_BUDGET_S,
                                        samples=(n,), horizons=(PAPER_HORIZON,))
    return rows


def race_figures(laps: int, lap_seconds: float, log=print) -> dict:
    """A batch of ``laps`` laps of the ``best`` race (true state, seeds 0..laps-1) flown in one vmapped call, as
    ``pixelmpc race`` flies a batch (:func:`~pixelmpc_jax.apps.racing.race.fly_batch`): once to compile, then once
    timed, from the worlds' making to the logs on the host (the laps' metrics, computed after, are not timed)."""
    spec = preset(RACE_PRESET).replace(laps=laps, max_time_s=float(lap_seconds))
    race = race_lib.prepare(spec, batch_size=laps)
    seeds = list(range(spec.seed, spec.seed + laps))
    log(f"  compiling and flying {laps} lap(s) of {lap_seconds:g} s at most")
    start = time.perf_counter()
    race_lib.fly_batch(race, seeds)
    first_s = time.perf_counter() - start
    log(f"  flying them again, timed (the first flight took {first_s:.1f} s)")
    start = time.perf_counter()
    flown = race_lib.fly_batch(race, seeds)
    wall_s = time.perf_counter() - start
    ticks = np.asarray([int(lap_log.num_ticks) for lap_log, _ in flown])
    finished = np.asarray([bool(lap_log.finished) for lap_log, _ in flown])
    simulated_s = float(ticks.sum()) * timing.CONTROL_DT
    return {
        "preset": RACE_PRESET, "controller": spec.controller, "estimator": spec.estimator, "speed": spec.speed,
        "course": spec.course, "laps": laps, "batch_size": race.batch_size, "lap_seconds": spec.max_time_s,
        "num_samples": spec.config.mppi.num_samples, "horizon": spec.config.mppi.horizon,
        "sample_devices": race.flight.sample_devices,
        "wall_s": wall_s, "first_flight_s": first_s, "compile_s": max(first_s - wall_s, 0.0),
        "laps_finished": int(finished.sum()),
        "lap_time_s_median": float(np.median(ticks[finished])) * timing.CONTROL_DT if finished.any() else None,
        "ticks": int(ticks.sum()), "ticks_longest_lap": int(ticks.max()),
        "ticks_per_s": float(ticks.sum()) / wall_s, "batch_ticks_per_s": float(ticks.max()) / wall_s,
        "simulated_s": simulated_s, "real_time_factor": simulated_s / wall_s,
    }


# --------------------------------------------------------------------------------------------------
# The run.
# --------------------------------------------------------------------------------------------------


def summarize(result: dict) -> dict:
    """The headline figures of the parts done, and each goal: True or False where measured, None where not."""
    steps = {r["step"]: r["median_ms"] for r in result.get("table1", [])}
    by_n = {r["num_samples"]: r["median_ms"] for r in result.get("scaling", [])}
    if "dof" in steps:
        by_n.setdefault(PAPER_SAMPLES, steps["dof"])
    race = result.get("race") or {}
    summary = {
        "dof_step_median_ms": {n: by_n[n] for n in sorted(by_n)},
        **{f"{step}_median_ms": steps.get(step) for step in TABLE1_STEPS[1:]},
        "race_wall_s": race.get("wall_s"),
        "race_laps_finished": race.get("laps_finished"),
        "race_ticks_per_s": race.get("ticks_per_s"),
        "race_real_time_factor": race.get("real_time_factor"),
    }
    summary["goals"] = {f"dof_step_ms at {n} x {PAPER_HORIZON} <= {limit:g}": (by_n[n] <= limit if n in by_n else None)
                        for n, limit in GOALS.items()}
    return summary


def _write(out: Path, result: dict) -> None:
    result["summary"] = summarize(result)
    write_json_atomic(out / JSON_NAME, result, indent=1)


def run_device_suite(out_dir, config: DeviceSuiteConfig = DeviceSuiteConfig()) -> dict:
    """Run the suite's parts into ``out_dir``: ``device.json`` rewritten after each part, then the plot.

    Returns:
        the device.json content: ``device`` (the platform, ``device_kind`` of ``jax.devices()[0]``, jax and jaxlib
        versions, the CPU), ``config``, ``goals``, one entry per part done (``table1`` and ``scaling``: bench rows;
        ``race``: :func:`race_figures`), ``parts_done``, ``interrupted``, ``wall_s`` and ``summary``
        (:func:`summarize`).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def log(message: str) -> None:
        print(f"[{time.perf_counter() - start:7.1f} s] {message}", flush=True)

    device = device_description()
    result = {"suite": "device", "device": device, "config": dataclasses.asdict(config),
              "goals": {f"dof_step_ms at {n} x {PAPER_HORIZON}": limit for n, limit in GOALS.items()},
              "parts_done": [], "interrupted": False, "wall_s": 0.0}
    log(f"device {device['platform']} ({device['device_kind']}), {device['num_devices']} device(s); "
        f"jax {device['jax']}; samples {', '.join(map(str, config.samples))}; {config.laps} lap(s); "
        f"{config.repeats} repeats; writing {out / JSON_NAME}")
    parts = {"table1": lambda: table1_rows(config.repeats, log),
             "scaling": lambda: scaling_rows(config, next(r for r in result["table1"] if r["step"] == "dof"), log),
             "race": lambda: race_figures(config.laps, config.lap_seconds, log)}
    try:
        for part in PARTS:
            log(f"{part}")
            result[part] = parts[part]()
            result["parts_done"].append(part)
            result["wall_s"] = time.perf_counter() - start
            _write(out, result)
    except KeyboardInterrupt:
        result["interrupted"] = True
        result["wall_s"] = time.perf_counter() - start
        _write(out, result)
        print(f"interrupted: the parts done ({', '.join(result['parts_done']) or 'none'}) are in {out / JSON_NAME}")
        raise
    plot_device_scaling(result, out / PLOT_NAME)
    log(f"wrote {out / JSON_NAME} and {out / PLOT_NAME}")
    print(headline(result), flush=True)
    return result


def headline(result: dict) -> str:
    """One paragraph of the figures."""
    s = result["summary"]
    steps = ", ".join(f"N={n}: {ms:.3f}" for n, ms in s["dof_step_median_ms"].items())
    race = result.get("race")
    lap = (f"; {race['laps']} laps of the {race['preset']} race in one batch: {race['wall_s']:.1f} s wall, "
           f"{race['laps_finished']} finished, {race['ticks_per_s']:.0f} ticks/s, "
           f"{race['real_time_factor']:.1f}x real time (compile {race['compile_s']:.1f} s)") if race else ""
    return (f"{result['device']['device_kind']}: DOF step (T={PAPER_HORIZON}) median ms {steps}; vdof "
            f"{s['vdof_median_ms']:.3f} ms, nominal MPPI {s['nominal_median_ms']:.3f} ms, DOF network alone "
            f"{s['dof_network_median_ms']:.3f} ms{lap}; goals {s['goals']}")


def plot_device_scaling(result: dict, path) -> None:
    """The DOF step's median (bars: min to p95) against N on log axes, vdof and nominal MPPI at 512, the goals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    rows = sorted(result.get("scaling", []), key=lambda r: r["num_samples"])
    if rows:
        n = np.asarray([r["num_samples"] for r in rows])
        median = np.asarray([r["median_ms"] for r in rows])
        spread = [median - np.asarray([r["min_ms"] for r in rows]), np.asarray([r["p95_ms"] for r in rows]) - median]
        ax.errorbar(n, median, yerr=spread, fmt="o-", capsize=3, label="PixelMPC step, DOF (min to p95)")
    markers = {"vdof": ("s", "PixelMPC step, vdof"), "nominal": ("^", "nominal MPPI step"),
               "dof_network": ("x", "DOF network alone (the paper's Table I row)")}
    for r in result.get("table1", []):
        if r["step"] in markers:
            marker, label = markers[r["step"]]
            ax.plot(r["num_samples"], r["median_ms"], marker, label=label)
    goal_n = sorted(GOALS)
    ax.plot(goal_n, [GOALS[n] for n in goal_n], "rv--", lw=0.8, label="goal (at most)")
    for n in goal_n:
        ax.annotate(f"≤ {GOALS[n]:g} ms", (n, GOALS[n]), textcoords="offset points", xytext=(0, 7), ha="center",
                    color="r")
    ax.set_xlim(goal_n[0] / 1.6, max([goal_n[-1], *(r["num_samples"] for r in rows)]) * 1.6)
    ax.set(xscale="log", yscale="log", xlabel="samples N (T = 80)", ylabel="median step time (ms)",
           title=f"{result['device']['device_kind']}, jax {result['device']['jax']}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
