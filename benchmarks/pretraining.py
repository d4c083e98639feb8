"""Pretraining results: evaluations and learning curves of `recipes/pretrain` runs, side by side.

    # the runs (each a recipes/pretrain/pretrain.py run directory), then the report
    python recipes/pretrain/pretrain.py --config-name maniskill env.task=PushCube-v1 run_dir=runs/push_bins_s0
    python recipes/pretrain/pretrain.py --config-name maniskill env.task=PickCube-v1 run_dir=runs/pick_bins_s0
    python recipes/pretrain/pretrain.py --config-name maniskill env.task=PushCube-v1 run_dir=runs/push_vq_s0 \\
        tokenizers.action_type=vq optim.total_steps=4000
    python recipes/pretrain/pretrain.py --config-name maniskill env.task=PushCube-v1 run_dir=runs/push_bins_nogoal_s0 \\
        model.predict_goal=false tokenizers.dir=runs/push_bins_s0/tokenizers
    python benchmarks/pretraining.py runs/push_bins_s0 runs/pick_bins_s0 runs/push_vq_s0 runs/push_bins_nogoal_s0

For every run: its task, action tokenizer, whether it predicts the goal image, steps trained, every evaluation
(``success_once`` with its 95% Wilson interval on the fixed evaluation seeds) and
the action-token accuracy at masked positions along training (TorchRL CSV logs).
Writes ``benchmarks/results/pretraining.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402

from mmada_rl.data import window_skips  # noqa: E402


def read_scalar(run: Path, name: str) -> list[tuple[int, float]]:
    path = run / "logs" / "scalars" / f"{name}.csv"
    if not path.exists():
        return []
    with path.open() as f:
        return [(int(float(step)), float(value)) for step, value in csv.reader(f)]


def read_evaluations(run: Path, prefix: str = "eval") -> list[dict]:
    """Every evaluation logged under ``prefix`` (``eval`` or ``eval/<task>`` for a multi-task run), by step;
    the shares of episodes that reached the task's progress flags as ``reached/<flag>``."""
    evals = {step: {"success_once": v} for step, v in read_scalar(run, f"{prefix}/success_once")}
    reached = sorted(f"reached/{p.stem}" for p in (run / "logs" / "scalars" / prefix / "reached").glob("*.csv"))
    for key in ("success_once_ci_low", "success_once_ci_high", "episodes", "success_at_end", "decode_ms_mean", *reached):
        for step, v in read_scalar(run, f"{prefix}/{key}"):
            evals.setdefault(step, {})[key] = v
    return [{"step": s, **e} for s, e in sorted(evals.items())]


def summarize(run: Path) -> dict:
    ckpts = sorted((run / "checkpoints").glob("step_*")) if (run / "checkpoints").exists() else []
    if not ckpts:
        raise FileNotFoundError(f"{run} holds no checkpoints: not a pretraining run directory.")
    config = json.loads((ckpts[-1] / "config.json").read_text())
    tasks = config.get("tasks") or [config["env"]["task"]]
    return {
        "run": str(run),
        "task": "+".join(tasks),
        "tasks": tasks,
        "action_tokenizer": config["tokenizers"]["action_type"],
        "denoiser": config["model"]["denoiser"],
        "predict_goal": bool(config["model"].get("predict_goal", True)),
        "chunk_size": int(config["model"]["chunk_size"]),
        "execute_steps": int(config["eval"]["execute_steps"]),
        **window_skips(config.get("data", {})),
        "visual_encoder_channels": (config["model"].get("denoiser_overrides") or {}).get("visual_encoder_channels"),
        # from the run's own image tokenizer (it may come from tokenizers.dir, not this run's config)
        "image_foreground_weight": float(json.loads((ckpts[-1] / "model" / "tokenizers" / "image" / "config.json").read_text())
                                         ["config"].get("foreground_weight", 1.0)),
        "steps": int(ckpts[-1].name.split("_")[-1]),
        "planned_steps": config["optim"]["total_steps"],
        # a single-task run logs eval/...; a multi-task run also logs eval/<task>/... (eval/... is their mean)
        "evaluations": read_evaluations(run),
        "per_task": {t: read_evaluations(run, f"eval/{t}") for t in tasks} if len(tasks) > 1 else {},
        "action_accuracy": read_scalar(run, "train/action_accuracy"),
    }


