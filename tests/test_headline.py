"""The headline comparison is built from the recorded results, and says so when one is missing."""
from __future__ import annotations

import json
import shutil

import pytest

from script_loader import REPO, load_script

headline = load_script("benchmarks/compare/headline.py")
RESULTS = REPO / "benchmarks" / "results"


def test_headline_reproduces_the_recorded_figures(tmp_path):
    assert headline.main(["--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "headline.json").read_text())
    assert (tmp_path / "headline.png").stat().st_size > 0
    markdown = (tmp_path / "headline.md").read_text()
    rows = {(row.task, row.label): f"{i:02d}" for i, row in enumerate(headline.HEADLINE)}
    # each curve is its compare.json entry's evaluations, seeds merged across reports
    recorded = json.loads((RESULTS / "compare_push_dart" / "compare.json").read_text())
    entry = recorded["results"]["PushCube-v1"]["mmada_return_to_go_noise_keep_lr1e4_ema"]
    assert written["results"]["PushCube-v1"][rows["PushCube-v1", "ours: returns to go, lr 1e-4, moving average"]]["histories"] == entry["histories"]
    sac = written["results"]["PickCube-v1"][rows["PickCube-v1", "SAC + demonstrations (RLPD)"]]
    assert sorted(sac["histories"]) == ["s0", "s1", "s2"] and sac["online"]
    # a demonstration-only method from a seeds report: one evaluation per seed at env step 0
    dp = written["results"]["PickCube-v1"][rows["PickCube-v1", "Diffusion Policy, 24,000 steps (demonstrations only)"]]
    assert not dp["online"] and [h[0]["success_once"] for h in dp["histories"].values()] == [0.34, 0.66, 0.34]
    # the final figures: the pooled groups added up, or the curves' last evaluations
    finals = {(row[0], row[1]): row[-1] for row in written["final"]}
    assert finals["PickCube-v1", "BC, 24,000 steps (demonstrations only)"].startswith("266/450 = **0.59**")
    assert finals["PickCube-v1", "ours: returns to go, lr 1e-4, moving average, from the d = 128 policies"].startswith("335/450")
    assert finals["PushCube-v1", "ours: returns to go, lr 1e-4, moving average"].startswith("117/150 = **0.78**")
    assert "seeds_PickCube-v1-fov45-100-bc24k #2 (BC trained 24,000 steps: next 100)" in markdown


def test_a_missing_recorded_result_is_named(tmp_path):
    shutil.copytree(RESULTS / "compare_pick100_cells4_gripper", tmp_path / "compare_pick100_cells4_gripper")
    with pytest.raises(SystemExit, match="seeds_PickCube-v1-fov45-100-bc24k.json is missing: the headline reads the recorded"):
        headline.main(["--results", str(tmp_path), "--out", str(tmp_path / "out")])
