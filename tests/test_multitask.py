"""One model on several tasks: mixed chunk windows, tokenizers fitted on every task, the recipe end to end."""
from __future__ import annotations

import json
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest
import torch

from mmada_rl.data import DemoBuffer, MultiTaskWindows, RandomShift, pad_state
from mmada_rl.keys import GOAL_IMAGE_KEY, IMAGE_KEY, STATE_KEY, TASK_INDEX_KEY
from mmada_rl.policy.model import instructions_of
from mmada_rl.tokenizers.from_buffer import TokenizerFitConfig, fit_tokenizers
from recipe_runs import check_error, errors_by_config
from script_loader import load_script

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "pretrain" / "pretrain.py"


@pytest.fixture(scope="module")
def buffers(pick_demos, push_demos) -> list[DemoBuffer]:
    return [DemoBuffer.open(pick_demos), DemoBuffer.open(push_demos)]


def test_state_sizes_differ_between_tasks(buffers):
    # PickCube's observation adds the goal position and a grasp flag: the reason states are padded
    pick, push = (b.metadata.state_dim for b in buffers)
    assert pick > push


def test_batches_mix_tasks_with_their_own_instructions_and_padded_states(buffers):
    windows = MultiTaskWindows(buffers, chunk_size=5, batch_size=64, seed=0)
    batch = windows.sample()
    assert batch.shape == (64,)
    tasks = batch.get(TASK_INDEX_KEY)
    assert set(tasks.tolist()) == {0, 1}
    assert batch.get(STATE_KEY).shape == (64, max(b.metadata.state_dim for b in buffers))
    texts = instructions_of(batch)  # what the model reads
    for i, b in enumerate(buffers):
        assert {texts[j] for j in torch.nonzero(tasks == i).flatten().tolist()} == set(b.metadata.instructions)
    push_states = batch.get(STATE_KEY)[tasks == 1]
    assert (push_states[:, buffers[1].metadata.state_dim:] == 0).all()


def test_task_weights_set_the_mix(buffers):
    counts = torch.zeros(2)
    windows = MultiTaskWindows(buffers, chunk_size=5, batch_size=50, weights=[3.0, 1.0], seed=1)
    for _ in range(8):
        counts += torch.bincount(windows.sample().get(TASK_INDEX_KEY), minlength=2)
    assert counts[0] / counts.sum() == pytest.approx(0.75, abs=0.08)
    only_push = MultiTaskWindows(buffers, chunk_size=5, batch_size=20, weights=[0.0, 1.0], seed=1).sample()
    assert (only_push.get(TASK_INDEX_KEY) == 1).all()


def test_same_seed_same_batches(buffers):
    a = MultiTaskWindows(buffers, chunk_size=5, batch_size=16, seed=3).sample()
    b = MultiTaskWindows(buffers, chunk_size=5, batch_size=16, seed=3).sample()
    assert torch.equal(a.get(TASK_INDEX_KEY), b.get(TASK_INDEX_KEY)) and torch.equal(a.get(STATE_KEY), b.get(STATE_KEY))


def test_a_transform_appended_to_the_mix_reaches_every_task(buffers):
    plain = MultiTaskWindows(buffers, chunk_size=5, batch_size=16, seed=3).sample()
    windows = MultiTaskWindows(buffers, chunk_size=5, batch_size=16, seed=3)
    windows.append_transform(RandomShift(4, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY]))
    shifted = windows.sample()  # the same windows, images shifted
    tasks = shifted.get(TASK_INDEX_KEY)
    assert torch.equal(tasks, plain.get(TASK_INDEX_KEY)) and torch.equal(shifted.get(STATE_KEY), plain.get(STATE_KEY))
    moved = torch.tensor([not torch.equal(a, b) for a, b in zip(shifted.get(IMAGE_KEY), plain.get(IMAGE_KEY))])
    for i in range(len(buffers)):
        assert moved[tasks == i].any()


