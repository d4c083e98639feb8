"""Paired comparisons of evaluations on the same episodes: which episodes each arm wins and loses.

    R=runs/compare_pick100_cells4_w256/PickCube-v1/mmada_return_to_go_noise_keep_gripper_ema
    python benchmarks/paired.py \\
        --arm "pretrained, greedy" runs/pick100_cells4_w256_s{0,1,2}/eval150/eval.json \\
        --arm "fine-tuned, greedy moving average" $R/s{0,1,2}/eval150/eval.json \\
        --contrast 1 2 --name paired_example

``benchmarks/seeds.py`` pools each configuration's successes and compares configurations as
independent samples. Evaluations written by ``mmada-rl eval`` on the same fixed evaluation seeds
are not independent, though: the same initial states, and for one training seed the same policy
before and after a change. Pairing them episode by episode asks more of the data:

* an **arm** is a label and one source per training seed: an ``eval.json`` of ``mmada-rl eval``
  (its ``per_episode`` records; a pretraining or imitation run writes its evaluation at the end as
  ``RUN/final_eval/eval.json``), or a fine-tuning or online RL baseline run directory (``recipes/finetune``,
  ``recipes/baselines/online.py``, e.g. one of ``benchmarks/compare``'s) for the last evaluation its
  ``eval_history.json`` recorded, ``RUN@S`` for the one at ``S`` online env steps (each record
  keeps its episodes); every arm names the same
  number of sources, and source ``i`` of one arm is paired with source ``i`` of every other (list
  the training seeds in the same order), episode by episode on the env seeds both ran, which must
  be the same list;
* a **contrast** ``I J`` (arms counted from 1; ``--contrast``, repeatable; default: every arm
  against the first) counts the paired episodes both arms succeed in, only ``I``, only ``J`` and
  neither, and gives the exact two-sided McNemar test of the discordant pairs (a binomial test
  of ``only I`` against ``only J`` at one half), the paired counterpart of comparing two pooled
  rates;
* within an arm of two or more sources, the **failure overlap**: on how many env seeds ``k`` of
  its ``n`` policies fail, for ``k = 0..n``. Failures shared by every policy are initial states
  none of them solves; failures spread over single policies are each policy's own, which an
  ensemble of them can average away.

Success is ``success_once`` (success at any step), as everywhere in the reports.
Writes ``benchmarks/results/NAME.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402
from seeds import run_evaluation, split_tags  # noqa: E402

from mmada_rl.evaluation import wilson_interval  # noqa: E402


def read_episodes(path: Path) -> dict:
    """One source's episodes: ``{source, checkpoint, seeds: [env seed], success: [bool]}``; the source is an
    ``eval.json`` or a fine-tuning or online RL baseline run's evaluation (``RUN``, ``RUN@S``)."""
    run, at_step, _ = split_tags(path)
    if run.is_dir():
        return read_run_episodes(path, run, at_step)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (an arm's sources are eval.json files of `mmada-rl eval`, "
                                f"or fine-tuning run directories).")
    data = json.loads(path.read_text())
    episodes = data.get("per_episode")
    if "eval/success_once" not in data or not episodes:
        raise ValueError(f"{path} records no episodes (per_episode): pair evaluations written by `mmada-rl eval`.")
    return _episodes(path, data.get("checkpoint"), episodes)


def _episodes(source: Path, checkpoint: str | None, episodes: list[dict]) -> dict:
    """``per_episode`` records (``seed``, ``success_once``; an ``eval.json``'s or an ``eval_history.json`` record's)
    as :func:`read_episodes` returns them."""
    return {"source": str(source), "checkpoint": checkpoint,
            "seeds": [int(e["seed"]) for e in episodes], "success": [bool(e["success_once"]) for e in episodes]}


