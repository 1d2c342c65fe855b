"""The frontier gain three ways (apps/experiments/gains.py): hand-computed frontiers where the answer is known by
construction, a curved frontier where the chord overstates, laps outside their seed's range, the seed bootstrap."""

import numpy as np
import pytest

from pixelmpc_jax.apps.experiments import gains as G


def nominal_at(lap_times_by_seed: dict, avoidable) -> list[G.Laps]:
    """One :class:`G.Laps` per target speed: speed k gives seed s the lap time ``lap_times_by_seed[s][k]`` and the
    avoidable time ``avoidable(lap time)`` (or ``avoidable[s][k]`` from a dict)."""
    seeds = sorted(lap_times_by_seed)
    speeds = len(lap_times_by_seed[seeds[0]])
    out = []
    for k in range(speeds):
        times = [lap_times_by_seed[s][k] for s in seeds]
        values = [avoidable[s][k] for s in seeds] if isinstance(avoidable, dict) else [avoidable(t) for t in times]
        out.append(G.laps(seeds, times, values))
    return out


def test_on_a_straight_frontier_the_three_constructions_agree_with_the_answer_known_by_construction():
    """avoidable = 0.5 (40 - t) for every seed (seed s flies 0.5 s slower at every speed); the cell's laps at
    33 + 0.5 s with 0.5 s avoidable. Nominal at 33.75 s (the mean) has 3.125 s: a gain of 6.25, every way."""
    line = lambda t: 0.5 * (40.0 - t)  # noqa: E731
    nominal = nominal_at({s: [30.0 + 0.5 * s, 32.0 + 0.5 * s, 34.0 + 0.5 * s, 36.0 + 0.5 * s] for s in range(4)}, line)
    cell = G.laps(range(4), [33.0 + 0.5 * s for s in range(4)], [0.5] * 4)
    out = G.frontier_gains(cell, nominal, draws=200)
    for name in G.CONSTRUCTIONS:
        assert out[name]["gain"] == pytest.approx(6.25), name
    assert out["laps_paired"] == 4 and out["laps_out_of_range"] == 0
    assert out["widest_gap_s"] == pytest.approx(2.0)
    assert [lap["frontier_avoidable_s"] for lap in out["laps"]] == pytest.approx([line(33.0 + 0.5 * s)
                                                                                  for s in range(4)])
    assert out["smallest"]["construction"] == "paired" and out["smallest"]["gain"] == pytest.approx(6.25)


def curved(t):
    return 0.05 * (t - 43.0) ** 2  # 7.2 s at 31 s laps, 3.2 s at 35 s, 0.8 s at 39 s


def test_on_a_curved_frontier_the_chord_across_a_gap_overstates_and_a_dense_frontier_does_not():
    """The cell flies 35 s laps with 0.8 s avoidable. Nominal flown only at 31 s and 39 s: the chord gives 4.0 s at
    35 s (a gain of 5.0), where the frontier has 3.2 s: overstated by a quarter. Flown every 2 s, the paired and the
    joined means read 3.2 s (gain 4.0); the local line through 33, 35 and 37 s reads their mean, 10/3 s
    (gain 4.17): a straight line over a convex curve overstates a little too. The smallest is the paired one."""
    seeds = range(3)
    cell = G.laps(seeds, [35.0] * 3, [0.8] * 3)
    coarse = G.frontier_gains(cell, nominal_at({s: [31.0, 39.0] for s in seeds}, curved), draws=100)
    assert coarse["joined_means"]["gain"] == pytest.approx(5.0)
    assert coarse["paired"]["gain"] == pytest.approx(5.0)  # paired, but against a frontier with a gap
    assert coarse["widest_gap_s"] == pytest.approx(8.0)
    assert coarse["local_fit"]["gain"] is None  # no nominal lap within 2 s of 35 s
    dense = G.frontier_gains(cell, nominal_at({s: [31.0, 33.0, 35.0, 37.0, 39.0] for s in seeds}, curved), draws=100)
    assert dense["paired"]["gain"] == pytest.approx(4.0)
    assert dense["joined_means"]["gain"] == pytest.approx(4.0)
    assert dense["local_fit"]["gain"] == pytest.approx((5.0 + 3.2 + 1.8) / 3 / 0.8)
    assert dense["smallest"]["construction"] == "paired" and dense["smallest"]["gain"] == pytest.approx(4.0)


def two_seeds():
    """Seed 0's frontier (30 s, 8 s) - (40 s, 2 s) is twice seed 1's (30 s, 4 s) - (40 s, 1 s)."""
    return nominal_at({0: [30.0, 40.0], 1: [30.0, 40.0]}, {0: [8.0, 2.0], 1: [4.0, 1.0]})


