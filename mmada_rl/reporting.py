"""Plots and Markdown for run reports (learning curves, evaluation tables)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence


def learning_curve(history: Sequence[Mapping], path: str | Path, *, keys: Sequence[str] = ("train/loss_action", "train/loss_goal")) -> Path:
    """PNG of training losses (and accuracy) against steps from a recipe's ``history.json``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for key in keys:
        values = [h.get(key) for h in history]
        if any(v is not None for v in values):
            axes[0].plot(steps, values, label=key.split("/")[-1])
    axes[0].set(xlabel="step", ylabel="cross-entropy", title="masked-diffusion loss")
    axes[0].legend()
    for key in ("train/action_accuracy", "train/goal_accuracy"):
        values = [h.get(key) for h in history]
        if any(v is not None for v in values):
            axes[1].plot(steps, values, label=key.split("/")[-1])
    axes[1].set(xlabel="step", ylabel="accuracy at masked positions", title="token accuracy", ylim=(0, 1))
    axes[1].legend()
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def metrics_table(metrics: Mapping[str, float], prefix: str = "eval/") -> str:
    rows = [(k[len(prefix):], v) for k, v in metrics.items() if k.startswith(prefix)]
    lines = ["| metric | value |", "|---|---|"]
    lines += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in rows]
    return "\n".join(lines)
