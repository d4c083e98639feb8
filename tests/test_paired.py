"""benchmarks/paired.py: evaluations on the same episodes compared episode by episode."""
from __future__ import annotations

import json
import math

import pytest
from script_loader import load_script

from mmada_rl.evaluation import EVAL_SEED_BASE

paired = load_script("benchmarks/paired.py")


def write_eval(path, successes, first_seed=EVAL_SEED_BASE):
    """An eval.json as `mmada-rl eval` writes it, reduced to what the comparison reads."""
    path.parent.mkdir(parents=True, exist_ok=True)
    episodes = [{"seed": first_seed + i, "success_once": bool(s), "success_at_end": False}
                for i, s in enumerate(successes)]
    path.write_text(json.dumps({"eval/success_once": sum(successes) / len(successes), "checkpoint": str(path.parent),
                                "per_episode": episodes}))
    return str(path)


def test_exact_mcnemar_is_the_two_sided_binomial_tail():
    assert paired.mcnemar_exact(0, 0) == 1.0
    assert paired.mcnemar_exact(0, 6) == pytest.approx(2 / 2**6)
    assert paired.mcnemar_exact(9, 1) == pytest.approx(2 * (1 + 10) / 2**10)
    assert paired.mcnemar_exact(3, 3) == 1.0  # an even split is capped at 1
    # the same as summing the binomial pmf over every split at most as likely as the observed one
    n, k = 12, 2
    pmf = [math.comb(n, i) / 2**n for i in range(n + 1)]
    assert paired.mcnemar_exact(k, n - k) == pytest.approx(sum(p for p in pmf if p <= pmf[k] + 1e-15))


def test_paired_report_counts_discordant_episodes_and_failure_overlap(tmp_path):
    # two training seeds, five episodes each; seed 0 gains episodes 2 and 4, seed 1 gains 0 and loses 3
    before = [write_eval(tmp_path / "before_s0/eval.json", [1, 1, 0, 1, 0]),
              write_eval(tmp_path / "before_s1/eval.json", [0, 1, 0, 1, 1])]
    after = [write_eval(tmp_path / "after_s0/eval.json", [1, 1, 1, 1, 1]),
             write_eval(tmp_path / "after_s1/eval.json", [1, 1, 0, 0, 1])]
    out = tmp_path / "report"
    assert paired.main(["--arm", "before", *before, "--arm", "after", *after, "--name", "p", "--out", str(out)]) == 0
    report = json.loads((out / "p.json").read_text())
    first, second = report["arms"]
    assert first["successes"] == [3, 3] and second["successes"] == [5, 3]
    assert first["pooled"]["successes"] == 6 and first["pooled"]["trials"] == 10
    # env seeds failed by 0, 1 and 2 of the arm's policies: before fails episode 2 with both, 0 and 4 with one
    assert first["failure_overlap"] == [2, 2, 1] and second["failure_overlap"] == [3, 2, 0]
    (c,) = report["contrasts"]  # default: every arm against the first
    assert (c["both"], c["only_first"], c["only_second"], c["neither"], c["pairs"]) == (5, 1, 3, 1, 10)
    assert c["p_mcnemar"] == pytest.approx(paired.mcnemar_exact(1, 3)) == pytest.approx(0.625)
    assert "exact McNemar p" in (out / "p.md").read_text() and (out / "p.png").stat().st_size > 0


def test_paired_report_refuses_what_cannot_be_paired(tmp_path):
    a = write_eval(tmp_path / "a/eval.json", [1, 0])
    b = write_eval(tmp_path / "b/eval.json", [1, 0])
    shifted = write_eval(tmp_path / "c/eval.json", [1, 0], first_seed=EVAL_SEED_BASE + 50)
    with pytest.raises(ValueError, match="ran other env seeds"):
        paired.main(["--arm", "a", a, "--arm", "c", shifted, "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="different numbers of sources"):
        paired.main(["--arm", "a", a, b, "--arm", "b", b, "--out", str(tmp_path)])
    (tmp_path / "bare.json").write_text(json.dumps({"eval/success_once": 0.5}))
    with pytest.raises(ValueError, match="records no episodes"):
        paired.main(["--arm", "a", a, "--arm", "bare", str(tmp_path / "bare.json"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit):  # one arm only
        paired.main(["--arm", "a", a, "--out", str(tmp_path)])
    with pytest.raises(SystemExit):  # an arm out of range
        paired.main(["--arm", "a", a, "--arm", "b", b, "--contrast", "1", "3", "--out", str(tmp_path)])


def test_a_fine_tuning_run_is_a_source_where_its_evaluations_kept_their_episodes(tmp_path):
    """A run directory is read from its eval_history.json (RUN: the last evaluation, RUN@S: the one at S env
    steps); a record without episodes, or a run that is not a fine-tuning run, is refused with what to do."""
    a = write_eval(tmp_path / "a/eval.json", [1, 0])
    run = tmp_path / "run"
    run.mkdir()
    episodes = [{"seed": EVAL_SEED_BASE + i, "success_once": s} for i, s in enumerate([False, True])]
    (run / "eval_history.json").write_text(json.dumps([
        {"env_steps": 0, "success_once": 0.5, "episodes": 2},  # recorded before evaluations kept their episodes
        {"env_steps": 4135, "success_once": 0.5, "episodes": 2, "per_episode": episodes}]))
    out = tmp_path / "report"
    assert paired.main(["--arm", "a", a, "--arm", "run", str(run), "--name", "p", "--out", str(out)]) == 0
    (c,) = json.loads((out / "p.json").read_text())["contrasts"]
    assert (c["only_first"], c["only_second"]) == (1, 1)
    assert paired.main(["--arm", "a", a, "--arm", "run", f"{run}@4135", "--name", "p", "--out", str(out)]) == 0
    with pytest.raises(ValueError, match="evaluation at env step 0 keeps no episodes"):
        paired.main(["--arm", "a", a, "--arm", "run", f"{run}@0", "--out", str(out)])
    with pytest.raises(ValueError, match="evaluation at the end only, in final_eval/eval.json; evaluate one of its"):
        paired.main(["--arm", "a", a, "--arm", "dir", str(tmp_path / "a"), "--out", str(out)])