def test_each_lap_is_read_on_its_own_seeds_frontier():
    """Seed 0's lap at 32 s against its frontier: 6.8 s; seed 1's at 38 s: 1.6 s; each lap 1 s avoidable. Paired:
    4.2. The joined means read the mean frontier (30 s, 6 s) - (40 s, 1.5 s) at the mean lap, 35 s: 3.75."""
    cell = G.laps([0, 1], [32.0, 38.0], [1.0, 1.0])
    out = G.frontier_gains(cell, two_seeds(), draws=100)
    assert [lap["frontier_avoidable_s"] for lap in out["laps"]] == pytest.approx([6.8, 1.6])
    assert out["paired"]["gain"] == pytest.approx(4.2)
    assert out["joined_means"]["gain"] == pytest.approx(3.75)
    assert out["smallest"] == {"construction": "joined_means", "gain": pytest.approx(3.75),
                               "interval": out["joined_means"]["interval"]}


def test_a_lap_outside_its_seeds_flown_range_is_out_of_range_and_never_extrapolated():
    """Seed 0 also flies a 29 s lap (its fastest nominal lap took 30 s) with 5 s avoidable, seed 7 one with no
    nominal laps at all: both are reported out of range and left out of the paired gain, which stays 4.2. A lap
    exactly at the range's end is in it."""
    cell = G.laps([0, 1, 0, 7], [32.0, 38.0, 29.0, 35.0], [1.0, 1.0, 5.0, 5.0])
    out = G.frontier_gains(cell, two_seeds(), draws=100)
    assert out["laps_paired"] == 2 and out["laps_out_of_range"] == 2
    assert out["laps"][2]["frontier_avoidable_s"] is None and out["laps"][3]["frontier_avoidable_s"] is None
    assert out["laps"][2]["gap_s"] is None
    assert out["paired"]["gain"] == pytest.approx(4.2)
    edge = G.paired_frontier(G.laps([1], [30.0], [1.0]), two_seeds())
    assert edge[0][0] == pytest.approx(4.0) and edge[1][0] == pytest.approx(10.0)
    nothing = G.frontier_gains(G.laps([7], [35.0], [1.0]), two_seeds(), draws=50)
    assert nothing["paired"] == {"gain": None, "interval": None} and nothing["widest_gap_s"] is None


def test_the_local_line_needs_laps_on_both_sides_and_weights_them():
    times, avoidable = np.asarray([33.0, 34.0, 36.0]), np.asarray([4.0, 3.0, 1.0])
    assert G.local_line(35.0, times, avoidable, np.ones(3)) == pytest.approx(2.0)  # the line 37 - t, exactly
    assert G.local_line(32.0, times, avoidable, np.ones(3)) is None  # every lap on one side: no extrapolation
    assert G.local_line(35.0, times, avoidable, np.asarray([1.0, 0.0, 1.0])) is None  # two laps drawn: too few
    # a lap counted twice pulls the line: through (33, 4) x2 and (34, 3), (36, 1) ... still 37 - t, all on it
    assert G.local_line(35.0, times, avoidable, np.asarray([2.0, 1.0, 1.0])) == pytest.approx(2.0)
    bent = np.asarray([4.0, 3.0, 2.0])  # (36, 2) off the line
    once, twice = (G.local_line(35.0, times, bent, np.asarray(w)) for w in ([1.0, 1.0, 1.0], [1.0, 1.0, 3.0]))
    assert once != pytest.approx(twice) and twice > once  # the heavier lap above the line lifts the reading


def test_the_seed_bootstrap_is_reproducible_and_resamples_whole_seeds():
    """Identical seeds give a zero-width interval at the gain; seeds that differ give an interval around it, the same
    on every call (a fixed generator seed)."""
    line = lambda t: 0.5 * (40.0 - t)  # noqa: E731
    same = G.frontier_gains(G.laps(range(5), [33.0] * 5, [0.5] * 5),
                            nominal_at({s: [30.0, 32.0, 34.0, 36.0] for s in range(5)}, line), draws=300)
    for name in G.CONSTRUCTIONS:
        assert same[name]["interval"] == pytest.approx((same[name]["gain"],) * 2), name
    cell = G.laps(range(6), [32.0, 33.0, 34.0, 33.0, 32.5, 33.5], [0.3, 0.5, 0.9, 0.4, 0.7, 0.6])
    nominal = nominal_at({s: [30.0 + 0.2 * s, 32.0, 34.0 - 0.1 * s, 36.0] for s in range(6)},
                         lambda t: 0.5 * (40.0 - t) + 0.01 * t ** 1.5)
    first, again = (G.frontier_gains(cell, nominal, draws=400) for _ in range(2))
    for name in G.CONSTRUCTIONS:
        low, high = first[name]["interval"]
        assert low < first[name]["gain"] < high and high - low > 0.5, name
        assert again[name]["interval"] == first[name]["interval"]
    other = G.frontier_gains(cell, nominal, draws=400, seed=1)
    assert other["paired"]["interval"] != first["paired"]["interval"]


