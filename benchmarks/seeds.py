"""Training-seed spread: the same configuration trained with different seeds, evaluated on the same episodes.

    # three pretraining seeds of the PushCube-v1 policy, each evaluated on the same 50 evaluation seeds
    python recipes/pretrain/pretrain.py --config-name maniskill env.task=PushCube-v1 run_dir=runs/push_bins_s1 seed=1 \\
        eval.interval=2000 eval.episodes=50
    mmada-rl eval --checkpoint runs/push_bins_s0 --task PushCube-v1 --episodes 50 --out runs/evals/push_bins_s0_50ep
    python benchmarks/seeds.py --group "PushCube-v1, small denoiser, 256 bins, 2000 steps" \\
        runs/evals/push_bins_s0_50ep/eval.json runs/push_bins_s1 runs/push_bins_s2 --name seeds_PushCube-v1

A source is either an ``eval.json`` written by ``mmada-rl eval`` or a training run directory
(``recipes/pretrain``, ``recipes/baselines/imitation.py``: its last logged evaluation, or the one
logged at step S with ``RUN@S``, e.g. ``runs/push300_pdrop_s0@5000``). ``RUN@raw`` (or ``RUN@S@raw``)
reads the evaluation of the optimizer's own weights that a pretraining run with ``ema.enabled=true
ema.evaluate_raw=true`` logs beside its weight average's (``eval_raw/...``; ``RUN`` alone: the average).
A fine-tuning run (``recipes/finetune``, e.g. one of ``benchmarks/compare``'s) is read from its
``eval_history.json``: its last evaluation, or with ``RUN@S`` the one at ``S`` online env steps.
``REPORT.json#G/sS`` takes seed ``S`` of group ``G`` (counted from 1) of an earlier report written by
this script, e.g. ``benchmarks/results/seeds_X.json#1/s0``: seeds whose runs are no longer on the
machine are pooled with new ones from the figures their report recorded.
For every group: each seed's ``success_once`` with its 95% Wilson interval, the mean and
standard deviation over seeds, and the episodes of all seeds pooled (successes / trials,
with their Wilson interval); where every source recorded the task's progress flags
(``eval/reached/<flag>``, e.g. PickCube-v1's ``is_grasped``), the pooled episodes that
reached each. Sources of one group must have been evaluated on the same
number of episodes (the same fixed evaluation seeds), or the comparison is not like for like.
Writes ``benchmarks/results/NAME.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import textwrap
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402
from pretraining import read_evaluations  # noqa: E402

from mmada_rl.evaluation import ENSEMBLE_CHECKPOINT_SEPARATOR, wilson_interval  # noqa: E402
from mmada_rl.policy.ensemble import AVERAGE_FILE  # noqa: E402


def _run_seed(path: Path) -> int | str | None:
    """The training ``seed`` of a run directory (its newest checkpoint's config), a checkpoint, or a
    checkpoint's ``model/`` directory (``None`` when none of them says); for a weight average written by
    ``mmada-rl average``, its members' seeds, e.g. ``"0+1+2 averaged"``."""
    if (path / AVERAGE_FILE).is_file():
        seeds = [_run_seed(Path(member)) for member in json.loads((path / AVERAGE_FILE).read_text())["members"]]
        return None if None in seeds else "+".join(str(seed) for seed in seeds) + " averaged"
    for candidate in (path, path.parent):
        configs = sorted((candidate / "checkpoints").glob("step_*/config.json")) or [candidate / "config.json"]
        if configs[-1].is_file():
            return json.loads(configs[-1].read_text()).get("seed")
    return None


def _checkpoint_seed(checkpoint: str | None) -> int | str | None:
    """The training seed of the policy an ``eval.json`` names; for an ensemble (``"A + B + C"``, as
    ``mmada-rl eval --checkpoint A B C`` records it) its members' seeds joined by ``+``, e.g. ``"0+1+2"``."""
    if not checkpoint:
        return None
    seeds = [_run_seed(Path(c)) if Path(c).is_dir() else None for c in checkpoint.split(ENSEMBLE_CHECKPOINT_SEPARATOR)]
    if len(seeds) == 1:
        return seeds[0]
    return None if None in seeds else "+".join(str(seed) for seed in seeds)


def split_tags(source: Path) -> tuple[Path, int | None, str]:
    """``RUN[@STEP][@raw]`` -> ``(RUN, STEP or None, log prefix)`` when ``RUN`` is a directory: ``eval``, or
    ``eval_raw`` with ``@raw``; any other source -> ``(source, None, "eval")``. A path that merely contains
    ``@`` stays a path."""
    run, step, raw = str(source), None, False
    while "@" in run:
        head, _, tag = run.rpartition("@")
        if tag.isdigit() and step is None:
            step = int(tag)
        elif tag == "raw" and not raw:
            raw = True
        else:
            break
        run = head
    if run != str(source) and Path(run).is_dir():
        return Path(run), step, "eval_raw" if raw else "eval"
    return source, None, "eval"


REPORT_SEED_SEPARATOR = "#"


def read_report_seed(report: Path, tag: str) -> dict:
    """Seed ``S`` of group ``G`` (from 1) of ``report``, an earlier report of this script, as it recorded it;
    ``tag`` is ``G/sS``, what follows ``REPORT.json#`` in the source."""
    source = f"{report}{REPORT_SEED_SEPARATOR}{tag}"
    group_index, _, seed = tag.partition("/s")
    if not (group_index.isdigit() and seed.lstrip("-").isdigit()):
        raise ValueError(f"{source}: a seed of an earlier report is named REPORT.json#G/sS, e.g. "
                         f"benchmarks/results/seeds_X.json#1/s0 (group G counted from 1, training seed S).")
    groups = json.loads(report.read_text()).get("groups")
    if not groups:
        raise ValueError(f"{report} is not a report of benchmarks/seeds.py (it has no groups).")
    if not 1 <= int(group_index) <= len(groups):
        raise ValueError(f"{source}: {report} has groups 1 to {len(groups)}.")
    group = groups[int(group_index) - 1]
    rows = [r for r in group["seeds"] if str(r["seed"]) == seed]
    if len(rows) != 1:
        recorded = ", ".join(str(r["seed"]) for r in group["seeds"])
        raise ValueError(f"{source}: group {group_index} ({group['label']!r}) of {report} has "
                         f"{'no' if not rows else 'more than one'} seed {seed} (its seeds: {recorded}).")
    row = {k: v for k, v in rows[0].items() if k not in ("source", "ci")}
    return {"source": source, **row}


def read_source(source: Path) -> dict:
    """One seed's evaluation: ``{source, seed, step, episodes, successes, success_once, success_at_end, reached}``
    (``reached``: ``{flag: share of episodes}`` of the task's progress flags, empty where none were recorded)."""
    report, _, tag = str(source).rpartition(REPORT_SEED_SEPARATOR)
    if report.endswith(".json") and Path(report).is_file():
        return read_report_seed(Path(report), tag)
    label = source
    source, at_step, prefix = split_tags(source)
    if source.is_file():
        data = json.loads(source.read_text())
        if "eval/success_once" not in data:
            raise ValueError(f"{source} is not an evaluation written by `mmada-rl eval` (no eval/success_once).")
        episodes = int(data["eval/episodes"])
        seed = _checkpoint_seed(data.get("checkpoint"))
        row = {"seed": seed, "step": None, "episodes": episodes, "success_once": float(data["eval/success_once"]),
               "success_at_end": float(data["eval/success_at_end"]),
               "reached": {k[len("eval/reached/"):]: float(v) for k, v in data.items() if k.startswith("eval/reached/")}}
    elif source.is_dir():
        chosen = run_evaluation(source, at_step, prefix)
        row = {"seed": _run_seed(source), "step": chosen["step"], "episodes": int(chosen.get("episodes", 0)),
               "success_once": chosen["success_once"], "success_at_end": chosen.get("success_at_end"),
               "reached": {k[len("reached/"):]: v for k, v in chosen.items() if k.startswith("reached/")}}
    else:
        raise FileNotFoundError(f"{source}: neither an eval.json nor a run directory.")
    if row["episodes"] < 1:
        raise ValueError(f"{label}: the evaluation logs no episode count, so its successes cannot be pooled.")
    row["successes"] = round(row["success_once"] * row["episodes"])
    return {"source": str(label), **row}


def run_evaluation(run: Path, at_step: int | None = None, prefix: str = "eval") -> dict:
    """The evaluation a run directory logged at ``at_step`` (its last when ``None``), with its ``step``: online env
    steps for a fine-tuning run (its ``eval_history.json`` record), updates for a pretraining or imitation run."""
    evaluations, unit = _run_evaluations(run, prefix)
    if at_step is None:
        return evaluations[-1]
    chosen = next((e for e in evaluations if e["step"] == at_step), None)
    if chosen is None:
        logged = ", ".join(str(e["step"]) for e in evaluations)
        raise ValueError(f"{run} logged no evaluation at {unit} {at_step} (it logged: {logged}).")
    return chosen


def _run_evaluations(run: Path, prefix: str) -> tuple[list[dict], str]:
    """A run directory's evaluations by step, and what its steps count: a fine-tuning run's from its
    ``eval_history.json`` (online env steps), a pretraining or imitation run's from its logs (updates)."""
    if (run / "eval_history.json").is_file():
        if prefix != "eval":
            raise ValueError(f"{run} is a fine-tuning run: it evaluates one set of weights (no @raw).")
        evaluations = [{**e, "step": e["env_steps"]} for e in json.loads((run / "eval_history.json").read_text())]
        if not evaluations:
            raise ValueError(f"{run}/eval_history.json holds no evaluation.")
        return evaluations, "env step"
    evaluations = read_evaluations(run, prefix)
    if not evaluations:
        hint = " (a pretraining run logs it with ema.enabled=true ema.evaluate_raw=true)" if prefix == "eval_raw" else ""
        raise ValueError(f"{run} logged no evaluation (logs/scalars/{prefix}/success_once.csv is missing or "
                         f"empty){hint}.")
    return evaluations, "step"


def summarize_group(label: str, sources: list[Path]) -> dict:
    rows = [read_source(s) for s in sources]
    episodes = {r["episodes"] for r in rows}
    if len(episodes) != 1:
        counts = ", ".join(f"{r['source']}: {r['episodes']}" for r in rows)
        raise ValueError(f"group {label!r}: sources were evaluated on different numbers of episodes "
                         f"({counts}); evaluate them alike.")
    rates = [r["success_once"] for r in rows]
    successes, trials = sum(r["successes"] for r in rows), sum(r["episodes"] for r in rows)
    pooled = wilson_interval(successes, trials)
    for r in rows:
        r["ci"] = list(wilson_interval(r["successes"], r["episodes"]))
    flags = [f for f in rows[0]["reached"] if all(f in r["reached"] for r in rows)]  # recorded by every seed
    reached = {}
    for flag in flags:
        count = sum(round(r["reached"][flag] * r["episodes"]) for r in rows)
        reached[flag] = {"episodes": count, "trials": trials, "rate": count / trials, "ci": list(wilson_interval(count, trials))}
    return {
        "label": label, "seeds": rows, "num_seeds": len(rows), "episodes_per_seed": episodes.pop(),
        "mean": statistics.fmean(rates), "std": statistics.stdev(rates) if len(rates) > 1 else 0.0,
        "pooled": {"successes": successes, "trials": trials, "rate": successes / trials, "ci": list(pooled)},
        "reached": reached,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--group", nargs="+", action="append", required=True, metavar=("LABEL", "SOURCE"),
                        help="a label, then one source per training seed (eval.json, run directory, RUN@STEP for the "
                             "run's evaluation logged at STEP, RUN@raw or RUN@STEP@raw for the evaluation of the "
                             "optimizer's own weights beside a weight average, REPORT.json#G/sS for seed S of group G "
                             "of an earlier report); repeatable")
    parser.add_argument("--name", default="seeds", help="result file name under --out (default: seeds)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    for group in args.group:
        if len(group) < 2:
            parser.error(f"--group {group[0]!r} names no source: give a label, then one eval.json or run per seed.")
    groups = [summarize_group(label, [Path(s) for s in sources]) for label, *sources in args.group]

    staged = any(g["reached"] for g in groups)  # a column of stages when any group recorded them
    rows = []
    for g in groups:
        per_seed = "; ".join(f"s{r['seed'] if r['seed'] is not None else '?'}: {r['successes']}/{r['episodes']}"
                             for r in g["seeds"])
        p = g["pooled"]
        rows.append([g["label"], g["num_seeds"], g["episodes_per_seed"], per_seed, f"{g['mean']:.2f} ± {g['std']:.2f}",
                     f"{p['successes']}/{p['trials']} = {p['rate']:.2f} [{p['ci'][0]:.2f}, {p['ci'][1]:.2f}]"])
        if staged:
            rows[-1].append("; ".join(f"{flag} {r['episodes']}/{r['trials']}" for flag, r in g["reached"].items()) or "-")
    header = ["configuration", "training seeds", "episodes per seed", "successes per seed",
              "success_once mean ± std over seeds", "pooled [95% CI]"]
    if staged:
        header.append("episodes reaching each stage, pooled")
    table = markdown_table(header, rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # long labels wrapped under their group rather than rotated off the figure: 2.6 inches per group (up to 10
    # groups), each label's lines as wide as its share of the figure allows
    group_in, margin_in, max_groups = 2.6, 1.5, 10
    groups_in_width = min(len(groups), max_groups)
    width = margin_in + group_in * groups_in_width
    label_chars = max(12, 32 * groups_in_width // len(groups))
    fig, ax = plt.subplots(figsize=(width, 5.0))
    for i, g in enumerate(groups):
        n = g["num_seeds"]
        for j, r in enumerate(g["seeds"]):
            x = i + (j - (n - 1) / 2) * 0.18
            ax.errorbar(x, r["success_once"], yerr=[[r["success_once"] - r["ci"][0]], [r["ci"][1] - r["success_once"]]],
                        fmt="o", color=f"C{i}", capsize=3)
        ax.hlines(g["pooled"]["rate"], i - 0.35, i + 0.35, colors=f"C{i}", linestyles="--")
    ax.set_xticks(range(len(groups)), [textwrap.fill(g["label"], label_chars) for g in groups], fontsize=7)
    ax.set_ylabel("success_once\n(per seed, 95% CI; dashed: pooled)")
    ax.set_ylim(-0.02, 1.02)
    save_figure(fig, args.out / f"{args.name}.png")
    write_results(args.name, {"groups": groups}, f"# Training seeds\n\n{table}\n\n![seeds]({args.name}.png)\n",
                  directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
