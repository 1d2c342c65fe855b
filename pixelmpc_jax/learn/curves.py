"""The learning curve of `pixelmpc train` (training and held-out loss against the Adam step, as a PNG), and the
axes the multi-step prediction plots of the evaluations share (:func:`finish_multistep_plot`).

Reads the history :func:`pixelmpc_jax.learn.train.train` returns (and ``run_train`` writes as ``history.json``), the
same for every model: ``loss_window`` at ``step`` (the mean training loss over each log window), ``probe_loss`` at
``probe_step`` (the deterministic loss on fixed training rows: the DOF's seeded probe batch, vdof's every row) and
``test_probe_loss`` at ``probe_step`` when the history has it (the same loss on held-out rows). A model trained in
several stages (vdof: one-step, then rollout; ``stage`` and ``probe_stage`` say which) gets one curve per stage and
a line where each later stage begins: each stage's loss is its own.
"""

from __future__ import annotations

import numpy as np

CURVES = (  # (history key, the steps it is logged at, their stages, label, style)
    ("loss_window", "step", "stage", "training loss (mean over the log window)", "C0-"),
    ("probe_loss", "probe_step", "probe_stage", "training probe (no dropout)", "C0--"),
    ("test_probe_loss", "probe_step", "probe_stage", "held-out probe (no dropout)", "C1-"),
)


def learning_curves(history: dict) -> dict:
    """``{label: (steps (n,), loss (n,), style)}`` of the curves of :data:`CURVES` the history holds (finite,
    positive values only: a log axis), one per stage (its name after the label) when there are several."""
    curves = {}
    several = len(set(history.get("stage") or [])) > 1
    for key, step_key, stage_key, label, style in CURVES:
        values, steps = history.get(key) or [], history.get(step_key) or []
        if not values or len(values) != len(steps):
            continue
        stages = history.get(stage_key) or [None] * len(steps)
        steps = np.asarray(steps, np.float64)
        values = np.asarray([np.nan if v is None else v for v in values], np.float64)
        for stage in dict.fromkeys(stages):
            keep = np.isfinite(values) & (values > 0) & (np.asarray(stages, object) == stage)
            if keep.any():
                curves[f"{label}, {stage}" if several else label] = (steps[keep], values[keep], style)
    return curves


def stage_starts(history: dict) -> list[tuple[float, str]]:
    """``(step, name)`` of every stage after the first: where its curves begin."""
    stages, steps = history.get("probe_stage") or [], history.get("probe_step") or []
    return [(float(steps[i]), stage) for i, stage in enumerate(stages) if i > 0 and stage != stages[i - 1]]


def plot_learning_curve(history: dict, path, title: str = "learning curve", note: str = "") -> None:
    """Training (and, when logged, held-out) loss against the step on a log axis, stage by stage, with ``note``
    (the held-out figures; a line per "; ") in a corner, written to ``path`` as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    curves = learning_curves(history)
    for label, (steps, values, style) in curves.items():
        ax.semilogy(steps, values, style, lw=1.2, label=label)
    for step, stage in stage_starts(history):
        ax.axvline(step, color="0.5", lw=0.8, ls=":")
        ax.text(step, 0.02, f" {stage}", transform=ax.get_xaxis_transform(), fontsize=7, color="0.4")
    if not curves:
        ax.text(0.5, 0.5, "no losses logged", transform=ax.transAxes, ha="center")
    ax.text(0.99, 0.97, note.replace("; ", "\n"), transform=ax.transAxes, ha="right", va="top", fontsize=7)
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss (each stage's own)" if stage_starts(history) else "loss")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if curves:
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def finish_multistep_plot(fig, ax, dt_s: float, title: str, path) -> None:
    """Label, grid and save a multi-step gate-centre error plot (error in px against the prediction step)."""
    import matplotlib.pyplot as plt

    ax.set(xlabel=f"prediction step (dt = {dt_s:g} s)", ylabel="gate-centre error [px]",
           title=title or "multi-step pixel prediction error")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