def test_each_bootstrap_draw_gives_three_gains_of_its_own_weights_to_the_last_bit():
    """The bootstrap computes every draw's weighted means before it reads the draws; each draw's gains must still be
    :func:`G.three_gains` of that draw's seed counts, bit for bit. Lap times on the control tick's grid put a draw's
    mean exactly at the edge of the local fit's window, where a rounding would change which laps enter it; one speed
    has no laps and some draws miss every seed of the cell."""
    rng = np.random.default_rng(3)
    grid = lambda n: np.round(rng.uniform(26.0, 36.0, n) / 0.025) * 0.025  # noqa: E731
    cell = G.laps([0, 0, 1, 4, 4, 4, 5, 6, 7, 7], grid(10), rng.uniform(0.0, 2.0, 10) * (rng.random(10) > 0.3))
    nominal = [G.laps(rng.integers(0, 9, 12), grid(12), rng.uniform(2.0, 15.0, 12)) for _ in range(5)]
    nominal.append(G.laps([], [], []))
    frontier, _ = G.paired_frontier(cell, nominal)
    draws = 500
    seeds = np.unique(np.concatenate([cell.seed, *(n.seed for n in nominal)]))
    drawn = np.random.default_rng(G.BOOTSTRAP_SEED).integers(0, len(seeds), (draws, len(seeds)))
    values: dict = {name: [] for name in G.CONSTRUCTIONS}
    for row in drawn:  # seed_intervals' draws, one at a time
        count = np.bincount(row, minlength=len(seeds)).astype(float)
        weights = [count[np.searchsorted(seeds, n.seed)] for n in nominal]
        for name, gain in G.three_gains(cell, nominal, frontier, count[np.searchsorted(seeds, cell.seed)],
                                        weights).items():
            if gain is not None:
                values[name].append(gain)
    assert 0 < len(values["paired"]) < draws  # some draws hold none of the cell's paired laps
    tail = 100 * (1 - G.BOOTSTRAP_LEVEL) / 2
    expected = {name: (float(np.percentile(v, tail)), float(np.percentile(v, 100 - tail))) if len(v) >= draws / 2
                else None for name, v in values.items()}
    assert G.seed_intervals(cell, nominal, frontier, draws=draws) == expected


def test_completed_laps_take_the_seed_of_the_lap_or_of_its_place_in_the_run():
    result = {"seed": 10, "laps": [
        {"success": True, "lap_time_s": 33.0, "time_vis_avoidable_s": 1.0},
        {"success": False, "lap_time_s": None, "time_vis_avoidable_s": 0.5},
        {"success": True, "lap_time_s": 34.0, "time_vis_avoidable_s": 2.0, "seed": 99}]}
    laps = G.completed_laps(result)
    assert laps.seed.tolist() == [10, 99] and laps.lap_time.tolist() == [33.0, 34.0]
    assert G.completed_laps({"laps": []}).seed.shape == (0,)
    with pytest.raises(ValueError, match="equally long"):
        G.laps([0, 1], [30.0], [1.0])
    assert G.smallest({name: {"gain": None, "interval": None} for name in G.CONSTRUCTIONS}) is None


def test_a_lap_figure_is_paired_by_seed_as_the_gain_is():
    """Seed 0 flies nominal laps of 30 and 34 s in view 80 % and 90 %, seed 1 of 32 and 36 s in view 70 % and 94 %;
    the race's laps (33 s, 34 s; in view 97 %, 95 %) read 87.5 % and 82 % on their own seeds: 84.75 % paired. A lap
    outside its seed's lap times (seed 2 has one nominal lap) is left out, and none pairing gives None."""
    def race(seeds, times, shares, success=True):
        return {"laps": [{"seed": s, "lap_time_s": t, "share_target_in_view": v, "time_vis_avoidable_s": 1.0,
                          "success": success} for s, t, v in zip(seeds, times, shares)]}

    nominal = [race([0, 1, 2], [30.0, 32.0, 31.0], [0.80, 0.70, 0.5]), race([0, 1], [34.0, 36.0], [0.90, 0.94])]
    cell = race([0, 1, 2], [33.0, 34.0, 33.0], [0.97, 0.95, 0.99])
    paired = G.paired_figure(cell, nominal, "share_target_in_view")
    assert paired.laps_paired == 2
    assert paired.nominal == pytest.approx((0.875 + 0.82) / 2) and paired.cell == pytest.approx(0.96)
    assert G.paired_figure(race([2], [33.0], [0.9]), nominal, "share_target_in_view") is None
    failed = race([0], [33.0], [0.9], success=False)  # a lap not finished pairs with nothing
    assert G.paired_figure(failed, nominal, "share_target_in_view") is None
