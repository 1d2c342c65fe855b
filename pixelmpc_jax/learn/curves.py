"""The learning curve of `pixelmpc train` (training and held-out loss against the Adam step, as a PNG), and the
axes the multi-step prediction plots of the evaluations share (:func:`finish_multistep_plot`).

Reads the history :func:`pixelmpc_jax.learn.train.train` returns (and ``run_train`` writes as ``history.json``):
``loss_window`` at ``step`` (the mean training loss over each log window), ``probe_loss`` at ``probe_step`` (the
deterministic loss on a fixed seeded batch of training rows), ``test_probe_loss`` at ``probe_step`` when the history
has it (the same loss on a fixed batch of held-out rows), and the final held-out AEE (``test_aee_px``, with
``test_zero_flow_aee_px``) as a note on the figure.
"""

from __future__ import annotations

import numpy as np

CURVES = (  # (history key, the steps it is logged at, label, style)
    ("loss_window", "step", "training loss (mean over the log window)", "C0-"),
    ("probe_loss", "probe_step", "training probe batch (no dropout)", "C0--"),
    ("test_probe_loss", "probe_step", "held-out probe batch (no dropout)", "C1-"),
)


def learning_curves(history: dict) -> dict:
    """``{label: (steps (n,), loss (n,), style)}`` of the curves of :data:`CURVES` the history holds (finite,
    positive values only: a log axis)."""
    curves = {}
    for key, step_key, label, style in CURVES:
        values, steps = history.get(key) or [], history.get(step_key) or []
        if not values or len(values) != len(steps):
            continue
        steps = np.asarray(steps, np.float64)
        values = np.asarray([np.nan if v is None else v for v in values], np.float64)
        keep = np.isfinite(values) & (values > 0)
        if keep.any():
            curves[label] = (steps[keep], values[keep], style)
    return curves


def _aee_note(history: dict) -> str:
    aee, zero = history.get("test_aee_px"), history.get("test_zero_flow_aee_px")
    if aee is None:
        return "no held-out AEE" + (" (interrupted)" if history.get("interrupted") else "")
    return f"held-out AEE {aee:.2f} px/frame" + ("" if zero is None else f" (zero flow {zero:.2f})")


def plot_learning_curve(history: dict, path, title: str = "DOF learning curve") -> None:
    """Training (and, when logged, held-out) loss against the step on a log axis, with the final held-out AEE
    noted, written to ``path`` as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    curves = learning_curves(history)
    for label, (steps, values, style) in curves.items():
        ax.semilogy(steps, values, style, lw=1.2, label=label)
    if not curves:
        ax.text(0.5, 0.5, "no losses logged", transform=ax.transAxes, ha="center")
    ax.text(0.99, 0.97, _aee_note(history), transform=ax.transAxes, ha="right", va="top", fontsize=8)
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss")
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