def read_run_episodes(source: Path, run: Path, at_step: int | None) -> dict:
    """The episodes of a fine-tuning (or online RL baseline) run's evaluation at ``at_step`` online env steps (its
    last when ``None``)."""
    if not (run / "eval_history.json").is_file():
        final = run / "final_eval" / "eval.json"
        hint = (f"pair {final}, its evaluation at the end" if final.is_file() and at_step is None else
                "evaluate one of its checkpoints with `mmada-rl eval --out DIR` and pair DIR/eval.json")
        raise ValueError(f"{source}: a pretraining or imitation run keeps the episodes of its evaluation at the end "
                         f"only, in final_eval/eval.json; {hint}.")
    chosen = run_evaluation(run, at_step)
    episodes = chosen.get("per_episode")
    if not episodes:
        raise ValueError(f"{source}: its evaluation at env step {chosen['step']} keeps no episodes (per_episode, "
                         f"which older runs did not record): evaluate its checkpoint with `mmada-rl eval`.")
    return _episodes(source, str(run), episodes)


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar p-value: the binomial probability, at one half, of a split of the
    ``only_a + only_b`` discordant pairs at least as uneven as the one observed (1 when there are none)."""
    n, k = only_a + only_b, min(only_a, only_b)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


def check_paired(arms: list[dict]) -> None:
    """Every arm names the same number of sources, and paired sources ran the same env seeds."""
    counts = {len(arm["sources"]) for arm in arms}
    if len(counts) != 1:
        named = ", ".join(f"{arm['label']!r}: {len(arm['sources'])}" for arm in arms)
        raise ValueError(f"arms name different numbers of sources ({named}); source i of each arm is paired "
                         f"with source i of the others, so give every arm one source per training seed.")
    for i in range(counts.pop()):
        first = arms[0]["sources"][i]
        for arm in arms[1:]:
            other = arm["sources"][i]
            if other["seeds"] != first["seeds"]:
                raise ValueError(f"{other['source']} ran other env seeds than {first['source']} "
                                 f"({len(other['seeds'])} from {other['seeds'][0]} against {len(first['seeds'])} "
                                 f"from {first['seeds'][0]}): evaluate both on the same episodes "
                                 f"(`mmada-rl eval --episodes N --seed-offset O` alike).")


def summarize_arm(label: str, sources: list[dict]) -> dict:
    successes = [sum(s["success"]) for s in sources]
    trials = sum(len(s["success"]) for s in sources)
    pooled = sum(successes)
    arm = {"label": label, "sources": sources, "successes": successes,
           "pooled": {"successes": pooled, "trials": trials, "rate": pooled / trials,
                      "ci": list(wilson_interval(pooled, trials))}}
    if len(sources) > 1 and all(s["seeds"] == sources[0]["seeds"] for s in sources):
        failed = [sum(not s["success"][e] for s in sources) for e in range(len(sources[0]["seeds"]))]
        arm["failure_overlap"] = [failed.count(k) for k in range(len(sources) + 1)]
    return arm


def contrast(arms: list[dict], i: int, j: int) -> dict:
    """Arm ``i`` against arm ``j`` (0-based), over every paired episode of every paired source."""
    counts = {"both": 0, "only_first": 0, "only_second": 0, "neither": 0}
    for a, b in zip(arms[i]["sources"], arms[j]["sources"]):
        for x, y in zip(a["success"], b["success"]):
            counts["both" if x and y else "only_first" if x else "only_second" if y else "neither"] += 1
    return {"first": arms[i]["label"], "second": arms[j]["label"], "arms": [i + 1, j + 1], **counts,
            "pairs": sum(counts.values()), "p_mcnemar": mcnemar_exact(counts["only_first"], counts["only_second"])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arm", nargs="+", action="append", required=True, metavar=("LABEL", "SOURCE"),
                        help="a label, then one source per training seed, in the same seed order in every arm: an "
                             "eval.json of `mmada-rl eval`, or a fine-tuning or online RL baseline run directory (its last evaluation; "
                             "RUN@S: the one at S online env steps); repeatable (at least two arms)")
    parser.add_argument("--contrast", nargs=2, type=int, action="append", metavar=("I", "J"),
                        help="compare arm I with arm J (counted from 1) episode by episode; repeatable "
                             "(default: every arm against the first)")
    parser.add_argument("--name", default="paired", help="result file name under --out (default: paired)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    for arm in args.arm:
        if len(arm) < 2:
            parser.error(f"--arm {arm[0]!r} names no source: give a label, then one eval.json (or run directory) "
                         f"per training seed.")
    if len(args.arm) < 2:
        parser.error("give at least two --arm to compare.")
    pairs = args.contrast or [[1, j] for j in range(2, len(args.arm) + 1)]
    for i, j in pairs:
        if not (1 <= i <= len(args.arm) and 1 <= j <= len(args.arm)) or i == j:
            parser.error(f"--contrast {i} {j}: name two different arms between 1 and {len(args.arm)}.")

    arms = [summarize_arm(label, [read_episodes(Path(p)) for p in paths]) for label, *paths in args.arm]
    check_paired(arms)
    contrasts = [contrast(arms, i - 1, j - 1) for i, j in pairs]

    arm_rows = []
    for n, arm in enumerate(arms, 1):
        p = arm["pooled"]
        overlap = arm.get("failure_overlap")
        arm_rows.append([n, arm["label"], " + ".join(str(s) for s in arm["successes"]),
                         f"{p['successes']}/{p['trials']} = {p['rate']:.2f} [{p['ci'][0]:.2f}, {p['ci'][1]:.2f}]",
                         " / ".join(str(c) for c in overlap) if overlap else "-"])
    arms_table = markdown_table(["arm", "label", "successes per source", "pooled [95% CI]",
                                 "env seeds failed by 0 / 1 / … / n of its policies"], arm_rows)
    contrast_rows = [[f"{c['arms'][0]} vs {c['arms'][1]}", c["first"], c["second"], c["pairs"], c["both"],
                      c["only_first"], c["only_second"], c["neither"], f"{c['p_mcnemar']:.3g}"] for c in contrasts]
    contrasts_table = markdown_table(["contrast", "first", "second", "paired episodes", "both succeed",
                                      "only the first", "only the second", "neither", "exact McNemar p"],
                                     contrast_rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    for n, arm in enumerate(arms):
        p = arm["pooled"]
        left.errorbar(n, p["rate"], yerr=[[p["rate"] - p["ci"][0]], [p["ci"][1] - p["rate"]]], fmt="o",
                      color=f"C{n}", capsize=4)
    left.set_xticks(range(len(arms)), [str(n) for n in range(1, len(arms) + 1)])
    left.set_xlabel("arm (labels in the table)")
    left.set_ylabel("success_once, pooled (95% CI)")
    left.set_ylim(-0.02, 1.02)
    width = 0.8 / len(contrasts)
    for n, c in enumerate(contrasts):
        right.bar([x + n * width for x in range(2)], [c["only_first"], c["only_second"]], width,
                  label=f"{c['arms'][0]} vs {c['arms'][1]} (p = {c['p_mcnemar']:.2g})")
    right.set_xticks([x + width * (len(contrasts) - 1) / 2 for x in range(2)],
                     ["only the first succeeds", "only the second succeeds"])
    right.set_ylabel("paired episodes")
    right.legend(fontsize=7)
    save_figure(fig, args.out / f"{args.name}.png")
    markdown = (f"# Paired evaluations\n\n{arms_table}\n\n{contrasts_table}\n\n![paired]({args.name}.png)\n")
    write_results(args.name, {"arms": arms, "contrasts": contrasts}, markdown, directory=args.out)
    print(arms_table, contrasts_table, sep="\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
