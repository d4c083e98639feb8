"""``mmada-rl quickstart``: demonstrations → tokenizers → pretraining → evaluation → report.

Runs the pretraining recipe of this source checkout (``recipes/pretrain``) with
the task's CPU config (``pickcube_cpu`` for PickCube-v1, ``pushcube_cpu`` for
PushCube-v1): 100 DART demonstrations (collected into the config's ``data.dir``
when missing, shared with the recipe's own runs), tokenizers fitted on them and
the denoiser pretrained, shortened by default (the config's width halved for
PickCube-v1, fewer steps) so that it fits in about half an hour on 2 CPU cores;
``--full`` runs the config as it is, the recipe of the README's figures. Then it
evaluates the final checkpoint on fixed evaluation seeds and writes ``report.md``
with a learning curve and a grid of predicted goal images beside the real
frames. Every stage resumes: re-running the command after an interruption
continues where it stopped.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "pretrain" / "pretrain.py"
#: each task's config in recipes/pretrain/config, and of the same name in recipes/finetune/config
CONFIGS = {"PickCube-v1": "pickcube_cpu", "PushCube-v1": "pushcube_cpu"}
#: what each task's fine-tuning config has measured (docs/results/finetuning.md), for the report's next step:
#: by (task, --full); PickCube-v1's from the quickstart's own policies (one seed each, 150 evaluation episodes)
FINETUNE_RESULTS = {
    ("PickCube-v1", False): "measured from the quickstart's default run (one seed): 0.16 -> 0.47 over 150 evaluation episodes, "
                            "most of it from the demonstrations' updates: 0.40 without RL (demos.ratio=1.0); "
                            "from d_model = 128 policies pretrained 5000 steps 0.54 -> 0.74 over three seeds",
    ("PickCube-v1", True): "measured from the quickstart's --full run (one seed): 0.79 -> 0.75 over 150 evaluation episodes, no lift, "
                           "and 0.75 without RL (demos.ratio=1.0) too; from three d_model = 256 seeds 0.70 -> 0.78",
    **{("PushCube-v1", full): "0.93 -> 0.90 from the full config's policies: it holds their level, lifting nothing"
       for full in (False, True)},  # measured from the full config's policies only: one line for both runs
}
SHORT_STEPS = 3000  # pretraining steps of the default (not --full) run
#: the default run's changes to each config: PickCube-v1 at d_model = 128, a training step 0.37x the time of d = 256's
#: (benchmarks/results/train_throughput_bf16.md)
SHORT_OVERRIDES = {"PickCube-v1": ["model.denoiser_overrides.d_model=128"]}


def recipe_overrides(args: argparse.Namespace, run_dir: Path) -> list[str]:
    """The pretraining recipe's command-line overrides for this quickstart."""
    overrides = [f"run_dir={run_dir}", "eval.episodes=0"]  # evaluated after training, with the goal-image grid
    if args.demos:
        overrides.append(f"data.dir={args.demos}")
    if args.episodes is not None:
        overrides.append(f"data.collect_episodes={args.episodes}")
    if not args.full:
        overrides += SHORT_OVERRIDES.get(args.task, [])
    steps = args.steps or (None if args.full else SHORT_STEPS)
    if steps:
        overrides.append(f"optim.total_steps={steps}")
    return overrides


def _train(args: argparse.Namespace, run_dir: Path) -> None:
    from mmada_rl.training import latest_checkpoint

    if (run_dir / "final.json").exists():
        print(f"[quickstart] pretraining already finished in {run_dir}")
        return
    if not RECIPE.exists():
        raise FileNotFoundError(f"{RECIPE} not found: the quickstart runs the recipes of a source checkout of mmada_rl.")
    overrides = recipe_overrides(args, run_dir)
    if latest_checkpoint(run_dir) is not None:
        overrides.append("checkpoint.resume=true")
    cmd = [sys.executable, str(RECIPE), "--config-name", CONFIGS[args.task], *overrides]
    print("[quickstart] " + " ".join(cmd[1:]))
    subprocess.run(cmd, check=True)