@pytest.mark.parametrize("weights", [[1.0], [0.0, 0.0], [-1.0, 2.0], "balanced"])
def test_bad_task_weights_are_refused(buffers, weights):
    with pytest.raises(ValueError, match="weight"):
        MultiTaskWindows(buffers, chunk_size=5, batch_size=8, weights=weights)


def test_pad_state_refuses_a_larger_state():
    assert pad_state(torch.ones(2, 3), 5).tolist() == [[1, 1, 1, 0, 0]] * 2
    with pytest.raises(ValueError, match="more than the 2"):
        pad_state(torch.ones(3), 2)


def test_tokenizers_fitted_on_every_task(buffers):
    cfg = TokenizerFitConfig(action_type="bins", action={"num_bins": 32}, image_steps=2, proprio_bins=8,
                             image={"codebook_size": 16, "hidden_channels": 8, "embed_dim": 8})
    fitted = fit_tokenizers(buffers, cfg, progress=False)
    assert fitted.proprio.config.action_dim == max(b.metadata.state_dim for b in buffers)
    for b in buffers:  # one word vocabulary covers every task's instruction
        assert "[UNK]" not in fitted.text.decode(fitted.text.encode(b.metadata.instructions).ids)[0]
    # the shared action bins are fitted on both tasks' actions: their data range is the union of the two
    union = torch.cat([b.storage[: len(b)].get("action") for b in buffers])
    torch.testing.assert_close(fitted.action.normalizer.data_min, union.min(0).values)
    torch.testing.assert_close(fitted.action.normalizer.data_max, union.max(0).values)


@pytest.fixture(scope="module")
def push_demos_fov60(tmp_path_factory) -> Path:
    """One PushCube-v1 planner demonstration through a 60° camera."""
    from mmada_rl.data.collect import collect
    from mmada_rl.envs.maniskill import EnvConfig

    out = tmp_path_factory.mktemp("demos60") / "PushCube-v1-fov60"
    assert collect(out, EnvConfig(task="PushCube-v1", camera_fov=60), episodes=1, progress=False).new_episodes == 1
    return out


