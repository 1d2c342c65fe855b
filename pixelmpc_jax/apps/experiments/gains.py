"""The frontier gain three ways, each with a bootstrap interval over seeds, and the smallest of them.

A cell's gain is nominal MPPI's avoidable low-visibility time at the cell's lap time over the cell's own (above 1:
better than flying slower). Nominal's avoidable time "at the cell's lap time", three ways:

- **paired** (the headline): each completed lap of the cell against its own seed's nominal frontier, that seed's
  completed nominal laps at every target speed sorted by lap time and joined linearly, read at the lap's time. A
  lap outside its seed's flown lap times (or of a seed with fewer than two completed nominal laps) is never
  extrapolated: it is reported out of range and left out. Gain: the mean of the frontier at the paired laps over
  the mean of their own avoidable times.
- **joined means**: nominal's per-speed means joined linearly, read at the cell's mean lap time (the construction
  of :func:`~pixelmpc_jax.apps.experiments.frontier.build`'s ``frontier_gain``). Where the frontier curves between
  two points far apart, the chord overstates nominal's loss.
- **local fit**: a straight line fitted by least squares to nominal's completed laps within
  :data:`LOCAL_FIT_HALF_WIDTH_S` of the cell's mean lap time, read there; none without laps on both sides of it.

Each divides by the cell's mean avoidable time over the laps it reads, at least :data:`AVOIDABLE_FLOOR_S`. A claim's
bars apply to the smallest of the three (:func:`smallest`). The intervals are a percentile bootstrap over seeds
with a fixed generator seed: a draw resamples the seeds with replacement, each drawn seed bringing its cell lap and
its nominal laps at every speed, so the pairing survives the draw.

Pure numpy: the laps come in as :class:`Laps`, the gains go out as plain numbers.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pixelmpc_jax.timing import CONTROL_DT

AVOIDABLE_FLOOR_S = CONTROL_DT  # a cell with no avoidable loss is divided by one control tick (0.025 s)
BOOTSTRAP_DRAWS = 2000
BOOTSTRAP_LEVEL = 0.90
BOOTSTRAP_SEED = 0  # the generator's seed: an interval is the same every time it is computed
LOCAL_FIT_HALF_WIDTH_S = 2.0  # nominal laps this close in lap time to the cell's mean enter the local fit
LOCAL_FIT_MIN_LAPS = 3
CONSTRUCTIONS = ("paired", "joined_means", "local_fit")


class Laps(NamedTuple):
    """The completed laps of one race.

    Attributes:
        seed: (L,) int, each lap's seed.
        lap_time: (L,) s.
        avoidable: (L,) avoidable time with the target's visibility below 50 %, s.
    """

    seed: np.ndarray
    lap_time: np.ndarray
    avoidable: np.ndarray


def laps(seed, lap_time, avoidable) -> Laps:
    """:class:`Laps` of three equally long sequences."""
    out = Laps(np.asarray(seed, np.int64).reshape(-1), np.asarray(lap_time, np.float64).reshape(-1),
               np.asarray(avoidable, np.float64).reshape(-1))
    if not len(out.seed) == len(out.lap_time) == len(out.avoidable):
        raise ValueError(f"seed, lap_time and avoidable must be equally long, got {[len(a) for a in out]}")
    return out


def completed_laps(result: dict, figure: str = "time_vis_avoidable_s") -> Laps:
    """The completed laps with an avoidable time of one race's results (``{"laps": [...], "seed": first}``); a lap
    that does not record its seed is lap i of the run, seed ``first + i``. With ``figure``, each lap's value of that
    figure (e.g. ``share_target_in_view``) stands where the avoidable time would (:func:`paired_figure`)."""
    first = result.get("seed", 0)
    rows = [(lap.get("seed", first + i), lap["lap_time_s"], lap[figure])
            for i, lap in enumerate(result.get("laps", []))
            if lap.get("success") and lap.get("lap_time_s") is not None
            and lap.get("time_vis_avoidable_s") is not None and lap.get(figure) is not None]
    return laps(*zip(*rows)) if rows else laps([], [], [])


class PairedFigure(NamedTuple):
    """One lap figure of a race and of nominal MPPI at the same lap times (:func:`paired_figure`).

    Attributes:
        nominal: nominal's figure read at each paired lap's time on that lap's seed, the mean over the paired laps.
        cell: the race's own figure, the mean over the same laps.
        laps_paired: how many laps pair (a lap outside its seed's nominal lap times does not).
    """

    nominal: float
    cell: float
    laps_paired: int


def paired_figure(cell: dict, nominal: list[dict], figure: str) -> PairedFigure | None:
    """Nominal MPPI's lap ``figure`` at the race's lap times, paired as the gain pairs them: each completed lap of
    the race ``cell`` read on its own seed's nominal laps (``nominal``: one race's results per target speed) joined
    by lap time (:func:`paired_frontier`), beside the race's own figure, each the mean over the laps that pair; None
    where none pairs. Joining per-speed means instead overstates nominal's loss where the frontier curves."""
    laps_of_cell = completed_laps(cell, figure)
    value, _ = paired_frontier(laps_of_cell, [completed_laps(n, figure) for n in nominal])
    paired = ~np.isnan(value)
    if not paired.any():
        return None
    return PairedFigure(float(np.mean(value[paired])), float(np.mean(laps_of_cell.avoidable[paired])),
                        int(paired.sum()))