def _report(out: Path, run_dir: Path, demos: Path, result, seconds: float, args: argparse.Namespace) -> Path:
    from mmada_rl.data import DemoBuffer
    from mmada_rl.reporting import learning_curve, metrics_table

    history = json.loads((run_dir / "history.json").read_text())
    curve = learning_curve(history, out / "learning_curve.png")
    buf = DemoBuffer.open(demos)
    dart = f"executed with DART action noise {buf.metadata.action_noise:g}, " if buf.metadata.action_noise else ""
    metrics = result.to_dict()
    lines = [
        f"# mmada_rl quickstart: {args.task}",
        "",
        f"* demonstrations: {buf.metadata.num_episodes} motion-planner episodes in {demos}, {len(buf)} transitions "
        f"({dart}{buf.metadata.control_mode}, {buf.metadata.image_size}×{buf.metadata.image_size} RGB through a "
        f"{buf.metadata.camera_fov or 90:g}° camera + proprio + instruction)",
        f"* pretraining command: `recipes/pretrain/pretrain.py --config-name {CONFIGS[args.task]} {' '.join(recipe_overrides(args, run_dir))}`",
        f"* pretraining: {history[-1]['step'] if history else 0} steps, final action-token accuracy "
        f"{history[-1].get('train/action_accuracy', float('nan')):.3f} at masked positions" if history else "* pretraining: no steps logged",
        f"* wall-clock time of this run: {seconds / 60:.1f} min",
        "",
        f"## Evaluation ({int(metrics.get('eval/episodes', 0))} episodes on fixed evaluation seeds, greedy decoding)",
        "",
        f"Reproduce: `mmada-rl eval --checkpoint {run_dir} --task {args.task} --episodes {args.eval_episodes}`",
        "",
        metrics_table(metrics),
        "",
        f"![learning curve]({curve.name})",
    ]
    lines += ["", f"Next, online fine-tuning of this policy (the README's recipe; {FINETUNE_RESULTS[args.task, args.full]}; "
              "70-95 minutes for 50k env steps on 2 cores):", "",
              f"`python recipes/finetune/finetune.py --config-name {CONFIGS[args.task]} pretrained={run_dir} "
              f"demos.dir={demos} run_dir={out / 'finetune'}`"]
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
    from mmada_rl.training.checkpoint import CONFIG_FILE

    if args.episodes is not None and args.episodes < 1:
        raise SystemExit(f"mmada-rl quickstart: --episodes must be positive, got {args.episodes}.")
    torch.set_num_threads(1)  # more torch threads contend with the simulator on 2 cores
    start = time.perf_counter()
    out = Path(args.out or ("runs/quickstart_full" if args.full else "runs/quickstart"))
    out.mkdir(parents=True, exist_ok=True)
    run_dir = out / "pretrain"
    _train(args, run_dir)
    ckpt = latest_checkpoint(run_dir)
    demos = Path(json.loads((ckpt / CONFIG_FILE).read_text())["data"]["dir"])  # the buffer the run trained on
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
    p.add_argument("--task", default="PickCube-v1", choices=sorted(CONFIGS),
                   help="ManiSkill3 task; its config: " + ", ".join(f"{t}: {c}.yaml" for t, c in CONFIGS.items())
                   + " (default: %(default)s; another task: recipes/pretrain/pretrain.py --config-name maniskill_cpu "
                   "env.task=TASK)")
    p.add_argument("--demos", default=None,
                   help="demonstration buffer directory (default: the config's data.dir, e.g. data/dart/PickCube-v1-fov45; "
                        "collected there when missing and shared with the recipe's runs)")
    p.add_argument("--episodes", type=int, default=None, help="DART planner demonstrations to collect (default: the config's, 100)")
    p.add_argument("--steps", type=int, default=None,
                   help=f"pretraining steps (default: {SHORT_STEPS}, with --full the config's 5000)")
    p.add_argument("--eval-episodes", type=int, default=50, help="evaluation episodes (default: %(default)s)")
    p.add_argument("--out", default=None, help="output directory (default: runs/quickstart, with --full runs/quickstart_full)")
    p.add_argument("--full", action="store_true",
                   help="the config as it is, the recipe of the README's figures (PickCube-v1: d_model = 256, "
                        "about 90 minutes of pretraining on 2 cores)")
    p.set_defaults(func=run)