@pytest.fixture(scope="module")
def multitask_run(pick_demos, push_demos_fov60, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """Three toy steps of one model on PickCube-v1 (the task's own camera) and PushCube-v1 (a 60° camera),
    each task's buffer and camera named in a mapping (no window in the planners' leading hold; a
    foreground-weighted image tokenizer; no joint velocities in the sequence), a one-episode evaluation
    of each task."""
    run_dir = tmp_path_factory.mktemp("multitask") / "multi"
    proc = subprocess.run(
        [sys.executable, str(RECIPE), f"run_dir={run_dir}", "tasks=[PickCube-v1,PushCube-v1]",
         f"data.dir={{PickCube-v1: '{pick_demos}', PushCube-v1: '{push_demos_fov60}'}}",
         "env.camera_fov={PickCube-v1: null, PushCube-v1: 60}", "data.collect_episodes=0", "optim.total_steps=3",
         "checkpoint.interval=3", "eval.episodes=1", "eval.max_episode_steps=5", "num_threads=1",
         "data.skip_idle_start=true",  # the option end to end (its effect: tests/test_data.py)
         "tokenizers.image.foreground_weight=5",  # likewise (its effect: tests/test_tokenizers.py)
         "model.proprio_drop_dims=[9,10,11,12,13,14,15,16,17]"],  # likewise (tests/test_actor.py)
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir, proc


def test_multitask_recipe_trains_and_evaluates_each_task(multitask_run):
    run_dir, proc = multitask_run
    assert "PickCube-v1: 2 demos" in proc.stdout and "PushCube-v1: 1 demos" in proc.stdout
    final = json.loads((run_dir / "final.json").read_text())
    for task in ("PickCube-v1", "PushCube-v1"):
        assert final[f"eval/{task}/episodes"] == 1 and final[f"eval/{task}/episode_length"] == 5
    mean = (final["eval/PickCube-v1/success_once"] + final["eval/PushCube-v1/success_once"]) / 2
    assert final["eval/success_once"] == pytest.approx(mean)
    for task in ("PickCube-v1", "PushCube-v1"):  # each task's evaluation at the end, episode by episode
        recorded = json.loads((run_dir / "final_eval" / task / "eval.json").read_text())
        assert recorded["task"] == task and len(recorded["per_episode"]) == 1
        assert recorded["eval/success_once"] == final[f"eval/{task}/success_once"]
    config = json.loads((run_dir / "checkpoints" / "step_00000003" / "config.json").read_text())
    assert config["tasks"] == ["PickCube-v1", "PushCube-v1"]
    model = json.loads((run_dir / "checkpoints" / "step_00000003" / "model" / "model.json").read_text())
    assert model["config"]["proprio_drop_dims"] == list(range(9, 18))
    assert model["layout"]["layout"]["proprio_tokens"] == 29 - 9  # PickCube's state, the larger of the two


def test_multitask_model_keeps_each_tasks_camera(multitask_run):
    from mmada_rl.evaluation import eval_env_config, load_actor

    run_dir, _ = multitask_run
    actor = load_actor(run_dir / "checkpoints" / "step_00000003")
    assert actor.model.config.camera_fov == {"PickCube-v1": None, "PushCube-v1": 60.0}
    assert eval_env_config(actor, "PushCube-v1").camera_fov == 60.0  # what the recipe's evaluation built
    assert eval_env_config(actor, "PickCube-v1").camera_fov is None
    with pytest.raises(ValueError, match="not of 'StackCube-v1'"):  # a task it has no camera for
        eval_env_config(actor, "StackCube-v1")


BAD_CONFIGS = [
    (["data.dir={demos}"], "put {task} in data.dir"),
    (["data.dir={{PickCube-v1: '{demos}'}}"], "data.dir gives the buffers of ['PickCube-v1'] but not of 'PushCube-v1'"),
    (["data.dir='{parent}/{{task}}'", "env.camera_fov={{PickCube-v1: null}}"],
     "camera_fov gives the cameras of ['PickCube-v1'] but not of 'PushCube-v1'"),
]


def bad_config_run(pick_demos: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    """Two tasks, ``overrides`` (``{demos}``: ``pick_demos``, ``{parent}``: its folder) naming their buffers and
    cameras, one step, no evaluation."""
    overrides = [o.format(demos=pick_demos, parent=pick_demos.parent) for o in overrides]
    return [f"run_dir={run_dir}", "tasks=[PickCube-v1,PushCube-v1]", *overrides, "data.collect_episodes=0",
            "optim.total_steps=1", "eval.episodes=0"]


@pytest.fixture(scope="module")
def bad_config_errors(pick_demos, push_demos, tmp_path_factory) -> dict[str, str | None]:
    """The error the recipe ends each of ``BAD_CONFIGS`` with, all run in one process (tests/recipe_runs.py)."""
    return errors_by_config(RECIPE, BAD_CONFIGS, partial(bad_config_run, pick_demos), tmp_path_factory.mktemp("bad_configs"))


@pytest.mark.parametrize("overrides, message", BAD_CONFIGS)
def test_multitask_bad_buffers_or_cameras_are_one_clear_error(bad_config_errors, overrides, message):
    check_error(bad_config_errors, overrides, message)


def test_a_bad_multitask_config_on_the_command_line_exits_with_its_message(pick_demos, push_demos, tmp_path):
    overrides, message = BAD_CONFIGS[0]
    proc = subprocess.run([sys.executable, str(RECIPE), *bad_config_run(pick_demos, tmp_path / "bad", overrides)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr[-2000:]


def test_pretraining_report_gives_one_row_per_task(multitask_run, toy_pretrain_run, tmp_path):
    bench = load_script("benchmarks/pretraining.py", "pretraining_benchmark")
    assert bench.main([str(multitask_run[0]), str(toy_pretrain_run), "--out", str(tmp_path)]) == 0
    report = (tmp_path / "pretraining.md").read_text()
    assert "PickCube-v1 (multi-task, 2 tasks)" in report and "PushCube-v1 (multi-task, 2 tasks)" in report
    assert "\n| PickCube-v1 | " in report  # the single-task toy run, which keeps the hold windows
    run, single = json.loads((tmp_path / "pretraining.json").read_text())["runs"]
    assert run["tasks"] == ["PickCube-v1", "PushCube-v1"]
    assert run["skip_idle_start"] and not single["skip_idle_start"]
    assert run["image_foreground_weight"] == 5.0 and single["image_foreground_weight"] == 1.0
    assert "| PushCube-v1 (multi-task, 2 tasks) (no window in the leading hold) (image foreground weight 5) |" in report
    assert all(evals[0]["step"] == 3 and evals[0]["episodes"] == 1 for evals in run["per_task"].values())
    assert (tmp_path / "pretraining.png").exists()


def test_demo_fit_report_scores_each_task_on_the_same_windows(multitask_run, pick_demos, push_demos, push_demos_fov60,
                                                             tmp_path, capsys):
    """Each task's windows come from its own buffer (PushCube-v1's at the 60° camera the model was trained with)."""
    bench = load_script("benchmarks/demo_fit.py", "demo_fit")
    args = ["--run", f"{multitask_run[0]}=PickCube-v1,PushCube-v1",
            "--demos", f"{pick_demos.parent}/{{task}}", f"PushCube-v1={push_demos_fov60}",
            "--ratios", "0.5", "1.0", "--minibatches", "2", "--batch-size", "2", "--decode-minibatches", "1"]
    assert bench.main([*args, "--out", str(tmp_path / "a")]) == 0
    assert bench.main([*args, "--out", str(tmp_path / "b")]) == 0
    a, b = (json.loads((tmp_path / d / "demo_fit.json").read_text()) for d in "ab")
    assert [(r["task"], r["ratio"]) for r in a["results"]] == [
        ("PickCube-v1", 0.5), ("PickCube-v1", 1.0), ("PushCube-v1", 0.5), ("PushCube-v1", 1.0)]
    assert all(0 <= r["action_accuracy"] <= 1 and 0 <= r["goal_accuracy"] <= 1 for r in a["results"])
    assert a["results"] == b["results"] and a["decoded"] == b["decoded"]  # same seed: same windows, masks, chunks
    for d in a["decoded"]:
        assert len(d["chunk_mae_per_dim"]) == 7 and d["chunk_mae"] > 0 and d["num_denoise_steps"] >= 1
    assert (tmp_path / "a" / "demo_fit.png").exists() and "PushCube-v1" in (tmp_path / "a" / "demo_fit.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--run", f"{multitask_run[0]}", "--out", str(tmp_path)])  # no =TASK
    assert f"PushCube-v1={push_demos_fov60}" in (tmp_path / "a" / "demo_fit.md").read_text()  # the command, whole
    with pytest.raises(SystemExit):
        bench.main(["--run", f"{multitask_run[0]}=StackCube-v1", "--demos", f"{pick_demos.parent}/{{task}}"])  # no buffer
    capsys.readouterr()
    with pytest.raises(SystemExit):  # the template's PushCube-v1 buffer was recorded with the task's own camera
        bench.main(["--run", f"{multitask_run[0]}=PushCube-v1", "--demos", f"{pick_demos.parent}/{{task}}",
                    "--out", str(tmp_path / "c")])
    assert "was recorded with camera_fov=None but 60.0 was asked for" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.main(["--run", f"{multitask_run[0]}=PickCube-v1", "--demos", "data/a/{task}", "data/b/{task}"])
    assert "at most one path template" in capsys.readouterr().err
