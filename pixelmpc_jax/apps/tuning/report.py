"""What ``pixelmpc tune`` writes: the trials (``trials.json``, ``trials.csv``), the best trial's race (``best.json``),
the plot of the search (``tune.png``) and the validation table (``validation.json``, ``validation.md``)."""

from __future__ import annotations

import csv
import datetime
from pathlib import Path

from pixelmpc_jax.apps.experiments import frontier
from pixelmpc_jax.apps.racing.frontier_curve import SAME_LAP_TIME_FIGURES
from pixelmpc_jax.strict_json import json_safe, write_json_atomic

FIGURES = ("score", "feasible", "gain", "lap_time_s", "lap_time_change", "avoidable_s", "vis_below_50_s",
           "share_target_in_view", "mean_target_angle_deg", "laps_completed", "laps", "wall_time_s")


def trial_rows(study) -> list[dict]:
    """One row per trial: its number, state, objective, the figures its objective recorded and its settings."""
    rows = []
    for trial in study.get_trials(deepcopy=False):
        attrs = trial.user_attrs
        rows.append({"number": trial.number, "state": trial.state.name, **{k: attrs.get(k) for k in FIGURES},
                     "score": trial.value, "gain_interval": attrs.get("gain_interval"),
                     "retry_of": trial.system_attrs.get("failed_trial"), "params": dict(trial.params)})
    return rows


def best_trial(study):
    """The completed trial of the highest objective (None before any): a feasible one whenever there is one, as
    every infeasible objective lies below every feasible one."""
    from optuna.trial import TrialState

    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    return max(done, key=lambda t: t.value) if done else None


def nominal_points(nominal: dict, setup) -> list[dict]:
    """The nominal frontier's points (:func:`frontier.build`) from the nominal results."""
    return frontier.build(nominal, setup.nominal_speeds, [], setup.laps, setup.seed, setup.base.max_time_s)["nominal"]


def write_outputs(study, setup, nominal: dict, out: Path, trial=None) -> None:
    """Write ``trials.json``, ``trials.csv`` and ``best.json`` into ``out``; with ``trial`` (a trial just finished),
    print a line about it, else (the search ends or stops) also draw ``tune.png``."""
    from pixelmpc_jax.platform_info import device_description

    out = Path(out)
    rows, best, points = trial_rows(study), best_trial(study), nominal_points(nominal, setup)
    record = {"setup": setup.record(), "nominal": points, "trials": rows,
              "best": None if best is None else best.number,
              "best_feasible": None if best is None else best.user_attrs.get("feasible"),
              "measured": {"device": device_description(), "written": _now(),
                           "trials_wall_time_s": sum(r["wall_time_s"] or 0.0 for r in rows),
                           "nominal_wall_time_s": sum(r.get("wall_time_s") or 0.0 for r in nominal.values())}}
    write_json_atomic(out / "trials.json", json_safe(record))
    _write_csv(rows, out / "trials.csv")
    if best is not None:
        write_json_atomic(out / "best.json", best.user_attrs["race"])
    if trial is None:
        plot(rows, points, setup, best, out / "tune.png")
    elif trial.value is not None:
        from tqdm import tqdm

        a = trial.user_attrs
        tqdm.write(f"trial {trial.number}: objective {trial.value:.3f} ({'feasible' if a['feasible'] else 'infeasible'}"
                   f"; {a['laps_completed']}/{a['laps']} laps, lap {_f(a['lap_time_s'], 1)} s "
                   f"({_percent(a['lap_time_change'])}), avoidable {_f(a['avoidable_s'])} s); best so far: trial "
                   f"{best.number}, {best.value:.3f}")


def summary(study, out: Path) -> str:
    """Lines for the terminal: how many trials finished, the best one and its settings, the files written."""
    best = best_trial(study)
    done = [t for t in study.get_trials(deepcopy=False) if t.state.name == "COMPLETE"]
    if best is None:
        return f"no trial completed yet; the study is in {out}"
    a = best.user_attrs
    settings = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in best.params.items())
    return (f"{len(done)} trial(s) completed, {sum(bool(t.user_attrs.get('feasible')) for t in done)} feasible. Best: "
            f"trial {best.number}, objective {best.value:.3f} ({'feasible' if a['feasible'] else 'INFEASIBLE'}; "
            f"{a['laps_completed']}/{a['laps']} laps, lap {_f(a['lap_time_s'], 1)} s ({_percent(a['lap_time_change'])}"
            f" on nominal), avoidable {_f(a['avoidable_s'])} s): {settings}\n"
            f"wrote {', '.join(str(Path(out) / n) for n in ('best.json', 'trials.json', 'trials.csv', 'tune.png'))}")


def _now() -> str:
    return datetime.datetime.now().isoformat(timespec="seconds")