def seed_frontiers(nominal: list[Laps]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{seed: (lap times (P,), avoidable (P,))}``: each seed's nominal laps over every speed, by lap time."""
    seeds = np.concatenate([n.seed for n in nominal]) if nominal else np.zeros(0, np.int64)
    times = np.concatenate([n.lap_time for n in nominal]) if nominal else np.zeros(0)
    avoidable = np.concatenate([n.avoidable for n in nominal]) if nominal else np.zeros(0)
    frontiers = {}
    for seed in np.unique(seeds):
        mine = seeds == seed
        order = np.argsort(times[mine], kind="stable")
        frontiers[int(seed)] = times[mine][order], avoidable[mine][order]
    return frontiers


def paired_frontier(cell: Laps, nominal: list[Laps]) -> tuple[np.ndarray, np.ndarray]:
    """Each cell lap's own seed's nominal frontier at its lap time, and the lap-time gap between the two nominal
    laps that bracket it; both (L,), NaN where the lap lies outside its seed's nominal lap times."""
    frontiers = seed_frontiers(nominal)
    value = np.full(len(cell.seed), np.nan)
    gap = np.full(len(cell.seed), np.nan)
    for i, (seed, lap_time) in enumerate(zip(cell.seed, cell.lap_time)):
        xs, ys = frontiers.get(int(seed), (np.zeros(0), np.zeros(0)))
        if len(xs) < 2 or not xs[0] <= lap_time <= xs[-1]:
            continue
        value[i] = np.interp(lap_time, xs, ys)
        above = max(int(np.searchsorted(xs, lap_time)), 1)  # xs[above - 1] <= lap_time <= xs[above]
        gap[i] = xs[above] - xs[above - 1]
    return value, gap


def _gain(frontier: float, avoidable: float) -> float:
    return float(frontier / max(avoidable, AVOIDABLE_FLOOR_S))


def _weighted_mean(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``np.average(values, weights=weights)`` as numpy computes it, to the last bit, without its checks: of one row
    of weights (L,), or of each row of weights (D, L), against ``values`` (L,). Each row is summed alone, as numpy
    sums a 1-D array (pairwise): a reduction over the rows of a 2-D array adds in another order, and a draw's mean lap
    time that moved by a rounding could cross the edge of the local fit's window, where lap times on the control
    tick's grid meet it exactly. A row whose weights sum to 0 gives NaN."""
    products = np.multiply(values, weights)
    if weights.ndim == 1:
        numerator, total = products.sum(), weights.sum()
    else:
        numerator, total = np.array([row.sum() for row in products]), np.array([row.sum() for row in weights])
    with np.errstate(invalid="ignore", divide="ignore"):
        return numerator / total


def _paired_gain(frontier: np.ndarray, avoidable: np.ndarray, weights: np.ndarray) -> float | None:
    paired = ~np.isnan(frontier) & (weights > 0)
    if not paired.any():
        return None
    return _gain(_weighted_mean(frontier[paired], weights[paired]), _weighted_mean(avoidable[paired], weights[paired]))


def _speed_means(nominal: list[Laps], weights: list[np.ndarray], shape: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
    """Each target speed's weighted mean lap time and avoidable time, ``shape + (K,)`` each for weights
    ``shape + (P_k,)`` per speed (NaN where a speed's weights sum to 0)."""
    means = [np.stack([_weighted_mean(getattr(n, field), w) for n, w in zip(nominal, weights)], -1) if nominal
             else np.zeros((*shape, 0)) for field in ("lap_time", "avoidable")]
    return means[0], means[1]


def _joined_means_gain(lap_time: float, avoidable: float, speed_times: np.ndarray, speed_avoidable: np.ndarray
                       ) -> float | None:
    """The gain against nominal's per-speed means (``speed_times``, ``speed_avoidable``: (K,) each, NaN for a speed
    without laps) joined linearly, read at ``lap_time``."""
    points = sorted((float(x), float(y)) for x, y in zip(speed_times, speed_avoidable) if not np.isnan(x))
    if len(points) < 2 or not points[0][0] <= lap_time <= points[-1][0]:
        return None
    xs, ys = np.asarray(points).T
    return _gain(np.interp(lap_time, xs, ys), avoidable)


def local_line(lap_time: float, times: np.ndarray, avoidable: np.ndarray, weights: np.ndarray,
               half_width: float = LOCAL_FIT_HALF_WIDTH_S) -> float | None:
    """The weighted least-squares line through the laps (``times``, ``avoidable``; all (P,)) within
    ``half_width`` of ``lap_time``, read at ``lap_time``; None with fewer than :data:`LOCAL_FIT_MIN_LAPS` of them
    or none on one side of it (no extrapolation).

    ``y(t) = y_bar + b (t - t_bar)``, ``b = sum w (t - t_bar)(y - y_bar) / sum w (t - t_bar)^2``, bars weighted means.
    """
    near = (np.abs(times - lap_time) <= half_width) & (weights > 0)
    if near.sum() < LOCAL_FIT_MIN_LAPS or not ((times[near] < lap_time).any() and (times[near] > lap_time).any()):
        return None
    t, y, w = times[near], avoidable[near], weights[near]
    t_bar, y_bar = _weighted_mean(t, w), _weighted_mean(y, w)
    slope = np.sum(w * (t - t_bar) * (y - y_bar)) / np.sum(w * (t - t_bar) ** 2)
    return float(y_bar + slope * (lap_time - t_bar))


def _pooled(nominal: list[Laps], field: str) -> np.ndarray:
    return np.concatenate([getattr(n, field) for n in nominal]) if nominal else np.zeros(0)


def three_gains(cell: Laps, nominal: list[Laps], frontier: np.ndarray, cell_weights: np.ndarray | None = None,
                nominal_weights: list[np.ndarray] | None = None, half_width: float = LOCAL_FIT_HALF_WIDTH_S) -> dict:
    """``{construction: gain or None}`` of :data:`CONSTRUCTIONS`, each lap weighted (a bootstrap draw's count of
    its seed; 1 by default).

    Args:
        cell: the cell's completed laps.
        nominal: nominal MPPI's completed laps, one :class:`Laps` per target speed.
        frontier: (L,) :func:`paired_frontier` of the cell's laps.
    """
    cell_weights = np.ones(len(cell.seed)) if cell_weights is None else cell_weights
    nominal_weights = [np.ones(len(n.seed)) for n in nominal] if nominal_weights is None else nominal_weights
    if cell_weights.sum() == 0:
        return dict.fromkeys(CONSTRUCTIONS)
    lap_time, avoidable = _weighted_mean(cell.lap_time, cell_weights), _weighted_mean(cell.avoidable, cell_weights)
    pooled_weights = np.concatenate(nominal_weights) if nominal else np.zeros(0)
    return _three_gains_at(cell, frontier, float(lap_time), float(avoidable), *_speed_means(nominal, nominal_weights),
                           _pooled(nominal, "lap_time"), _pooled(nominal, "avoidable"), pooled_weights,
                           cell_weights, half_width)


def _three_gains_at(cell: Laps, frontier: np.ndarray, lap_time: float, avoidable: float, speed_times: np.ndarray,
                    speed_avoidable: np.ndarray, pooled_times: np.ndarray, pooled_avoidable: np.ndarray,
                    pooled_weights: np.ndarray, cell_weights: np.ndarray, half_width: float) -> dict:
    """:func:`three_gains` from the weighted means it reads: the cell's, each speed's, and nominal's laps pooled."""
    line = local_line(lap_time, pooled_times, pooled_avoidable, pooled_weights, half_width)
    return {"paired": _paired_gain(frontier, cell.avoidable, cell_weights),
            "joined_means": _joined_means_gain(lap_time, avoidable, speed_times, speed_avoidable),
            "local_fit": None if line is None else _gain(line, avoidable)}


def seed_intervals(cell: Laps, nominal: list[Laps], frontier: np.ndarray, draws: int = BOOTSTRAP_DRAWS,
                   level: float = BOOTSTRAP_LEVEL, seed: int = BOOTSTRAP_SEED,
                   half_width: float = LOCAL_FIT_HALF_WIDTH_S) -> dict:
    """``{construction: (low, high) or None}``: the percentile bootstrap over seeds of :func:`three_gains`. A draw
    resamples the seeds (the cell's and nominal's together) with replacement and weights every lap by its seed's
    count; draws where a construction has no gain are dropped, and a construction with a gain in fewer than half the
    draws gets no interval.

    The weighted means every draw reads (the cell's, each speed's) are computed for all draws before the draws are
    read, each as :func:`three_gains` computes it for one, so each draw's gains are :func:`three_gains`'s to the
    last bit."""
    seeds = np.unique(np.concatenate([cell.seed, *(n.seed for n in nominal)]))
    if len(cell.seed) == 0 or len(seeds) == 0:
        return dict.fromkeys(CONSTRUCTIONS)
    rng = np.random.default_rng(seed)
    drawn = rng.integers(0, len(seeds), (draws, len(seeds)))
    counts = np.zeros((draws, len(seeds)))
    np.add.at(counts, (np.arange(draws)[:, None], drawn), 1.0)  # (draws, seeds) how often each seed was drawn
    cell_weights = counts[:, np.searchsorted(seeds, cell.seed)]  # (draws, L)
    nominal_weights = [counts[:, np.searchsorted(seeds, n.seed)] for n in nominal]  # (draws, P_k) per speed
    lap_times, avoidables = _weighted_mean(cell.lap_time, cell_weights), _weighted_mean(cell.avoidable, cell_weights)
    speed_times, speed_avoidable = _speed_means(nominal, nominal_weights, (draws,))  # (draws, K) each
    pooled_times, pooled_avoidable = _pooled(nominal, "lap_time"), _pooled(nominal, "avoidable")
    pooled_weights = np.concatenate(nominal_weights, axis=1) if nominal else np.zeros((draws, 0))
    values: dict = {name: [] for name in CONSTRUCTIONS}
    for d in np.flatnonzero(cell_weights.sum(1) > 0):  # a draw without the cell's seeds has no gain
        gains = _three_gains_at(cell, frontier, float(lap_times[d]), float(avoidables[d]), speed_times[d],
                                speed_avoidable[d], pooled_times, pooled_avoidable, pooled_weights[d],
                                cell_weights[d], half_width)
        for name, gain in gains.items():
            if gain is not None:
                values[name].append(gain)
    tail = 100 * (1 - level) / 2
    return {name: (float(np.percentile(v, tail)), float(np.percentile(v, 100 - tail))) if len(v) >= draws / 2
            else None for name, v in values.items()}


def smallest(gains: dict) -> dict | None:
    """The construction with the smallest gain (``{"construction", "gain", "interval"}``; the one a claim's bars
    apply to) of ``{construction: {"gain", "interval"}}``; None when none has a gain."""
    known = [name for name in CONSTRUCTIONS if (gains.get(name) or {}).get("gain") is not None]
    if not known:
        return None
    name = min(known, key=lambda n: gains[n]["gain"])  # on a tie, the first of CONSTRUCTIONS
    return {"construction": name, "gain": gains[name]["gain"], "interval": gains[name].get("interval")}


def frontier_gains(cell: Laps, nominal: list[Laps], draws: int = BOOTSTRAP_DRAWS, level: float = BOOTSTRAP_LEVEL,
                   seed: int = BOOTSTRAP_SEED, half_width: float = LOCAL_FIT_HALF_WIDTH_S) -> dict:
    """The three gains of a cell's completed laps against nominal's (one :class:`Laps` per target speed), their
    intervals, the smallest, and each lap's pairing: ``{construction: {"gain", "interval"}, "smallest",
    "laps_paired", "laps_out_of_range", "widest_gap_s" (the widest lap-time gap between the nominal laps that
    bracket a paired lap), "laps": [{"seed", "lap_time_s", "avoidable_s", "frontier_avoidable_s" (None: out of
    range), "gap_s"}]}``."""
    frontier, gap = paired_frontier(cell, nominal)
    point = three_gains(cell, nominal, frontier, half_width=half_width)
    intervals = seed_intervals(cell, nominal, frontier, draws, level, seed, half_width)
    out: dict = {name: {"gain": point[name], "interval": intervals[name]} for name in CONSTRUCTIONS}
    paired = ~np.isnan(frontier)
    out.update(smallest=smallest(out), laps_paired=int(paired.sum()), laps_out_of_range=int((~paired).sum()),
               widest_gap_s=float(np.max(gap[paired])) if paired.any() else None,
               laps=[{"seed": int(s), "lap_time_s": float(t), "avoidable_s": float(a),
                      "frontier_avoidable_s": None if np.isnan(f) else float(f),
                      "gap_s": None if np.isnan(g) else float(g)}
                     for s, t, a, f, g in zip(cell.seed, cell.lap_time, cell.avoidable, frontier, gap)])
    return out
