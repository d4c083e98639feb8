"""``mmada-rl quickstart``: demonstrations → tokenizers → pretraining → evaluation → report.

Runs the pretraining recipe of this source checkout (``recipes/pretrain``) with
its ``quickstart`` config (``--full``: ``maniskill``), then evaluates the final
checkpoint on fixed evaluation seeds and writes ``report.md`` with a learning
curve and a grid of predicted goal images beside the real frames. Every stage
resumes: re-running the command after an interruption continues where it stopped.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "pretrain" / "pretrain.py"


def _train(args: argparse.Namespace, run_dir: Path, demos: Path) -> None:
    from mmada_rl.training import latest_checkpoint

    if (run_dir / "final.json").exists():
        print(f"[quickstart] pretraining already finished in {run_dir}")
        return
    if not RECIPE.exists():
        raise FileNotFoundError(f"{RECIPE} not found: the quickstart runs the recipes of a source checkout of mmada_rl.")
    overrides = [f"run_dir={run_dir}", f"data.dir={demos}", f"env.task={args.task}", "eval.episodes=0"]
    if not args.full:
        overrides.append(f"data.collect_episodes={args.episodes}")
    if args.steps:
        overrides.append(f"optim.total_steps={args.steps}")
    if latest_checkpoint(run_dir) is not None:
        overrides.append("checkpoint.resume=true")
    cmd = [sys.executable, str(RECIPE), "--config-name", "maniskill" if args.full else "quickstart", *overrides]
    print("[quickstart] " + " ".join(cmd[1:]))
    subprocess.run(cmd, check=True)


def _report(out: Path, run_dir: Path, demos: Path, result, seconds: float, args: argparse.Namespace) -> Path:
    from mmada_rl.data import DemoBuffer
    from mmada_rl.reporting import learning_curve, metrics_table

    history = json.loads((run_dir / "history.json").read_text())
    curve = learning_curve(history, out / "learning_curve.png")
    buf = DemoBuffer.open(demos)
    metrics = result.to_dict()
    lines = [
        f"# mmada_rl quickstart: {args.task}",
        "",
        f"* demonstrations: {buf.metadata.num_episodes} motion-planner episodes, {len(buf)} transitions "
        f"({buf.metadata.control_mode}, {buf.metadata.image_size}×{buf.metadata.image_size} RGB + proprio + instruction)",
        f"* pretraining: {history[-1]['step'] if history else 0} steps, final action-token accuracy "
        f"{history[-1].get('train/action_accuracy', float('nan')):.3f} at masked positions" if history else "* pretraining: no steps logged",
        f"* wall-clock time of this run: {seconds / 60:.1f} min",
        "",
        f"## Evaluation ({int(metrics.get('eval/episodes', 0))} episodes on fixed evaluation seeds, greedy decoding)",
        "",
        metrics_table(metrics),
        "",
        f"![learning curve]({curve.name})",
    ]
    grid = out / "eval" / "goal_grid.png"
    if grid.exists():
        lines += ["", "Predicted goal images (decoded from the sampled goal tokens) beside the real frames K steps later:", "",
                  "![goal images](eval/goal_grid.png)"]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def run(args: argparse.Namespace) -> int:
    import torch

    from mmada_rl.evaluation import evaluate
    from mmada_rl.training import latest_checkpoint

    torch.set_num_threads(1)  # more torch threads contend with the simulator on 2 cores
    start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    demos, run_dir = out / "demos", out / "pretrain"
    if args.full:
        demos = Path("data") / args.task
    _train(args, run_dir, demos)
    ckpt = latest_checkpoint(run_dir)
    print(f"[quickstart] evaluating {ckpt} on {args.eval_episodes} episodes")
    result = evaluate(ckpt, args.task, episodes=args.eval_episodes, out_dir=out / "eval", goal_grid=True)
    print(result.table())
    report = _report(out, run_dir, demos, result, time.perf_counter() - start, args)
    print(f"[quickstart] report: {report}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "quickstart",
        help="the README's main job: demos -> tokenizers -> pretraining -> evaluation -> report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--task", default="PickCube-v1", help="ManiSkill3 task (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=20, help="planner demonstrations to collect (default: %(default)s)")
    p.add_argument("--steps", type=int, default=None, help="pretraining steps (default: the config's, 800 for the quickstart)")
    p.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes (default: %(default)s)")
    p.add_argument("--out", default="runs/quickstart", help="output directory (default: %(default)s)")
    p.add_argument("--full", action="store_true", help="the full-length run: 100 demos in data/TASK, maniskill.yaml (hours on 2 cores)")
    p.set_defaults(func=run)
