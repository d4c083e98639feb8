"""Fine-tuning iterations with collection overlapped with the updates (``collector.overlap=thread`` or
``process``) against the sequential loop, side by side on the same machine.

    python benchmarks/finetune_overlap.py --pretrained runs/pick100_cells4_w256_s0 \\
        --demos data/dart/PickCube-v1-fov45 --threads 1 2

A fine-tuning iteration collects a batch (the simulator's worker process and the actor's decoding), then trains on
it; each phase keeps about one core busy. With ``collector.overlap=thread`` the next batch is collected in a
background thread while the updates run (:class:`~mmada_rl.training.CollectAhead`), with ``process`` in a process
of its own (:class:`~mmada_rl.training.CollectAheadProcess`). This runs the fine-tuning
recipe exactly as ``benchmarks/compare/compare.py`` runs ``--method`` (default: the recipe's method), without
evaluation, for ``--iterations`` iterations per run: every combination of ``--modes`` (``collector.overlap``) and
``--threads`` (the recipe's ``num_threads``), one run of each per round, their order reversed every other round,
``--rounds`` rounds. Each run's iteration time is the median of its ``time/iteration_s`` log (from the collection,
or the wait for it, to the last update) after its first ``--skip`` iterations (start-up; the overlapped loop's
first batch has nothing to overlap with). Ratios are to the first ``--modes`` value (the sequential loop by default)
at the first ``--threads`` value, per round, then the median over rounds. Nothing else should run on the machine meanwhile: the gain is the idle core.
With ``--collect-beside`` the sequential loop is also timed while a collection-only run of the same method
(``optim.updates_per_batch=0``) goes on in another process: how much a collector in a process of its own (no shared
interpreter lock) would slow the updates.

The per-iteration cost does not depend on what the policy has learned (a fixed number of decisions per iteration
and updates per batch), so a briefly trained policy of the right size times as well as a finished one.

Writes ``benchmarks/results/<name>.{json,md,png}`` (default ``finetune_overlap``).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "benchmarks" / "compare"))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402
from compare import METHODS, command  # noqa: E402
from pretraining import read_scalar  # noqa: E402

DEFAULT_METHOD = "mmada_return_to_go_noise_keep_lr1e4_gripper_ema"
TIMES = ("iteration_s", "collect_s", "collect_ahead_s", "update_s")
MODES = {"false": "sequential", "thread": "overlapped", "process": "overlapped in a process"}  # collector.overlap


def recipe_command(args, budget: int, run_dir: Path, overrides: list[str]) -> list[str]:
    cmd = command(args.method, args.task, args.seed, budget, run_dir, args.pretrained, eval_episodes=0,
                  eval_every=0, demos=args.demos)
    return [*cmd, "demos.collect_episodes=0", *args.override, *overrides]  # the benchmark's own settings last


def run_once(args, overlap: str, threads: int, run_dir: Path, beside: bool = False) -> dict:
    """One fine-tuning run of ``args.iterations`` iterations; the medians of its per-iteration times. With
    ``beside``, a collection-only run of the same method (``optim.updates_per_batch=0``) goes on in another
    process meanwhile: the load a collector in its own process would add."""
    budget = args.iterations * args.steps_per_iteration
    cmd = recipe_command(args, budget, run_dir, [f"num_threads={threads}", f"collector.overlap={overlap}",
                                                 f"checkpoint.interval={args.iterations + 1}"])
    collector = None
    if beside:
        collector = subprocess.Popen(
            recipe_command(args, 10**9, run_dir.with_name(run_dir.name + "_collector"),
                           ["num_threads=1", "optim.updates_per_batch=0", "checkpoint.interval=1000000"]),
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    finally:
        if collector is not None:  # the recipe and its env workers
            os.killpg(collector.pid, signal.SIGTERM)
            collector.wait()
    if proc.returncode != 0:
        raise SystemExit(f"the fine-tuning run failed ({' '.join(cmd)}):\n{proc.stderr[-3000:]}")
    series = {name: read_scalar(run_dir, f"time/{name}") for name in TIMES}
    logged = {name: [v for _, v in rows][args.skip:] for name, rows in series.items()}
    steps = [s for s, _ in series["iteration_s"]]
    if not logged["iteration_s"]:
        raise SystemExit(f"{run_dir}: {len(steps)} iterations logged, none left after --skip {args.skip}; "
                         "raise --iterations.")
    per_step = (steps[-1] - steps[args.skip - 1]) / len(logged["iteration_s"]) if args.skip else steps[-1] / len(steps)
    return {"overlap": overlap, "threads": threads, "beside": beside, "iterations": len(logged["iteration_s"]),
            "env_steps_per_iteration": per_step,
            **{f"median_{name}": statistics.median(v) if v else None for name, v in logged.items()}}


def plot(rows: list[dict], path: Path) -> Path:
    """Each configuration's median iteration: the wait for the batch, the updates, the rest (advantages, logging)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.9))
    labels = [row["label"] for row in rows]
    wait = [row["median_collect_s"] for row in rows]
    update = [row["median_update_s"] for row in rows]
    rest = [max(0.0, row["median_iteration_s"] - w - u) for row, w, u in zip(rows, wait, update)]
    ax.barh(labels, wait, color="tab:orange", label="collection (or the wait for it)")
    ax.barh(labels, update, left=wait, color="tab:blue", label="updates")
    ax.barh(labels, rest, left=[w + u for w, u in zip(wait, update)], color="tab:gray", label="the rest")
    for i, row in enumerate(rows):
        ax.text(row["median_iteration_s"], i, f" {row['median_iteration_s']:.1f} s", va="center")
    ax.invert_yaxis()
    ax.set_xlabel("seconds per fine-tuning iteration (median over rounds)")
    ax.set_xlim(0, max(row["median_iteration_s"] for row in rows) * 1.2)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, fontsize=8, frameon=False)
    ax.set_title("collector.overlap: collection beside the updates", fontsize=10)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pretrained", required=True, help="pretraining run, checkpoint or model directory")
    parser.add_argument("--demos", required=True, help="the RGB demonstration buffer the method mixes in")
    parser.add_argument("--task", default="PickCube-v1", help="ManiSkill task (default: PickCube-v1)")
    parser.add_argument("--method", default=DEFAULT_METHOD, choices=sorted(m for m in METHODS if m.startswith("mmada")),
                        metavar="METHOD", help=f"a fine-tuning method of compare.py (default: {DEFAULT_METHOD})")
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="num_threads values to run (default: 1)")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES,
                        help="collector.overlap values to run; the first is the ratios' baseline "
                             "(default: false thread process)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of one run per configuration (default: 3)")
    parser.add_argument("--iterations", type=int, default=8, help="fine-tuning iterations per run (default: 8)")
    parser.add_argument("--skip", type=int, default=2, help="first iterations of each run not timed (default: 2)")
    parser.add_argument("--steps-per-iteration", type=int, default=200,
                        help="env steps per iteration (default: 200, the recipe's 40 decisions of 5 steps)")
    parser.add_argument("--collect-beside", action="store_true",
                        help="also time the sequential loop at each --threads value with a collection-only run of the "
                             "method in another process meanwhile (what a collector process would cost the updates)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                        help="an extra recipe override for every run (repeatable)")
    parser.add_argument("--name", default="finetune_overlap", help="results file stem (default: finetune_overlap)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.iterations <= args.skip or args.skip < 0 or min(args.threads) < 1:
        parser.error("need --rounds >= 1, 0 <= --skip < --iterations and --threads >= 1.")

    configs = [(overlap, threads, beside) for threads in args.threads
               for overlap, beside in (*((m, False) for m in args.modes),
                                       *((("false", True),) if args.collect_beside else ()))]
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="finetune_overlap_") as tmp:
        for r in range(args.rounds):
            for overlap, threads, beside in (configs if r % 2 == 0 else configs[::-1]):
                run = run_once(args, overlap, threads, Path(tmp) / f"r{r}_o{overlap}_t{threads}_b{int(beside)}",
                               beside)
                runs.append({"round": r, **run})
                print(f"round {r}: overlap={overlap} threads={threads} beside={beside}: "
                      f"{run['median_iteration_s']:.2f} s per iteration (updates {run['median_update_s']:.2f} s, "
                      f"waited {run['median_collect_s']:.2f} s)", flush=True)

    def same(run: dict, config: tuple) -> bool:
        return (run["overlap"], run["threads"], run["beside"]) == config

    rows = []
    for overlap, threads, beside in configs:
        mine = [x for x in runs if same(x, (overlap, threads, beside))]
        ratios = [m["median_iteration_s"] / b["median_iteration_s"] for m, b in
                  zip(mine, [x for x in runs if same(x, configs[0])])]
        label = f"{MODES[overlap]}, {threads} thread{'s' if threads > 1 else ''}"
        row = {"label": label + (", beside a collection-only process" if beside else ""),
               "overlap": overlap, "threads": threads, "beside": beside, "ratio_to_first": statistics.median(ratios)}
        for key in (f"median_{name}" for name in TIMES):
            values = [m[key] for m in mine if m[key] is not None]
            row[key] = statistics.median(values) if values else None
        row["env_steps_per_s"] = statistics.median(m["env_steps_per_iteration"] for m in mine) / row["median_iteration_s"]
        rows.append(row)

    fmt = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    table = markdown_table(
        ["configuration", "iteration (s)", "waited for the batch (s)", "collection itself (s)", "updates (s)",
         "env steps/s", "iteration time / first row's"],
        [[r["label"], fmt(r["median_iteration_s"]), fmt(r["median_collect_s"]), fmt(r["median_collect_ahead_s"]),
          fmt(r["median_update_s"]), f"{r['env_steps_per_s']:.1f}", f"{r['ratio_to_first']:.2f}x"] for r in rows])
    markdown = (f"# Fine-tuning with collection beside the updates ({args.task}, {args.method})\n\n"
                f"Medians over {args.rounds} rounds of each run's median iteration ({args.iterations} iterations, "
                f"the first {args.skip} not timed); the ratio is per round, then the median.\n\n{table}\n\n"
                "![iteration time](" + f"{args.name}.png)\n")
    write_results(args.name, {"task": args.task, "method": args.method, "pretrained": str(args.pretrained),
                              "demos": str(args.demos), "rounds": args.rounds, "iterations": args.iterations,
                              "skip": args.skip, "results": rows, "runs": runs}, markdown, args.out)
    plot(rows, args.out / f"{args.name}.png")
    print(json.dumps([{k: r[k] for k in ("label", "median_iteration_s", "ratio_to_first")} for r in rows], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
