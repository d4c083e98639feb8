"""The pretraining recipe run as users run it: a subprocess with the toy config and overrides."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings
from functools import partial
from pathlib import Path

import pytest
import torch

from checkpoint_checks import check_average_beside_own_weights, weights
from recipe_runs import check_error, errors_by_config, run_in_one_process
from script_loader import load_script
from mmada_rl.cli import main as cli_main
from mmada_rl.evaluation import load_actor
from mmada_rl.training.checkpoint import latest_checkpoint

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "pretrain" / "pretrain.py"


def run_recipe(*overrides, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(RECIPE), *map(str, overrides)], cwd=REPO, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def toy_run(toy_pretrain_run) -> Path:
    """Six toy steps with checkpoints at 3 and 6 and a one-episode evaluation at the end (conftest)."""
    return toy_pretrain_run


def test_toy_recipe_trains_logs_checkpoints_and_evaluates(toy_run):
    ckpts = sorted(p.name for p in (toy_run / "checkpoints").iterdir())
    assert ckpts == ["step_00000003", "step_00000006"]
    for name in ckpts:
        ckpt = toy_run / "checkpoints" / name
        assert (ckpt / "model" / "model.json").exists() and (ckpt / "trainer.pt").exists()
        config = json.loads((ckpt / "config.json").read_text())
        assert config["model"]["chunk_size"] == 5 and config["env"]["task"] == "PickCube-v1"
    history = json.loads((toy_run / "history.json").read_text())
    assert [h["step"] for h in history] == [1, 2, 3, 4, 5, 6]
    assert all(h["train/loss"] > 0 for h in history)
    final = json.loads((toy_run / "final.json").read_text())
    assert final["step"] == 6 and 0.0 <= final["eval/success_once"] <= 1.0
    assert (toy_run / "logs" / "scalars" / "train" / "loss_action.csv").exists()  # TorchRL CSV logger


def test_evaluation_at_the_end_is_recorded_episode_by_episode_for_pairing(toy_run):
    recorded = json.loads((toy_run / "final_eval" / "eval.json").read_text())  # mmada-rl eval's format
    final = json.loads((toy_run / "final.json").read_text())
    assert {k: v for k, v in recorded.items() if k.startswith("eval/")} == {k: v for k, v in final.items() if k != "step"}
    assert recorded["checkpoint"] == str(toy_run / "checkpoints" / "step_00000006") and recorded["own_weights"] is False
    assert [e["seed"] for e in recorded["per_episode"]] == recorded["seeds"] and len(recorded["seeds"]) == 1
    assert (toy_run / "final_eval" / "eval.md").read_text().startswith("PickCube-v1, 1 episodes")
    assert not (toy_run / "final_eval_raw").exists()  # no moving average kept: one set of weights evaluated

    paired = load_script("benchmarks/paired.py")
    episodes = paired.read_episodes(toy_run / "final_eval" / "eval.json")
    assert episodes["seeds"] == recorded["seeds"] and episodes["checkpoint"] == recorded["checkpoint"]
    assert episodes["success"] == [bool(final["eval/success_once"])]
    with pytest.raises(ValueError, match="final_eval/eval.json, its evaluation at the end"):
        paired.read_episodes(toy_run)  # the run directory: the message names the file to pair


def test_resume_continues_from_the_same_step_with_the_same_rng(toy_run, pick_demos, tmp_path):
    resumed = tmp_path / "resumed"
    (resumed / "checkpoints").mkdir(parents=True)
    shutil.copytree(toy_run / "checkpoints" / "step_00000003", resumed / "checkpoints" / "step_00000003")
    args = (f"run_dir={resumed}", f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=6",
            "checkpoint.interval=3", "checkpoint.keep=5", "logger.log_interval=1", "num_threads=1",
            "eval.episodes=0", f"tokenizers.dir={toy_run / 'tokenizers'}")
    fresh = run_recipe(*args)  # without checkpoint.resume a run there would overwrite the checkpoints: refused
    assert fresh.returncode != 0
    assert (f"run_dir={resumed} already holds a run's checkpoints (newest: step_00000003)" in fresh.stderr
            and "checkpoint.resume=true" in fresh.stderr)
    # refused before anything was written, Hydra's .hydra/ record and log file included (RunDirGuard)
    assert [p.name for p in resumed.iterdir()] == ["checkpoints"]
    assert [p.name for p in (resumed / "checkpoints").iterdir()] == ["step_00000003"]
    proc = run_recipe(*args, "checkpoint.resume=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resumed from" in proc.stdout and "at step 3" in proc.stdout
    history = json.loads((resumed / "history.json").read_text())
    assert [h["step"] for h in history] == [1, 2, 3, 4, 5, 6]  # the rows before the checkpoint came back with it
    original = json.loads((toy_run / "history.json").read_text())
    for a, b in zip(history, original):  # same batches, same noise, same updates
        assert a["train/loss"] == pytest.approx(b["train/loss"], rel=1e-5)
    w_resumed, w_original = weights(resumed / "checkpoints" / "step_00000006"), weights(toy_run / "checkpoints" / "step_00000006")
    for key in w_original:
        torch.testing.assert_close(w_resumed[key], w_original[key], rtol=1e-5, atol=1e-6)


def test_a_fresh_run_warns_of_an_earlier_runs_logs_in_its_run_dir(tmp_path):
    from omegaconf import OmegaConf

    from mmada_rl.training import start_run

    cfg = OmegaConf.create({"run_dir": str(tmp_path / "run"), "seed": 0, "num_threads": 0,
                            "checkpoint": {"resume": None}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an empty or new run_dir: no warning
        assert start_run(cfg)[0] == tmp_path / "run"
    (tmp_path / "run" / "logs" / "scalars").mkdir(parents=True)
    (tmp_path / "run" / "logs" / "scalars" / "loss.csv").write_text("1,0.5\n")  # a run stopped before a checkpoint
    with pytest.warns(UserWarning, match="holds the logs of an earlier run that saved no checkpoint"):
        start_run(cfg)


def test_a_fork_continues_the_checkpoint_with_its_own_draws_and_forks_average_into_one_policy(toy_run, pick_demos,
                                                                                              tmp_path):
    fork = tmp_path / "fork"  # from the toy run's step 3, with seed 1's draws instead of the checkpoint's RNG
    proc = run_recipe(f"run_dir={fork}", f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=6",
                      "checkpoint.interval=3", "checkpoint.keep=5", "logger.log_interval=1", "num_threads=1",
                      "eval.episodes=0", f"tokenizers.dir={toy_run / 'tokenizers'}", "seed=1",
                      f"checkpoint.resume={toy_run / 'checkpoints' / 'step_00000003'}", "checkpoint.restore_rng=false")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "at step 3 with this run's seed 1 (a fork)" in proc.stdout
    assert sorted(p.name for p in (fork / "checkpoints").iterdir()) == ["step_00000006"]  # its own run directory
    history, original = (json.loads((run / "history.json").read_text()) for run in (fork, toy_run))
    assert [h["step"] for h in history] == [1, 2, 3, 4, 5, 6]
    assert [h["train/loss"] for h in history[:3]] == [h["train/loss"] for h in original[:3]]  # the checkpoint's rows
    assert all(a["train/loss"] != b["train/loss"] for a, b in zip(history[3:], original[3:]))  # other batches and noise
    base, forked = weights(toy_run / "checkpoints" / "step_00000006"), weights(fork / "checkpoints" / "step_00000006")
    assert any(not torch.equal(base[key], forked[key]) for key in base)

    # the two continuations averaged into one policy that evaluation loads
    soup = tmp_path / "soup"
    assert cli_main(["average", "--checkpoint", str(toy_run), str(fork), "--out", str(soup)]) == 0
    members = json.loads((soup / "average.json").read_text())["members"]
    assert members == [str(run / "checkpoints" / "step_00000006" / "model") for run in (toy_run, fork)]
    policy = load_actor(soup).model
    for key, value in policy.denoiser.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value, (base[key] + forked[key]) / 2, rtol=1e-6, atol=1e-7)
        else:
            assert torch.equal(value, base[key])
    out = tmp_path / "eval_soup"
    assert cli_main(["eval", "--checkpoint", str(soup), "--task", "PickCube-v1", "--episodes", "1",
                     "--max-episode-steps", "4", "--no-progress", "--out", str(out)]) == 0
    assert json.loads((out / "eval.json").read_text())["per_episode"][0]["steps"] == 4
    seeds = load_script("benchmarks/seeds.py")  # the seeds report names the members' training seeds
    assert seeds.main(["--group", "soup", str(out / "eval.json"), "--name", "soup", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "soup.json").read_text())["groups"][0]["seeds"][0]["seed"] == "0+1 averaged"

    # policies read through other tokenizers, or one policy alone, are refused with a clear message
    other = shutil.copytree(fork / "checkpoints" / "step_00000006" / "model", tmp_path / "other" / "model")
    bins = next(p for p in sorted((other / "tokenizers").rglob("*")) if p.is_file())
    bins.write_bytes(bins.read_bytes() + b" ")
    with pytest.raises(SystemExit, match="was trained with other tokenizers than"):
        cli_main(["average", "--checkpoint", str(toy_run), str(other), "--out", str(tmp_path / "bad")])
    with pytest.raises(SystemExit, match="give two or more --checkpoint paths"):
        cli_main(["average", "--checkpoint", str(toy_run), "--out", str(tmp_path / "bad")])


def test_weight_average_is_evaluated_and_saved_beside_the_unchanged_training_and_resumes(toy_run, pick_demos, tmp_path):
    common = [f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=6", "checkpoint.interval=3",
              "checkpoint.keep=5", "logger.log_interval=1", "num_threads=1", "ema.enabled=true"]
    averaged = tmp_path / "ema"  # the toy run's overrides (it fits its tokenizers too), keeping an average
    proc = run_recipe(f"run_dir={averaged}", *common, "ema.evaluate_raw=true", "eval.episodes=1", "eval.max_episode_steps=10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    final = json.loads((averaged / "final.json").read_text())
    assert 0.0 <= final["eval/success_once"] <= 1.0 and 0.0 <= final["eval_raw/success_once"] <= 1.0
    history = json.loads((averaged / "history.json").read_text())
    assert [h["train/ema_decay"] for h in history][:2] == [0.0, pytest.approx(1 - 2 ** -0.75)]
    original = json.loads((toy_run / "history.json").read_text())
    for a, b in zip(history, original):  # keeping an average does not change training
        assert a["train/loss"] == pytest.approx(b["train/loss"], rel=1e-5)
    # the checkpoint's own weights are the plain run's; its model is their average
    own, saved = check_average_beside_own_weights(averaged / "checkpoints" / "step_00000006",
                                                  toy_run / "checkpoints" / "step_00000006", updates=6)

    # the seeds report reads either evaluation: RUN the average's, RUN@raw (or RUN@STEP@raw) the own weights'
    seeds = load_script("benchmarks/seeds.py")
    assert seeds.main(["--group", "average", str(averaged), "--group", "own", f"{averaged}@raw", f"{averaged}@6@raw",
                       "--name", "ema", "--out", str(tmp_path)]) == 0
    average, own_rows = json.loads((tmp_path / "ema.json").read_text())["groups"]
    assert average["seeds"][0]["success_once"] == final["eval/success_once"]
    assert [r["success_once"] for r in own_rows["seeds"]] == [final["eval_raw/success_once"]] * 2
    assert [r["step"] for r in own_rows["seeds"]] == [6, 6] and own_rows["seeds"][1]["source"] == f"{averaged}@6@raw"
    for flag in ("is_grasped", "is_obj_placed"):  # the stages logged with each evaluation
        assert average["reached"][flag]["rate"] == final[f"eval/reached/{flag}"]
        assert own_rows["reached"][flag]["rate"] == final[f"eval_raw/reached/{flag}"]
    # both evaluations at the end are recorded episode by episode, the own weights' marked as such
    for name, prefix, own_weights in (("final_eval", "eval/", False), ("final_eval_raw", "eval_raw/", True)):
        recorded = json.loads((averaged / name / "eval.json").read_text())
        assert recorded["own_weights"] is own_weights and recorded["eval/success_once"] == final[f"{prefix}success_once"]
        assert recorded["checkpoint"] == str(averaged / "checkpoints" / "step_00000006")
    with pytest.raises(ValueError, match=r"eval_raw/success_once.csv is missing or empty\) \(a pretraining run logs it"):
        seeds.main(["--group", "plain", f"{toy_run}@raw", "--out", str(tmp_path)])

    # evaluation loads the average by default, the own weights with own_weights (--own-weights), every member's
    for policy, expected in ((load_actor(averaged).model, saved), (load_actor(averaged, own_weights=True).model,
                                                                    own["train_weights"])):
        for key, value in policy.denoiser.state_dict().items():
            torch.testing.assert_close(value, expected[key], rtol=0, atol=0)
    pair = load_actor([averaged, averaged / "checkpoints" / "step_00000003"], own_weights=True).model
    third = torch.load(averaged / "checkpoints" / "step_00000003" / "trainer.pt", weights_only=False)["extra"]
    for member, expected in zip(pair.members, (own["train_weights"], third["train_weights"])):
        for key, value in member.denoiser.state_dict().items():
            torch.testing.assert_close(value, expected[key], rtol=0, atol=0)
    out = tmp_path / "eval_own"
    assert cli_main(["eval", "--checkpoint", str(averaged), "--own-weights", "--task", "PickCube-v1", "--episodes", "1",
                     "--max-episode-steps", "4", "--no-progress", "--out", str(out)]) == 0
    saved_eval = json.loads((out / "eval.json").read_text())
    assert saved_eval["own_weights"] is True and saved_eval["per_episode"][0]["steps"] == 4
    assert "the own weights beside the moving average" in (out / "eval.md").read_text()
    with pytest.raises(ValueError, match="kept no moving average of its weights"):  # a run without one
        load_actor(toy_run, own_weights=True)
    with pytest.raises(FileNotFoundError, match="is no training checkpoint"):  # a model directory outside a checkpoint
        load_actor(shutil.copytree(averaged / "checkpoints" / "step_00000006" / "model", tmp_path / "exported" / "model"),
                   own_weights=True)

    resumed = tmp_path / "resumed"  # from step 3: both the average and the own weights continue exactly
    (resumed / "checkpoints").mkdir(parents=True)
    shutil.copytree(averaged / "checkpoints" / "step_00000003", resumed / "checkpoints" / "step_00000003")
    proc = run_recipe(f"run_dir={resumed}", *common, f"tokenizers.dir={averaged / 'tokenizers'}", "eval.episodes=0",
                      "checkpoint.resume=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = resumed / "checkpoints" / "step_00000006"
    own_again = torch.load(again / "trainer.pt", weights_only=False)["extra"]
    assert own_again["ema_updates"] == 6
    for key in saved:
        torch.testing.assert_close(weights(again)[key], saved[key], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(own_again["train_weights"][key], own["train_weights"][key], rtol=1e-5, atol=1e-6)


BAD_CONFIGS = [
    (["model.chunk_size=500"], "chunk_size=500 is longer than every episode"),
    (["env.image_size=32"], "image_size=64 but 32 was asked for"),
    (["env.task=PickBanana-v9"], "Unknown task 'PickBanana-v9'"),
    (["loss.corruptions_per_sample=0"], "corruptions_per_sample must be a positive integer, got 0"),
    (["loss.action_label_sigma=0.75"], "needs ordered bin tokens (tokenizers.action_type=bins)"),
    (["loss.action_mean_weight=1"], "loss.action_mean_weight=1.0 scores the expected bin of each action token, "
                                    "so it needs ordered bin tokens"),
    (["data.skip_grasp_hold=0.05", "data.grasp_hold_gripper_only=true"],
     "data.grasp_hold_gripper_only scores the gripper's token of each action, so it needs ordered bin tokens"),
    (["loss.full_mask_prob=1.5"], "loss.full_mask_prob must lie in [0, 1], got 1.5"),
    (["replay_buffer.random_shift=-2"], "replay_buffer.random_shift=-2 must be a whole number of pixels"),
    (["model.action_readout=mean"], "action_readout='mean' reads each action token's expected bin, so it needs ordered "
                                      "bin tokens (tokenizers.action_type=bins), not a VQActionTokenizer"),
    (["model.state_differences=[[26,19]]"], "covers 29 dimensions, not the demonstrations' 29 plus the 1 of "
                                            "model.state_differences=[[26, 19]]"),
    (["model.visual_encoder_freeze=true"], "model.visual_encoder_freeze=true fixes a CNN copied from "
                                           "model.visual_encoder_init"),
    (["model.visual_encoder_init=runs/bc"], "copies a CNN into the denoiser's own, which it does not have"),
    (["optim.precision=fp16"], "precision must be one of fp32, bf16, got 'fp16'"),
]


def bad_config_run(pick_demos: Path, toy_run: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    """The toy recipe on ``pick_demos`` with ``toy_run``'s tokenizers, one step, no evaluation, and ``overrides``."""
    return [f"run_dir={run_dir}", f"data.dir={pick_demos}", "data.collect_episodes=0",
            f"tokenizers.dir={toy_run / 'tokenizers'}", "optim.total_steps=1", "eval.episodes=0", *overrides]