def format_evaluations(evaluations: list[dict]) -> str:
    return "; ".join(
        f"step {e['step']}: {e['success_once']:.2f} [{e.get('success_once_ci_low', float('nan')):.2f}, "
        f"{e.get('success_once_ci_high', float('nan')):.2f}] ({int(e.get('episodes', 0))} ep)"
        for e in evaluations) or "not evaluated"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    runs = [summarize(r) for r in args.runs]

    rows = []
    for r in runs:
        acc = r["action_accuracy"]
        last_acc = sum(v for _, v in acc[-10:]) / max(1, len(acc[-10:]))
        common = [r["action_tokenizer"], "yes" if r["predict_goal"] else "no", f"{r['chunk_size']} / {r['execute_steps']}",
                  r["denoiser"], f"{r['steps']} / {r['planned_steps']}", f"{last_acc:.2f}"]
        options = ((" (no window in the leading hold)" if r["skip_idle_start"] else "")
                   + (f" (no window starting in a pause, {r['skip_pauses']:g})" if r["skip_pauses"] else "")
                   + (f" (no window starting in the hold after a grasp, {r['skip_grasp_hold']:g})"
                      if r["skip_grasp_hold"] else "")
                   + (f" (image foreground weight {r['image_foreground_weight']:g})" if r["image_foreground_weight"] != 1 else "")
                   + (f" (cross-attention to CNN features {r['visual_encoder_channels']})" if r["visual_encoder_channels"] else ""))
        if r["per_task"]:
            rows += [[f"{task} (multi-task, {len(r['tasks'])} tasks){options}", *common, format_evaluations(evals)]
                     for task, evals in r["per_task"].items()]
        else:
            rows.append([r["task"] + options, *common, format_evaluations(r["evaluations"])])
    header = ["task", "action tokens", "goal prediction", "K / executed", "denoiser", "steps (trained / planned)",
              "action-token accuracy (last 10 logs)", "success_once [95% CI]"]
    table = markdown_table(header, rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    planned = [r["planned_steps"] for r in runs]
    usual = max(set(planned), key=planned.count)  # schedules of another length are named in the legend
    for r in runs:
        name = r["task"] if len(r["tasks"]) == 1 else "multi-task"
        ablated = (("" if r["predict_goal"] else ", no goal") + ("" if r["chunk_size"] == 5 else f", K={r['chunk_size']}")
                   + (", skip idle start" if r["skip_idle_start"] else "")
                   + (f", skip pauses {r['skip_pauses']:g}" if r["skip_pauses"] else "")
                   + (f", skip grasp hold {r['skip_grasp_hold']:g}" if r["skip_grasp_hold"] else "")
                   + (f", {r['planned_steps']} steps" if r["planned_steps"] != usual else "")
                   + (f", image fg x{r['image_foreground_weight']:g}" if r["image_foreground_weight"] != 1 else "")
                   + (", CNN cross-attention" if r["visual_encoder_channels"] else ""))
        label = f"{name} {r['action_tokenizer']}{ablated}"
        if r["action_accuracy"]:
            steps, values = zip(*r["action_accuracy"])
            ax[0].plot(steps, values, label=label, alpha=0.8)
        if r["evaluations"]:
            ax[1].plot([e["step"] for e in r["evaluations"]], [e["success_once"] for e in r["evaluations"]], marker="o", label=label)
    ax[0].set_xlabel("pretraining step")
    ax[0].set_ylabel("action-token accuracy (masked)")
    ax[1].set_xlabel("pretraining step")
    ax[1].set_ylabel("success_once")
    ax[1].set_ylim(-0.02, 1.02)
    for a in ax:
        a.legend(fontsize=7)
    save_figure(fig, args.out / "pretraining.png")
    write_results("pretraining", {"runs": runs}, f"# Pretraining results\n\n{table}\n\n![curves](pretraining.png)\n",
                  directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