def _f(value, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _in_view(share) -> str:
    return "-" if share is None else f"{100 * share:.1f}"


def _percent(change) -> str:
    return "-" if change is None else f"{100 * change:+.1f} %"


def _write_csv(rows: list[dict], path: Path) -> None:
    names = sorted({name for row in rows for name in row["params"]})
    columns = ["number", "state", *FIGURES, "gain_low", "gain_high", "retry_of", *names]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        for row in rows:
            low, high = row["gain_interval"] or (None, None)
            writer.writerow({**{k: row[k] for k in ("number", "state", *FIGURES, "retry_of")},
                             "gain_low": low, "gain_high": high, **row["params"]})


def plot(rows: list[dict], points: list[dict], setup, best, path: Path) -> None:
    """Left: the objective of each trial and the best so far. Right: avoidable low-visibility time against lap time
    for every completed trial, the nominal frontier and the lap-time bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if r["state"] == "COMPLETE"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.8))
    for feasible, style, label in ((True, "go", "feasible: the frontier gain"),
                                   (False, "rx", "infeasible: -(lost laps + excess / bound + view shortfall)")):
        picked = [r for r in done if bool(r["feasible"]) == feasible]
        left.plot([r["number"] for r in picked], [r["score"] for r in picked], style, ms=5, label=label)
    running, best_so_far = [], float("-inf")
    for r in done:
        best_so_far = max(best_so_far, r["score"])
        running.append(best_so_far)
    left.step([r["number"] for r in done], running, "k-", where="post", lw=1.2, label="best so far")
    left.axhline(0.0, color="0.6", lw=0.6)
    left.set(xlabel="trial", ylabel="objective", title="the search")
    left.legend(fontsize=7)
    _plot_tradeoff(right, done, points, setup, best)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_tradeoff(ax, done: list[dict], points: list[dict], setup, best) -> None:
    curve = sorted((p["lap_time_s"], p["avoidable_s"], p["speed"]) for p in points
                   if p["lap_time_s"] is not None and p["avoidable_s"] is not None)
    if curve:
        ax.plot([c[0] for c in curve], [c[1] for c in curve], "k-s", ms=5, label="nominal MPPI (flying slower)")
        for lap, avoidable, speed in curve:
            ax.annotate(f"{speed:g} m/s", (lap, avoidable), fontsize=7, xytext=(4, 4), textcoords="offset points")
    at_target = next((p for p in points if p["speed"] == setup.base.speed), None)
    if at_target and at_target["lap_time_s"] is not None:
        ax.axvline((1 + setup.bound) * at_target["lap_time_s"], color="grey", ls=":", lw=1,
                   label=f"lap-time bound (+{100 * setup.bound:g} % on nominal at {setup.base.speed:g} m/s)")
    shown = [r for r in done if r["lap_time_s"] is not None and r["avoidable_s"] is not None]
    for feasible, marker, label in ((True, "o", "trial, feasible (every lap, the bound, the view)"),
                                    (False, "x", "trial, laps lost, over the bound or seeing less")):
        picked = [r for r in shown if bool(r["feasible"]) == feasible]
        ax.scatter([r["lap_time_s"] for r in picked], [r["avoidable_s"] for r in picked], marker=marker, s=22,
                   c="tab:green" if feasible else "tab:red", label=label)
    if best is not None and best.user_attrs.get("lap_time_s") is not None:
        ax.plot(best.user_attrs["lap_time_s"], best.user_attrs["avoidable_s"], "*", color="gold", mec="k", ms=14,
                label=f"best: trial {best.number}")
    ax.set(xlabel="lap time [s]", ylabel="avoidable time with visibility < 50 % [s per lap]",
           title=f"every trial against the nominal frontier (seeds {setup.seed}-{setup.seed + setup.laps - 1})")
    ax.legend(fontsize=7)


def validation_record(built: dict, best, setup, results: dict, course: str | None = None) -> dict:
    """The validation table's record from :func:`frontier.build` over the tuned, preset and nominal-at-target cells
    (in that order) of the held-out ``results`` (flown on ``course``; None: the base race's). Each row holds its
    raw time below 50 %, share of time with the target in view and mean angle to it beside nominal MPPI's at the
    same lap time (``frontier_<figure>``)."""
    at_target = next(p for p in built["nominal"] if p["speed"] == setup.base.speed)
    labels = (f"tuned (trial {best.number})", f"{setup.preset} preset (hand-tuned)",
              f"nominal MPPI at {setup.base.speed:g} m/s")
    rows = []
    for label, row in zip(labels, built["cells"]):
        change = (None if row["lap_time_s"] is None or at_target["lap_time_s"] is None
                  else row["lap_time_s"] / at_target["lap_time_s"] - 1.0)
        rows.append({"label": label, "cell": row["name"], "gain": row["frontier_gain"],
                     "gain_interval": row["frontier_gain_interval"], "laps_completed": row["laps_completed"],
                     "laps": row["laps"], "lap_time_s": row["lap_time_s"], "lap_time_two_sigma_s":
                     row["lap_time_two_sigma_s"], "lap_time_change": change, "avoidable_s": row["avoidable_s"],
                     **{key: row[key] for figure in SAME_LAP_TIME_FIGURES
                        for key in (figure, f"frontier_{figure}")}})
    copied = {name: done["shared_from"] for name, done in results.items() if done.get("shared_from")}
    return json_safe({"rows": rows, "nominal": built["nominal"], "copied": copied, "setup": setup.record(),
                      "course": course if course is None else Path(course).name,
                      "tuned": {"trial": best.number, "training_objective": best.value,
                                "training_feasible": best.user_attrs.get("feasible"), "settings": dict(best.params)},
                      "measured": built["measured"]})


def validation_markdown(record: dict) -> str:
    """The validation table in Markdown, with the tuned settings and how it was measured."""
    m, d = record["measured"], record["measured"]["device"]
    setup = record["setup"]
    course = f", course {record['course']}" if record.get("course") else ""
    lines = [f"# Tuned against hand-tuned: held-out seeds {m['seeds'][0]}-{m['seeds'][1]}{course}", "",
             "Frontier gain: nominal MPPI's avoidable low-visibility time at the row's lap time over the row's (above "
             f"1: better than flying slower), with its {m['gain_interval']}. Lap time change: against nominal MPPI at "
             "the same target. Raw time below 50 % (nothing excused), share of time with the target in view and mean "
             "angle to it: the row's, and nominal MPPI's at the same lap time in brackets. Means over the completed "
             "laps.", "",
             "| controller | frontier gain [90 % interval] | laps completed | lap time [s] | lap time vs nominal "
             "| avoidable [s] | raw < 50 % [s] | in view [%] | angle [deg] |", "|---|---|---|---|---|---|---|---|---|"]
    for row in record["rows"]:
        gain = _f(row["gain"])
        if row["gain_interval"]:
            gain += " [{:.2f}, {:.2f}]".format(*row["gain_interval"])
        lap = "-" if row["lap_time_s"] is None else f"{row['lap_time_s']:.1f} ± {row['lap_time_two_sigma_s']:.1f}"
        raw = f"{_f(row.get('vis_below_50_s'))} ({_f(row.get('frontier_vis_below_50_s'))})"
        in_view = (f"{_in_view(row.get('share_target_in_view'))} "
                   f"({_in_view(row.get('frontier_share_target_in_view'))})")
        angle = f"{_f(row.get('mean_target_angle_deg'), 1)} ({_f(row.get('frontier_mean_target_angle_deg'), 1)})"
        lines.append(f"| {row['label']} | {gain} | {row['laps_completed']}/{row['laps']} | {lap} | "
                     f"{_percent(row['lap_time_change'])} | {_f(row['avoidable_s'])} | {raw} | {in_view} | {angle} |")
    tuned = record["tuned"]
    lines += ["", f"Tuned settings (trial {tuned['trial']}; training objective {tuned['training_objective']:.3f}, "
              f"{'feasible' if tuned['training_feasible'] else 'infeasible'} on seeds {setup['seed']}-"
              f"{setup['seed'] + setup['laps'] - 1}): "
              + ", ".join(f"`{k}` {v:.4g}" if isinstance(v, float) else f"`{k}` {v}"
                          for k, v in tuned["settings"].items())
              + f"; everything else as the `{setup['preset']}` preset.", "",
              "## Nominal frontier on these seeds", "", "| target [m/s] | laps done | lap time [s] | avoidable [s] |",
              "|---|---|---|---|"]
    for p in record["nominal"]:
        lines.append(f"| {p['speed']:g} | {p['laps_completed']}/{p['laps']} | {_f(p['lap_time_s'], 1)} | "
                     f"{_f(p['avoidable_s'])} |")
    lines += ["", "## How it was measured", "",
              f"{m['laps']} laps per row (seeds {m['seeds'][0]}-{m['seeds'][1]}), ground-truth state, on "
              f"{d['platform']} ({d['device_kind']}; CPU {d['cpu_model']}, {d['cpu_count']} cores; jax {d['jax']}), "
              f"written {m['written']}."]
    if record["copied"]:
        lines.append("Cells flown before and copied, not flown again (the same race, seeds and laps): "
                     + ", ".join(f"`{name}` from `{source}`" for name, source in record["copied"].items()) + ".")
    return "\n".join(lines) + "\n"
