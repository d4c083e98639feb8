"""The headline comparison: each method's best recorded variant on PickCube-v1 and PushCube-v1, one table and one figure.

Every number is read from the recorded results under ``benchmarks/results/``: the ``compare.json`` of
``compare.py report`` (each seed's evaluations against online env steps, the first 50 fixed evaluation episodes
each) and the ``seeds_*.json`` of ``benchmarks/seeds.py`` (the same policies on more episodes, and the imitation
baselines whose runs ``compare.py`` did not hold). :data:`HEADLINE` names, for each row, where its numbers come
from; nothing is simulated or trained here, so it runs in seconds on a fresh checkout.

    python benchmarks/compare/headline.py            # benchmarks/results/headline.{json,md,png}
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, write_results  # noqa: E402
from compare import budget_table, plot_curves  # noqa: E402

from mmada_rl.evaluation import wilson_interval  # noqa: E402

#: online env-step budgets of the table and the mean curves (the evaluations of every online run fall near these)
BUDGETS = [0, 10_000, 20_000, 30_000, 40_000, 50_000]


class Row(NamedTuple):
    """One method in the headline and where its recorded numbers are.

    Attributes:
        task: the ManiSkill task.
        label: what the row is (the method, its start, what stands behind it).
        observations: what the policy reads (``rgb+proprio``, or the privileged state as a reference).
        compare: ``(report, method)`` pairs: ``results/REPORT/compare.json``'s entry ``method`` gives its seeds'
            evaluations (several reports' seeds are merged; one seed may come from one report only).
        seeds: ``(name, group)`` pairs for a demonstration-only method without a ``compare.json`` entry:
            ``results/seeds_NAME.json``'s group number ``group`` gives one evaluation per seed, at env step 0.
        pooled: ``(name, group)`` pairs whose successes and episodes add up to the row's final figure (the policies
            at the end of training, on more evaluation episodes than the curves' 50 per seed); empty: the curves'
            last evaluations are pooled instead.
    """

    task: str
    label: str
    observations: str
    compare: tuple[tuple[str, str], ...] = ()
    seeds: tuple[tuple[str, int], ...] = ()
    pooled: tuple[tuple[str, int], ...] = ()


_OURS_D128 = "mmada_return_to_go_noise_keep_lr1e4_gripper_ema"
_PICK = "PickCube-v1-fov45-100"
HEADLINE: tuple[Row, ...] = (
    # PickCube-v1, 100 DART demonstrations, 45° camera
    Row("PickCube-v1", "ours: returns to go, lr 1e-4, moving average, from the d = 128 policies", "rgb+proprio",
        compare=(("compare_pick100_cells4_gripper", _OURS_D128),), pooled=((f"{_PICK}-bc24k", 7), (f"{_PICK}-bc24k", 8))),
    Row("PickCube-v1", "ours, the same from the d = 256 policies", "rgb+proprio",
        compare=(("compare_pick100_cells4_w256", _OURS_D128),), pooled=((f"{_PICK}-w256-ft", 1), (f"{_PICK}-w256-ft", 2))),
    Row("PickCube-v1", "ours, the same from the ensemble-distilled policies (+23k env steps of the teacher's rollouts "
        "before step 0)", "rgb+proprio", compare=(("compare_pick_distill", _OURS_D128),),
        pooled=((f"{_PICK}-distill2-ensft", 2), (f"{_PICK}-distill2-ensft", 3))),
    Row("PickCube-v1", "ours, the same after a second round of distillation (+194k env steps before step 0)",
        "rgb+proprio", compare=(("compare_pick_distill2", _OURS_D128),),
        pooled=((f"{_PICK}-distill2-ensft", 8), (f"{_PICK}-distill2-ensft", 9))),
    Row("PickCube-v1", "BC, 24,000 steps (demonstrations only)", "rgb+proprio", seeds=((f"{_PICK}-bc24k", 1),),
        pooled=((f"{_PICK}-bc24k", 1), (f"{_PICK}-bc24k", 2))),
    Row("PickCube-v1", "Diffusion Policy, 24,000 steps (demonstrations only)", "rgb+proprio",
        seeds=((f"{_PICK}-bc24k", 5), (f"{_PICK}-dp24k-s12", 1))),
    Row("PickCube-v1", "PPO from scratch", "rgb+proprio",
        compare=(("compare_pick_dart", "ppo_rgb"), ("compare_pick_dart_ppo_s12", "ppo_rgb")),
        pooled=(("PickCube-v1-dart100-ppo-rgb-50k", 0),)),
    Row("PickCube-v1", "SAC + demonstrations (RLPD)", "privileged state (reference)",
        compare=(("compare_pick_dart", "sac_rlpd_state"), ("compare_pick_dart_s2", "sac_rlpd_state")),
        pooled=(("PickCube-v1-dart100-rl-baselines-50k", 2), ("PickCube-v1-dart100-rl-baselines-50k-s2", 0))),
    Row("PickCube-v1", "IQL offline -> online", "privileged state (reference)",
        compare=(("compare_pick_dart", "iql_state"), ("compare_pick_dart_s2", "iql_state")),
        pooled=(("PickCube-v1-dart100-rl-baselines-50k", 4), ("PickCube-v1-dart100-rl-baselines-50k-s2", 2))),
    # PushCube-v1, 100 DART demonstrations, 60° camera
    Row("PushCube-v1", "ours: returns to go, lr 1e-4, moving average", "rgb+proprio",
        compare=(("compare_push_dart", "mmada_return_to_go_noise_keep_lr1e4_ema"),)),
    Row("PushCube-v1", "ours, the same at lr 3e-5", "rgb+proprio",
        compare=(("compare_push_dart", "mmada_return_to_go_noise_keep_ema"),)),
    Row("PushCube-v1", "ours, lr 1e-4 with a quarter of each minibatch online (demos.ratio=0.75)", "rgb+proprio",
        compare=(("compare_push_dart_control", "mmada_return_to_go_noise_keep_lr1e4_ema_demos075"),),
        pooled=(("PushCube-v1-fov60-dart100-share50k", 0), ("PushCube-v1-fov60-dart100-share50k", 1))),
    Row("PushCube-v1", "BC, 24,000 steps (demonstrations only)", "rgb+proprio",
        compare=(("compare_push_dart_rl", "bc_24k"),)),
    Row("PushCube-v1", "Diffusion Policy, 24,000 steps (demonstrations only)", "rgb+proprio",
        compare=(("compare_push_dart_rl", "diffusion_policy_24k"),)),
    Row("PushCube-v1", "PPO from scratch", "rgb+proprio", compare=(("compare_push_dart_rl", "ppo_rgb"),),
        pooled=(("PushCube-v1-dart100-ppo-rgb-50k", 0),)),
    Row("PushCube-v1", "SAC + demonstrations (RLPD)", "privileged state (reference)",
        compare=(("compare_push_dart", "sac_rlpd_state"),)),
    Row("PushCube-v1", "IQL offline -> online", "privileged state (reference)",
        compare=(("compare_push_dart_rl", "iql_state"),)),
)


@functools.cache  # several rows read one file (a seeds report's groups, a compare report's methods)
def _load(path: Path) -> dict:
    if not path.exists():
        raise SystemExit(f"[headline] {path} is missing: the headline reads the recorded results; restore it from git.")
    return json.loads(path.read_text())


def histories(row: Row, results: Path) -> tuple[dict[str, list[dict]], bool]:
    """Each seed's evaluations (``{"s0": [{"env_steps", "success_once", "episodes"}, ...]}``) and whether the
    method learns online (else its one evaluation stands at env step 0)."""
    merged, online = {}, None
    for report, method in row.compare:
        entry = _load(results / report / "compare.json")["results"][row.task].get(method)
        if entry is None:
            raise SystemExit(f"[headline] {report}/compare.json has no {row.task} entry {method!r}.")
        online = entry["online"] if online is None else online
        for seed, history in entry["histories"].items():
            if seed in merged:
                raise SystemExit(f"[headline] {row.label!r}: seed {seed} is in two reports; name it in one.")
            merged[seed] = history
    for name, group in row.seeds:
        online = False
        for r in _load(results / f"seeds_{name}.json")["groups"][group]["seeds"]:
            merged[f"s{r['seed']}"] = [{"env_steps": 0, "success_once": r["success_once"], "episodes": r["episodes"]}]
    return dict(sorted(merged.items())), bool(online)


def pooled(row: Row, results: Path, histories_: dict[str, list[dict]]) -> tuple[int, int, list[str]]:
    """Successes, episodes and the groups they come from, for the row's final figure."""
    if not row.pooled:
        last = [h[-1] for h in histories_.values()]
        return (sum(round(r["success_once"] * r["episodes"]) for r in last), sum(r["episodes"] for r in last),
                ["the curves' last evaluations"])
    successes = trials = 0
    sources = []
    for name, group in row.pooled:
        g = _load(results / f"seeds_{name}.json")["groups"][group]
        successes, trials = successes + g["pooled"]["successes"], trials + g["pooled"]["trials"]
        sources.append(f"seeds_{name} #{group} ({g['label']})")
    return successes, trials, sources


def build(results: Path = RESULTS) -> tuple[dict, list[list], list[list]]:
    """``compare.py``'s results layout (task → row → entry) for the curves and the equal-budget table, the final
    figures' rows and the sources' rows."""
    report, finals, sources = {}, [], []
    for i, row in enumerate(HEADLINE):
        runs, online = histories(row, results)
        report.setdefault(row.task, {})[f"{i:02d}"] = {"label": row.label, "observations": row.observations,
                                                       "online": online, "histories": runs}
        k, n, where = pooled(row, results, runs)
        low, high = wilson_interval(k, n)
        end = max(h[-1]["env_steps"] for h in runs.values()) if online else 0
        finals.append([row.task, row.label, row.observations, len(runs), f"{end:,}" if online else "-",
                       f"{k}/{n} = **{k / n:.2f}** [{low:.2f}, {high:.2f}]"])
        sources.append([row.task, row.label, ", ".join(f"{r}/compare.json: {m}" for r, m in row.compare) or
                        ", ".join(f"seeds_{s} #{g}" for s, g in row.seeds), "; ".join(where)])
    return report, finals, sources


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the recorded results are read")
    parser.add_argument("--out", type=Path, default=RESULTS, help="where headline.{json,md,png} go")
    args = parser.parse_args(argv)
    report, finals, sources = build(args.results)
    tasks = list(report)
    plot_curves(report, tasks, BUDGETS, args.out / "headline.png")
    at_budget = budget_table(report, BUDGETS)
    final = markdown_table(["task", "method", "observations", "seeds", "online env steps", "success_once at the end, "
                            "pooled over seeds [95% CI]"], finals)
    source = markdown_table(["task", "method", "curves from", "final figure from"], sources)
    write_results("headline", {"budgets": BUDGETS, "results": report, "final": finals}, (
        "# Headline comparison: 100 DART demonstrations per task, the same camera, evaluation seeds and env-step budget\n\n"
        "PickCube-v1 through a 45° camera, PushCube-v1 through a 60° one; greedy `success_once` on the fixed "
        "evaluation seeds. Our rows are fine-tuned online from policies pretrained on the demonstrations; the "
        "imitation baselines train on the demonstrations alone (one level for every budget); PPO learns from "
        "scratch; SAC and IQL read the privileged state, as references.\n\n"
        "## success_once at equal online env steps (mean over seeds; the first 50 evaluation episodes of each)\n\n"
        f"{at_budget}\n\n## At the end, on every evaluation episode recorded\n\n{final}\n\n"
        f"![curves](headline.png)\n\n## Where each row's numbers were recorded\n\n{source}\n"), directory=args.out)
    print(at_budget, final, sep="\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
