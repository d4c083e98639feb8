"""Tokenizers fitted on a real demonstration buffer: the command, its report, the replay proof, the pipeline."""
from __future__ import annotations

import json

import pytest
import torch

from mmada_rl.data import DemoBuffer
from mmada_rl.tokenizers.from_buffer import FittedTokenizers, TokenizerFitConfig, buffer_arrays, fit_tokenizers
from mmada_rl.tokenizers.normalize import ActionOutOfRangeWarning
from mmada_rl.tokenizers.replay import replay_demonstrations, round_trip


def test_fit_tokenizers_command_writes_tokenizers_and_report(pick_demos, run_cli, tmp_path):
    out = tmp_path / "tok"
    proc = run_cli("fit-tokenizers", "--data", pick_demos, "--out", out, "--action-steps", "30", "--image-steps", "5",
                   "--codebook-size", "32", "--tokens-per-action", "2", "--replay-episodes", "1",
                   "--image-foreground-weight", "10", "--state-differences", "26:19", "27:20", "28:21")
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert set(report["actions"]) == {"vq (ours)", "256 bins", "residual FSQ"}
    for rep in report["actions"].values():
        assert len(rep["per_dim"]) == 7 and rep["summary"]["mae_m"] >= 0
    assert report["actions"]["256 bins"]["summary"]["tokens_per_action"] == 7
    assert report["actions"]["residual FSQ"]["summary"]["tokens_per_action"] == 2
    assert report["replay"]["raw actions"]["success_rate"] == 1.0  # the recorded actions solve the task again
    image = report["image"]["summary"]
    assert 0.0 <= image["psnr_db"] <= 100.0 and 0.0 <= image["psnr_foreground_db"] <= 100.0
    assert 0.0 < image["foreground_fraction"] < 0.5  # the robot and the cube in front of a fixed camera
    for name in ("report.md", "reconstructions.png", "loss_curves.png"):
        assert (out / name).stat().st_size > 0
    assert "replay success" in (out / "report.md").read_text()
    loaded = FittedTokenizers.load(out)
    assert loaded.action.tokens_per_action == 2 and loaded.proprio is not None
    assert loaded.proprio.config.action_dim == 29 + 3  # PickCube-v1's state and the goal relative to the gripper
    assert loaded.image.config.foreground_weight == 10.0 and loaded.image.background.float().std() > 0  # a fitted median frame


def test_replay_of_a_broken_tokenizer_fails_where_raw_actions_succeed(pick_demos):
    """The closed-loop proof detects a tokenizer that loses the actions (here: one that decodes everything to zero)."""

    class Zero:
        def encode(self, actions):
            return torch.zeros(*actions.shape[:-1], 1, dtype=torch.long)

        def decode(self, tokens):
            return torch.zeros(*tokens.shape[:-1], 7)

    buf = DemoBuffer.open(pick_demos)
    results = replay_demonstrations(buf, {"raw": None, "zero": Zero()}, max_episodes=1, progress=False)
    assert results["raw"].successes == [True]
    assert results["zero"].successes == [False]


def test_uniform_bins_round_trip_within_half_a_bin_on_real_actions(pick_demos):
    buf = DemoBuffer.open(pick_demos)
    fitted = fit_tokenizers(buf, TokenizerFitConfig(action_type="bins", image_steps=2, image={"codebook_size": 16, "hidden_channels": 8, "embed_dim": 8}, proprio_bins=0), progress=False)
    actions = buffer_arrays(buf)["action"]
    norm = fitted.action.normalizer
    inside = ((norm.affine(actions).abs() <= 1).all(-1))
    with pytest.warns(ActionOutOfRangeWarning, match="outside the fitted range"):  # bins clip beyond the 1st/99th percentiles, and say so
        recon = round_trip(fitted.action, actions)
    err = (norm.affine(recon) - norm.affine(actions)).abs()[inside][:, :6]
    assert err.max() <= fitted.action.half_bin_width + 1e-5
    assert fitted.proprio is None
