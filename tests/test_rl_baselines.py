"""The RL baselines (PPO, SAC/RLPD, IQL): their networks, and the recipe run as a subprocess with the toy config."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SACLoss, SoftUpdate

from mmada_rl.baselines.rl import (OneStepChunkActor, RLAgent, RLNetworkConfig, is_rl_agent_dir, load_rl_actor, make_actor,
                                   make_qvalue, make_value)
from mmada_rl.evaluation import EVAL_SEED_BASE, evaluate
from recipe_runs import check_error, errors_by_config, run_in_one_process
from script_loader import load_script

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "baselines" / "online.py"
SPEC = Bounded(-1.0, 1.0, (7,))
SMALL_ENCODER = {"channels": [8, 16], "image_features": 16, "state_features": 8, "num_keypoints": 4}
RECORD_KEYS = {"env_steps", "updates", "success_once", "success_once_ci_low", "success_once_ci_high", "success_at_end",
               "episodes", "per_episode", "wall_s"}


def batch(config: RLNetworkConfig, n: int = 8) -> TensorDict:
    def obs():
        out = {"state": torch.randn(n, config.state_dim)}
        if config.obs_mode == "rgb":
            out["image"] = torch.randint(0, 256, (n, 3, config.image_size, config.image_size), dtype=torch.uint8)
        return out

    return TensorDict({"observation": obs(), "action": torch.rand(n, 7) * 2 - 1,
                       "next": {"observation": obs(), "reward": torch.randn(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool),
                                "terminated": torch.zeros(n, 1, dtype=torch.bool)}}, [n])


# -- networks -----------------------------------------------------------------------
@pytest.mark.parametrize("obs_mode", ["state", "rgb"])
def test_networks_read_the_canonical_keys_and_write_torchrl_outputs(obs_mode):
    config = RLNetworkConfig(obs_mode=obs_mode, state_dim=29, image_size=16, hidden_sizes=(16,), encoder=SMALL_ENCODER)
    td = batch(config)
    out = make_actor(config, SPEC)(td.clone())
    assert out["action"].shape == (8, 7) and out["action"].abs().max() <= 1 and out["action_log_prob"].shape == (8,)
    assert make_qvalue(config)(td.clone())["state_action_value"].shape == (8, 1)
    assert make_value(config)(td.clone())["state_value"].shape == (8, 1)


def test_one_step_chunk_actor_is_greedy_and_writes_a_chunk_of_one():
    config = RLNetworkConfig(state_dim=10, hidden_sizes=(16,))
    chunk_actor = OneStepChunkActor(make_actor(config, SPEC), "state")
    assert (chunk_actor.chunk_size, chunk_actor.execute_steps, chunk_actor.image_size) == (1, 1, None)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a = chunk_actor(batch(config)[:3].exclude("action"))
        b = chunk_actor(a.clone().exclude("action"))
    assert a["action"].shape == a["vla_action", "chunk"].shape == (3, 1, 7)
    torch.testing.assert_close(a["action"], b["action"])
    assert chunk_actor.get_new_version(execute_steps=1) is chunk_actor
    with pytest.raises(ValueError, match="one action per call"):
        chunk_actor.get_new_version(execute_steps=2)


def test_sac_loss_falls_and_the_agent_reloads(tmp_path):
    config = RLNetworkConfig(state_dim=10, hidden_sizes=(32, 32))
    torch.manual_seed(0)
    stats = (torch.randn(10), torch.rand(10) + 0.5)

    def sac():
        actor = make_actor(config, SPEC, stats)
        loss = SACLoss(actor, make_qvalue(config, stats), num_qvalue_nets=2, action_spec=SPEC)
        loss.make_value_estimator(gamma=0.9)
        SoftUpdate(loss, tau=0.005)
        return loss, actor

    (loss, actor), td = sac(), batch(config, 64)
    optimizer = torch.optim.Adam(loss.parameters(), lr=1e-3)
    first = None
    for _ in range(50):
        losses = loss(td.clone())
        step_loss = losses["loss_qvalue"] + losses["loss_actor"]
        first = float(losses["loss_qvalue"].detach()) if first is None else first
        optimizer.zero_grad()
        step_loss.backward()
        optimizer.step()
    assert float(losses["loss_qvalue"].detach()) < 0.5 * first
    RLAgent("sac", config, loss, actor).save(tmp_path)
    reloaded, _ = sac()
    RLAgent("sac", config, reloaded).load(tmp_path)
    for key, value in loss.state_dict().items():
        torch.testing.assert_close(reloaded.state_dict()[key], value)
    with pytest.raises(ValueError, match="holds a sac agent but algo=iql"):
        RLAgent("iql", config, reloaded).load(tmp_path)

    # the actor alone, as evaluation loads it: the trained weights and the state moments, greedy actions equal
    assert is_rl_agent_dir(tmp_path) and not is_rl_agent_dir(tmp_path / "nowhere")
    evaluated = load_rl_actor(tmp_path)
    assert (evaluated.obs_mode, evaluated.chunk_size, evaluated.action_dim) == ("state", 1, 7)
    obs = batch(config, 16).exclude("action", "next")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = OneStepChunkActor(actor, "state")(obs.clone())["action"]
        untrained = OneStepChunkActor(make_actor(config, SPEC, stats), "state")(obs.clone())["action"]
        got = evaluated(obs.clone())["action"]
    torch.testing.assert_close(got, expected)
    assert not torch.allclose(untrained, expected)  # so the equality above is the loaded weights' doing
    RLAgent("sac", config, loss).save(tmp_path / "loss_only")
    with pytest.raises(FileNotFoundError, match="saved without its actor"):
        load_rl_actor(tmp_path / "loss_only")


def test_sampled_evaluation_draws_the_actors_actions_and_repeats(tmp_path, monkeypatch):
    config = RLNetworkConfig(state_dim=42, hidden_sizes=(16,))  # PickCube-v1's privileged state
    torch.manual_seed(0)
    actor = make_actor(config, SPEC)
    RLAgent("sac", config, SACLoss(actor, make_qvalue(config), num_qvalue_nets=2, action_spec=SPEC), actor).save(tmp_path)
    executed, forward = [], OneStepChunkActor.forward

    def recording(self, tensordict):
        out = forward(self, tensordict)
        executed.append(out["action"].clone())
        return out

    monkeypatch.setattr(OneStepChunkActor, "forward", recording)

    def run(**kwargs):
        executed.clear()
        result = evaluate(tmp_path, "PickCube-v1", 1, max_episode_steps=3, progress=False, **kwargs)
        return result, torch.cat(executed)

    greedy, greedy_actions = run()
    sampled, sampled_actions = run(sample_actions=True)
    _, again = run(sample_actions=True)
    assert not greedy.sample_actions and sampled.sample_actions and "actions sampled from the actor" in sampled.table()
    assert "greedy" in greedy.table() and "greedy" not in sampled.table()
    assert sampled.to_dict()["eval/sample_actions"] == 1
    # the same observation at the reset (the warm-up and the first step): the mean twice, two different draws
    torch.testing.assert_close(greedy_actions[0], greedy_actions[1])
    assert not torch.allclose(sampled_actions[0], sampled_actions[1])
    # seeded with the episode (after the warm-up decode, row 0): a sampled evaluation repeats
    torch.testing.assert_close(sampled_actions[1:], again[1:])
    with pytest.raises(ValueError, match="sample_actions needs an RL baseline's actor"):
        evaluate(actor, "PickCube-v1", 1, sample_actions=True)  # the bare TorchRL actor, not a chunk policy


def test_bad_network_config_fails_with_a_sentence():
    with pytest.raises(ValueError, match="obs_mode must be one of"):
        RLNetworkConfig(obs_mode="depth")
    with pytest.raises(ValueError, match="hidden_sizes must be a non-empty list"):
        RLNetworkConfig(hidden_sizes=())
    with pytest.raises(ValueError, match="actions are"):
        make_actor(RLNetworkConfig(action_dim=4), SPEC)


# -- the recipe ---------------------------------------------------------------------
def run_recipe(*overrides, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(RECIPE), *map(str, overrides)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def toy_runs(state_demos, tmp_path_factory) -> dict[str, Path]:
    """Each algo once with online_toy.yaml, all in one process: 64 env steps, evaluations at 32 and 64 (IQL also at 0),
    checkpoints kept."""
    runs = {algo: tmp_path_factory.mktemp(algo) / "run" for algo in ("ppo", "sac", "iql")}
    done = run_in_one_process(RECIPE, [[f"algo={algo}", f"run_dir={run_dir}", f"data.dir={state_demos}",
                                        "data.collect_episodes=0", "checkpoint.keep=10"] for algo, run_dir in runs.items()],
                              "online_toy")
    for proc in done:
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "[online] done:" in proc.stdout
    return runs


@pytest.mark.parametrize("algo, observation, eval_steps, checkpoints", [
    ("ppo", "rgb+proprio", [32, 64], ["step_00000004", "step_00000008"]),
    ("sac", "privileged_state", [32, 64], ["step_00000032", "step_00000064"]),
    ("iql", "privileged_state", [0, 32, 64], ["step_00000005", "step_00000010", "step_00000042", "step_00000074"]),
])
def test_each_baseline_trains_evaluates_and_checkpoints(toy_runs, algo, observation, eval_steps, checkpoints):
    run_dir = toy_runs[algo]
    history = json.loads((run_dir / "eval_history.json").read_text())
    assert [r["env_steps"] for r in history] == eval_steps
    for record in history:
        assert set(record) == RECORD_KEYS
        assert 0.0 <= record["success_once_ci_low"] <= record["success_once"] <= record["success_once_ci_high"] <= 1.0
        assert record["episodes"] == 1 and record["wall_s"] >= 0
        assert record["per_episode"] == [{"seed": EVAL_SEED_BASE, "success_once": record["success_once"] == 1.0}]
    assert [r["updates"] for r in history] == sorted(r["updates"] for r in history)
    final = json.loads((run_dir / "final.json").read_text())
    assert {k: final[k] for k in RECORD_KEYS} == history[-1]
    assert final["algo"] == algo and final["observation"] == observation and final["config"]["collector"]["total_env_steps"] == 64
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == checkpoints
    # the training episodes (20 steps each, 64 env steps: 3 ended), as the comparison's rollout table reads them
    (successes, episodes), = load_script("benchmarks/compare/compare.py").training_rollouts(run_dir, 64)
    assert episodes == 3 and 0 <= successes <= episodes
    last = run_dir / "checkpoints" / checkpoints[-1]
    assert json.loads((last / "model" / "rl_agent.json").read_text())["algo"] == algo
    extra = torch.load(last / "trainer.pt", weights_only=False)["extra"]
    assert extra["env_steps"] == 64 and extra["updates"] == history[-1]["updates"]
    if algo != "ppo":  # the online replay buffer travels with the checkpoint
        assert extra["replay_buffer"].shape == (64,)
    assert (run_dir / "logs" / "scalars" / "train" / "reward.csv").exists()
    # what `mmada-rl eval --checkpoint RUN_DIR` runs: the newest checkpoint's actor, on the recipe's evaluation seed
    result = evaluate(run_dir, "PickCube-v1", episodes=1, max_episode_steps=20, progress=False)
    assert result.episodes == 1 and 1 <= result.episode_length <= 20
    assert (result.success_once, result.success_at_end) == (history[-1]["success_once"], history[-1]["success_at_end"])


@pytest.mark.parametrize("algo, checkpoint, message, eval_steps", [
    ("sac", "step_00000032", "at env step 32 (update 32)", [32, 64]),
    ("iql", "step_00000005", "at env step 0 (update 5)", [0, 32, 64]),  # interrupted in the offline phase
])
def test_interrupted_run_resumes_from_its_last_checkpoint(toy_runs, state_demos, tmp_path, algo, checkpoint, message, eval_steps):
    original = toy_runs[algo]
    (tmp_path / "checkpoints").mkdir()
    shutil.copytree(original / "checkpoints" / checkpoint, tmp_path / "checkpoints" / checkpoint)
    shutil.copy(original / "eval_history.json", tmp_path / "eval_history.json")  # holds records past the checkpoint too
    proc = run_recipe(f"algo={algo}", f"run_dir={tmp_path}", f"data.dir={state_demos}", "data.collect_episodes=0",
                      "checkpoint.keep=10", "checkpoint.resume=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resumed from" in proc.stdout and message in proc.stdout
    history = json.loads((tmp_path / "eval_history.json").read_text())
    assert [r["env_steps"] for r in history] == eval_steps
    expected = json.loads((original / "eval_history.json").read_text())
    assert [r["updates"] for r in history] == [r["updates"] for r in expected]  # same update schedule as without the break
    extra = torch.load(tmp_path / "checkpoints" / "step_00000064" / "trainer.pt", weights_only=False)["extra"] if algo == "sac" else None
    if extra is not None:
        assert extra["env_steps"] == 64 and extra["replay_buffer"].shape == (64,)  # 32 restored + 32 new transitions


BAD_CONFIGS = [
    (["algo=dqn"], "algo='dqn' is not an RL baseline; use algo=ppo, algo=sac or algo=iql"),
    (["algo=sac", "collector.total_env_steps=50"], "must be a positive multiple of collector.frames_per_batch=32"),
    (["algo=ppo", "loss.ppo.minibatch_size=10"], "must be a multiple of loss.ppo.minibatch_size=10"),
    (["device=cuda:0"], "recipe runs on the CPU only"),
]


@pytest.fixture(scope="module")
def bad_config_errors(tmp_path_factory) -> dict[str, str | None]:
    """The error the recipe ends each of ``BAD_CONFIGS`` with, all run in one process (tests/recipe_runs.py)."""
    return errors_by_config(RECIPE, BAD_CONFIGS, lambda run_dir, overrides: [f"run_dir={run_dir}", *overrides],
                            tmp_path_factory.mktemp("bad_configs"), "online_toy")


@pytest.mark.parametrize("overrides, message", BAD_CONFIGS)
def test_bad_configs_fail_with_one_clear_error(bad_config_errors, overrides, message):
    check_error(bad_config_errors, overrides, message)


def test_a_bad_config_on_the_command_line_exits_with_its_message(tmp_path):
    overrides, message = BAD_CONFIGS[0]
    proc = run_recipe(f"run_dir={tmp_path}", *overrides, timeout=120)
    assert proc.returncode != 0 and message in proc.stderr