@pytest.fixture(scope="module")
def bad_config_errors(pick_demos, toy_run, tmp_path_factory) -> dict[str, str | None]:
    """The error the recipe ends each of ``BAD_CONFIGS`` with, all run in one process (tests/recipe_runs.py)."""
    return errors_by_config(RECIPE, BAD_CONFIGS, partial(bad_config_run, pick_demos, toy_run),
                            tmp_path_factory.mktemp("bad_configs"))


@pytest.mark.parametrize("overrides, message", BAD_CONFIGS)
def test_bad_configs_fail_with_one_clear_error(bad_config_errors, overrides, message):
    check_error(bad_config_errors, overrides, message)


def test_a_bad_config_on_the_command_line_exits_with_its_message(pick_demos, toy_run, tmp_path):
    overrides, message = BAD_CONFIGS[0]
    proc = run_recipe(*bad_config_run(pick_demos, toy_run, tmp_path / "bad", overrides))
    assert proc.returncode != 0 and message in proc.stderr


def test_binning_action_tokens_by_config_alone(pick_demos, tmp_path):
    """The VQ-vs-bins ablation: ``tokenizers.action_type=bins`` with the bins' own options (and their Gaussian
    targets, ``loss.action_label_sigma``, the L1 error of their expected bin, ``loss.action_mean_weight``, the
    mean read-out of greedy chunks, ``model.action_readout``, and the grasp hold's windows scored on the gripper
    alone, ``data.grasp_hold_gripper_only``)."""
    run_dir = tmp_path / "bins"
    proc = run_recipe(f"run_dir={run_dir}", f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=2",
                      "eval.episodes=0", "tokenizers.action_type=bins", "tokenizers.action.bins.num_bins=32",
                      "loss.action_label_sigma=0.75", "loss.action_mean_weight=1.0", "model.action_readout=mean",
                      "data.skip_grasp_hold=0.05", "data.grasp_hold_gripper_only=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    config = json.loads((run_dir / "tokenizers" / "action" / "config.json").read_text())
    assert config["type"] == "UniformBinActionTokenizer" and config["config"]["num_bins"] == 32
    saved = json.loads((latest_checkpoint(run_dir) / "model" / "model.json").read_text())
    assert saved["config"]["action_readout"] == "mean"  # the saved policy reads its greedy chunks out by their mean
    assert (run_dir / "logs" / "scalars" / "train" / "loss_action_mean.csv").exists()  # trained and logged


def test_state_differences_are_fitted_and_read_by_config_alone(pick_demos, tmp_path):
    """``model.state_differences``: the recipe fits the proprio tokenizer on the state with the differences
    appended, the saved policy reads them, and state dropout can keep them readable."""
    run_dir = tmp_path / "relative"
    proc = run_recipe(f"run_dir={run_dir}", f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=2",
                      "eval.episodes=0", "model.state_differences=[[26,19],[27,20],[28,21]]",
                      "loss.proprio_drop_prob=0.5", "loss.proprio_drop_keep_dims=[26,27,28,29,30,31]")
    assert proc.returncode == 0, proc.stderr[-3000:]
    proprio = json.loads((run_dir / "tokenizers" / "proprio" / "config.json").read_text())
    assert proprio["config"]["action_dim"] == 32
    saved = json.loads((latest_checkpoint(run_dir) / "model" / "model.json").read_text())
    assert saved["config"]["state_differences"] == [[26, 19], [27, 20], [28, 21]]


def test_state_dropout_can_keep_the_goal_position_readable(toy_run):
    """``loss.proprio_drop_keep_dims``: state dropout masks every proprio token but those of the named state
    dimensions (PickCube-v1's goal position, which the camera does not show); misuse fails with a clear error."""
    from omegaconf import OmegaConf

    from mmada_rl.policy import MMaDAModel

    utils = load_script("recipes/pretrain/utils.py", "pretrain_utils")
    cfg = OmegaConf.load(REPO / "recipes" / "pretrain" / "config" / "toy.yaml")
    model = MMaDAModel.load(latest_checkpoint(toy_run) / "model")
    assert model.layout.config.proprio_tokens == 29
    cfg.loss.proprio_drop_prob = 0.3
    assert utils.make_loss(cfg, model).proprio_drop_index is None  # the whole segment by default
    cfg.loss.proprio_drop_keep_dims = [26, 27, 28]
    assert utils.make_loss(cfg, model).proprio_drop_index.tolist() == list(range(26))
    cfg.loss.proprio_drop_keep_dims = list(range(29))
    with pytest.raises(ValueError, match="would mask nothing"):
        utils.make_loss(cfg, model)
    cfg.loss.proprio_drop_keep_dims, cfg.loss.proprio_drop_prob = [26], 0.0
    with pytest.raises(ValueError, match="it is off"):
        utils.make_loss(cfg, model)


def test_random_shift_option_shifts_the_recipes_training_windows(pick_demos):
    """``replay_buffer.random_shift``: the recipe's windows are the plain ones, images shifted
    (how: tests/test_data.py, one offset per window for the observation and its goal frame)."""
    from omegaconf import OmegaConf

    from mmada_rl.keys import ACTION_CHUNK_KEY, GOAL_IMAGE_KEY, IMAGE_KEY, STATE_KEY

    utils = load_script("recipes/pretrain/utils.py", "pretrain_utils")
    cfg = OmegaConf.load(REPO / "recipes" / "pretrain" / "config" / "toy.yaml")
    cfg.data.dir, cfg.data.collect_episodes = str(pick_demos), 0
    buffers = utils.make_demo_buffers(cfg)
    plain = utils.make_data(cfg, buffers).sample()
    cfg.replay_buffer.random_shift = 4
    shifted = utils.make_data(cfg, buffers).sample()  # the same sampler seed: the same windows
    for key in (ACTION_CHUNK_KEY, STATE_KEY):
        torch.testing.assert_close(shifted[key], plain[key])
    for key in (IMAGE_KEY, GOAL_IMAGE_KEY):
        moved = [not torch.equal(a, b) for a, b in zip(shifted[key], plain[key])]
        assert sum(moved) >= len(moved) // 2  # 1 offset in 81 leaves a window in place


def test_window_skips_reach_the_pretraining_and_imitation_samplers(pick_demos):
    """``data.skip_*`` of the pretraining and imitation recipes become their samplers' no-start steps."""
    from omegaconf import OmegaConf

    from mmada_rl.data import DemoBuffer
    from mmada_rl.data.windows import no_start_steps

    expected = no_start_steps(DemoBuffer.open(pick_demos), skip_pauses=0.01, skip_grasp_hold=0.05)
    assert expected.any() and not expected.all()
    for recipe in ("pretrain", "baselines"):
        utils = load_script(f"recipes/{recipe}/utils.py", f"{recipe}_utils_skips")
        cfg = OmegaConf.load(REPO / "recipes" / recipe / "config" / "toy.yaml")
        assert cfg.data.skip_grasp_hold == 0.0 and cfg.data.skip_pauses == 0.0  # off by default
        cfg.data.dir, cfg.data.collect_episodes = str(pick_demos), 0
        cfg.data.skip_pauses, cfg.data.skip_grasp_hold = 0.01, 0.05
        data = utils.make_data(cfg, utils.make_demo_buffers(cfg) if recipe == "pretrain" else DemoBuffer.open(pick_demos))
        torch.testing.assert_close(data.sampler.no_start, expected)


def test_cpu_config_shortens_the_sequence_and_trains(pick_demos, tmp_path):
    """``--config-name maniskill_cpu``: the goal image as 4x4 codes, the observation through the CNN alone,
    no joint velocities, a denoiser of width 128; it composes, fits its tokenizers and trains."""
    run_dir = tmp_path / "cpu"
    proc = run_recipe("--config-name", "maniskill_cpu", f"run_dir={run_dir}", f"data.dir={pick_demos}",
                      "data.collect_episodes=0", "optim.total_steps=2", "optim.warmup_steps=1", "eval.episodes=0",
                      "tokenizers.image_steps=2", "tokenizers.action_steps=2", "replay_buffer.batch_size=4",
                      "checkpoint.interval=2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    image = json.loads((run_dir / "tokenizers" / "image" / "config.json").read_text())
    assert image["config"]["grid_size"] == 4
    saved = json.loads((latest_checkpoint(run_dir) / "model" / "model.json").read_text())["config"]
    assert saved["observation_tokens"] is False and saved["proprio_drop_dims"] == list(range(9, 18))
    assert saved["denoiser_overrides"]["d_model"] == 128
    assert "sequence length 92;" in proc.stdout  # 214 with maniskill.yaml's layout (benchmarks/train_throughput.py)


def test_bf16_forward_pass_trains_and_saves_float32_weights(toy_run, pick_demos, tmp_path):
    """``optim.precision=bf16``: the recipe trains with its forward pass under autocast to bfloat16, its losses
    those of the same run in float32 (same seed: same windows and masks) to bfloat16's precision; the
    optimizer's weights, hence the saved policy's, stay float32."""
    precisions = ("fp32", "bf16")
    runs = run_in_one_process(RECIPE, [[f"run_dir={tmp_path / precision}", f"data.dir={pick_demos}", "data.collect_episodes=0",
                                        "optim.total_steps=3", "logger.log_interval=1", "num_threads=1", "eval.episodes=0",
                                        f"tokenizers.dir={toy_run / 'tokenizers'}", f"optim.precision={precision}"]
                                       for precision in precisions])
    histories = {}
    for precision, proc in zip(precisions, runs):
        assert proc.returncode == 0, proc.stderr[-3000:]
        histories[precision] = json.loads((tmp_path / precision / "history.json").read_text())
    assert [h["step"] for h in histories["bf16"]] == [1, 2, 3]
    for low, exact in zip(histories["bf16"], histories["fp32"]):
        assert low["train/loss"] == pytest.approx(exact["train/loss"], rel=0.02)
        assert low["train/loss"] != exact["train/loss"]  # computed in bfloat16 indeed
    saved = weights(latest_checkpoint(tmp_path / "bf16"))
    assert saved and all(w.dtype == torch.float32 for w in saved.values())


def test_held_out_demonstrations_are_scored_while_training(toy_run, pick_demos, push_demos, tmp_path):
    """``validation.dir``: every ``validation.interval`` steps and at the end, the saved weights' scores on fixed
    windows of a held-out buffer (``val/...``: masked-token scores, greedy chunk error) are logged; a buffer of
    another task fails with one clear error."""
    run_dir = tmp_path / "val"
    common = [f"data.dir={pick_demos}", "data.collect_episodes=0", f"tokenizers.dir={toy_run / 'tokenizers'}",
              "eval.episodes=0", "logger.log_interval=5"]
    proc, other_task = run_in_one_process(RECIPE, [
        [f"run_dir={run_dir}", *common, "optim.total_steps=3", f"validation.dir={pick_demos}", "validation.interval=2",
         "validation.minibatches=1", "validation.batch_size=2"],
        [f"run_dir={tmp_path / 'bad'}", *common, "optim.total_steps=1", f"validation.dir={push_demos}"]])
    assert proc.returncode == 0, proc.stderr[-3000:]
    history = {row["step"]: row for row in json.loads((run_dir / "history.json").read_text())}
    assert set(history) == {2, 3}  # the report at step 2 is logged although 2 is not a logging step
    final = json.loads((run_dir / "final.json").read_text())
    for scores in (history[2], final):
        assert scores["val/chunk_mae"] > 0 and 0 <= scores["val/action_accuracy"] <= 1
        assert scores["val/loss_action"] > 0 and "val/loss_goal" in scores
    assert (run_dir / "logs" / "scalars" / "val" / "chunk_mae.csv").read_text().count("\n") == 2  # steps 2 and 3
    assert other_task.returncode != 0 and "PushCube-v1" in other_task.error and "PickCube-v1" in other_task.error


@pytest.mark.parametrize("config, task, fov, width", [("pickcube_cpu", "PickCube-v1", 45, 256),
                                                     ("pushcube_cpu", "PushCube-v1", 60, 128)])
def test_task_configs_hold_the_recipe_of_their_figures(config, task, fov, width):
    """``pickcube_cpu.yaml`` and ``pushcube_cpu.yaml`` are ``maniskill_cpu.yaml`` with the options of the
    README's PickCube-v1 (0.70) and PushCube-v1 (0.93) runs: 100 DART demonstrations through the task's camera,
    state dropout, the mean read-out of one pass, 5000 steps."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "recipes" / "pretrain" / "config"), version_base=None):
        cfg, base = compose(config_name=config), compose(config_name="maniskill_cpu")
    assert (cfg.env.task, cfg.env.camera_fov, cfg.model.denoiser_overrides.d_model) == (task, fov, width)
    assert (cfg.data.collect_episodes, cfg.data.action_noise, cfg.data.dir) == (100, 0.1, f"data/dart/{task}-fov{fov}")
    assert (cfg.model.action_readout, cfg.model.num_denoise_steps, cfg.loss.proprio_drop_prob) == ("mean", 1, 0.3)
    assert cfg.optim.total_steps == 5000 and base.data.action_noise == 0.0  # planner demonstrations without noise by default
    assert (cfg.tokenizers, cfg.optim.lr, cfg.replay_buffer) == (base.tokenizers, base.optim.lr, base.replay_buffer)


def test_multitask_config_collects_each_tasks_dart_buffer():
    """``multitask_cpu.yaml`` reads (and, when missing, collects) the per-task configs' DART buffers, each through
    its task's camera, so one command runs on a fresh machine."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "recipes" / "pretrain" / "config"), version_base=None):
        cfg = compose(config_name="multitask_cpu")
        per_task = {c.env.task: c for c in (compose(config_name="pickcube_cpu"), compose(config_name="pushcube_cpu"))}
    assert (cfg.data.collect_episodes, cfg.data.action_noise) == (100, 0.1)
    assert list(cfg.tasks) == list(cfg.data.dir) == list(cfg.env.camera_fov)
    for task, c in per_task.items():
        assert (cfg.data.dir[task], cfg.env.camera_fov[task]) == (c.data.dir, c.env.camera_fov)
        assert (cfg.data.collect_episodes, cfg.data.action_noise) == (c.data.collect_episodes, c.data.action_noise)
    assert (cfg.data.dir["StackCube-v1"], cfg.env.camera_fov["StackCube-v1"]) == ("data/dart/StackCube-v1-fov45", 45)


def test_pickcube_config_collects_dart_demonstrations_and_trains(tmp_path):
    """``--config-name pickcube_cpu`` end to end, shortened: the missing buffer is collected with the DART noise
    through the 45° camera (by two worker processes), the goal offsets enter the proprio tokenizer, and the saved policy holds the recipe."""
    from mmada_rl.data import DemoBuffer

    run_dir, demos = tmp_path / "run", tmp_path / "demos"
    proc = run_recipe("--config-name", "pickcube_cpu", f"run_dir={run_dir}", f"data.dir={demos}", "data.collect_episodes=1",
                      "data.collect_workers=2",
                      "optim.total_steps=2", "optim.warmup_steps=1", "eval.episodes=0", "tokenizers.image_steps=2",
                      "tokenizers.action_steps=2", "replay_buffer.batch_size=4", "checkpoint.interval=2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"collecting 1 planner demonstrations (DART action noise 0.1) into {demos} (2 processes side by side)" in proc.stdout
    meta = DemoBuffer.open(demos).metadata
    assert (meta.num_episodes, meta.action_noise, meta.camera_fov) == (1, 0.1, 45)
    saved = json.loads((latest_checkpoint(run_dir) / "model" / "model.json").read_text())["config"]
    assert saved["state_differences"] == [[26, 19], [27, 20], [28, 21]] and saved["action_readout"] == "mean"
    assert saved["denoiser_overrides"]["d_model"] == 256
    assert saved["denoiser_overrides"]["visual_encoder_channels"] == [32, 64, 128, 128]
