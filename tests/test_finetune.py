"""Online fine-tuning: chunk rewards, the two losses, advantages, the demo/online mix and the recipe end to end."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.data.windows import no_start_steps
from mmada_rl.diffusion.path import path_log_prob, sample_steps, select_steps
from mmada_rl.envs.maniskill import make_env
from mmada_rl.evaluation import EVAL_SEED_BASE
from mmada_rl.diffusion.keys import CORRUPTED_KEY, NOISY_SEQUENCE_KEY
from mmada_rl.keys import (ACTION_GRIPPER_ONLY_KEY, ACTION_IS_PAD_KEY, ADVANTAGE_KEY, GROUP_KEY, IS_DEMO_KEY, NOISE_LEVEL_KEY, SEQUENCE_KEY,
                           VALUE_TARGET_KEY)
from mmada_rl.objectives import PathPPOLoss, RewardWeightedDiffusionLoss
from mmada_rl.objectives.masked_diffusion import ACTION_SEGMENT
from mmada_rl.objectives.advantages import DecisionIndexBaseline, group_relative_advantages, returns_to_go
from mmada_rl.policy import DECODING_PATH_KEY, MMaDAActor, MMaDAEnsemble, MMaDAModel, make_policy_env
from mmada_rl.policy.execution import ChunkReward, ExecutionNoise, StepLog
from mmada_rl.training.checkpoint import TRAINER_FILE, latest_checkpoint, load_checkpoint
from checkpoint_checks import check_average_beside_own_weights, weights
from recipe_runs import RecipeRun, check_error, errors_by_config, run_in_one_process
from script_loader import load_script

pytestmark = pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.ActionOutOfRangeWarning")
REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "finetune" / "finetune.py"


def run_recipe(*overrides, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(RECIPE), *map(str, overrides)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def toy_args(pretrained: Path, demos: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    """The toy recipe's command-line arguments: from ``pretrained`` on ``demos`` into ``run_dir``, with ``overrides``."""
    return [f"pretrained={pretrained}", f"run_dir={run_dir}", f"demos.dir={demos}", *overrides]


def run_recipes(*runs: list) -> list[RecipeRun]:
    """Each list of overrides in ``runs``, run in order in one process (tests/recipe_runs.py)."""
    return run_in_one_process(RECIPE, [list(map(str, overrides)) for overrides in runs])


def recipe_utils():
    """The recipe's ``utils`` module (recipes are scripts, not a package)."""
    return load_script(RECIPE.parent / "utils.py", "finetune_utils")


@pytest.fixture(scope="module")
def model(toy_pretrain_run) -> MMaDAModel:
    return MMaDAModel.load(toy_pretrain_run / "checkpoints" / "step_00000006" / "model").eval()


def test_learning_rate_is_constant_or_decays_with_the_env_steps():
    utils = recipe_utils()
    cfg = OmegaConf.create({"optim": {"lr": 1e-4, "lr_decay": "constant", "min_lr_ratio": 0.1},
                            "collector": {"total_env_steps": 1000}})
    assert utils.learning_rate(cfg, 0) == utils.learning_rate(cfg, 1000) == 1e-4  # constant: optim.lr throughout
    cfg.optim.update(lr_decay="cosine", min_lr_ratio=0.2)
    assert [utils.learning_rate(cfg, s) for s in (0, 500, 1000, 2000)] == pytest.approx([1e-4, 0.6e-4, 0.2e-4, 0.2e-4])
    assert utils.learning_rate(cfg, 250) == pytest.approx(1e-4 * (0.2 + 0.8 * 0.5 * (1 + math.cos(math.pi / 4))))


# -- chunk rewards and seeds ----------------------------------------------------------------
def test_chunk_reward_is_the_discounted_sum_of_the_executed_steps():
    log = StepLog(["reward"])
    env = TransformedEnv(make_env("PushCube-v1", max_episode_steps=12), Compose(log, ChunkReward(gamma=0.9)), auto_unwrap=False)
    td = env.reset(seed=0)
    torch.manual_seed(0)
    executed = []
    for i in range(3):  # 5 + 5 + 2 steps: the episode ends inside the third chunk
        td = env.step(td.set("action", torch.rand(5, 7) * 2 - 1))
        rewards = torch.stack([s["reward"] for s in log.steps[1 + 5 * i: 6 + 5 * i]]).reshape(-1)
        executed.append(len(rewards))
        expected = (rewards * 0.9 ** torch.arange(len(rewards))).sum()
        assert td["next", "reward"].shape == (1,)
        torch.testing.assert_close(td["next", "reward"].reshape(()), expected)
        td = step_mdp(td)
    assert executed == [5, 5, 2]
    env.close()
    with pytest.raises(ValueError, match="gamma"):
        ChunkReward(gamma=0.0)


def test_chunk_reward_in_a_batch_locked_env_sums_only_the_steps_each_env_ran():
    """SerialEnv (like ParallelEnv) keeps a finished env's last reward in the skipped slots; they must not count."""
    from torchrl.envs import SerialEnv

    lengths = (7, 12)  # env 0 ends inside the second chunk, env 1 runs on
    torch.manual_seed(0)
    actions = torch.rand(2, 2, 5, 7) * 2 - 1  # (chunk, env, K, A)

    def factory(i):
        return lambda: make_env("PushCube-v1", max_episode_steps=lengths[i], train_seed=i)

    expected = torch.zeros(2, 2)
    for i in range(2):  # each env alone, same seeds and actions
        single = TransformedEnv(factory(i)(), ChunkReward(gamma=0.9))
        td = single.reset()
        for c in range(2):
            td = single.step(td.set("action", actions[c, i]))
            expected[c, i] = td["next", "reward"].reshape(())
            td = step_mdp(td)
        single.close()
    batched = TransformedEnv(SerialEnv(2, [factory(0), factory(1)]), ChunkReward(gamma=0.9))
    td = batched.reset()
    for c in range(2):
        td = batched.step(td.set("action", actions[c]))
        torch.testing.assert_close(td["next", "reward"].reshape(2), expected[c])
        td = step_mdp(td)
    assert td["done"].reshape(-1).tolist() == [True, False]
    batched.close()


def test_train_seed_schedule_repeats_each_initial_state_group_size_times():
    env = make_env("PushCube-v1", max_episode_steps=2, train_seed=10, group_size=2)
    rollout = env.rollout(8, break_when_any_done=False)
    seeds = rollout[GROUP_KEY].reshape(-1).tolist()
    assert seeds == [10, 10, 10, 10, 11, 11, 11, 11]  # two 2-step episodes per seed
    first = rollout["observation", "image"]
    torch.testing.assert_close(first[0], first[2])  # same seed, same initial frame
    assert not torch.equal(first[0], first[4])
    assert env.reset(seed=5)["episode_seed"].item() == 5  # an explicit seed wins
    env.close()


def test_a_resumed_run_starts_each_env_worker_at_the_initial_states_after_those_begun():
    """Episode seeds as two ParallelEnv workers report them (worker ``w`` from ``train_seed + w * stride``; the
    layout test_parallel_env_runs_chunks_across_episode_ends checks on real envs), two episodes per initial state:
    each worker has begun its initial states 0 and 1, so a resumed run's workers start at 2, in seeds that stay
    each worker's own."""
    utils = recipe_utils()
    stride = utils.WORKER_SEED_STRIDE
    cfg = OmegaConf.create({"env": {"train_seed": 10, "num_workers": 2}})
    seeds = torch.tensor([[10, 10, 10, 10, 11, 11], [10 + stride] * 4 + [11 + stride] * 2]).unsqueeze(-1)
    batch = TensorDict({GROUP_KEY: seeds}, batch_size=[2, 6])
    begun = utils.initial_states_begun(batch, cfg)
    assert begun == 2 and utils.initial_states_begun(batch, cfg, begun=5) == 5  # never back
    assert utils.initial_states_begun(batch[:, :4], cfg) == 1
    resumed = utils.with_initial_states_begun(cfg, begun)
    assert resumed.env.train_seed == 12 and cfg.env.train_seed == 10  # worker w resumes at 12 + w * stride
    assert utils.with_initial_states_begun(cfg, 0) is cfg
    with pytest.raises(ValueError, match="reach the next worker's seeds"):
        utils.with_initial_states_begun(cfg, stride)
    nine = OmegaConf.create({"env": {"train_seed": 10, "num_workers": 9}})
    utils.check_train_seeds(nine)  # their seeds end at 900_010
    with pytest.raises(ValueError, match="into the evaluation seeds"):
        utils.with_initial_states_begun(nine, stride - 5)  # the last worker's would pass 1_000_000


def test_group_relative_advantages():
    adv = group_relative_advantages(torch.tensor([1.0, 0.0, 1.0, 1.0, 3.0]), torch.tensor([7, 7, 8, 8, 9]))
    torch.testing.assert_close(adv, torch.tensor([1.0, -1.0, 0.0, 0.0, 0.0]))


def _chunk_episode(step_rewards: list[float], success: bool, k: int = 5) -> TensorDict:
    """Chunk-level transitions of one episode as the fine-tuning collector records them: each decision's reward is
    the discounted sum (gamma 0.99) of its ``k`` steps' rewards, the last decision runs what is left."""
    from mmada_rl.keys import STEP_KEY

    chunks = [torch.tensor(step_rewards[i:i + k]) for i in range(0, len(step_rewards), k)]
    n = len(chunks)
    reward = torch.stack([(c * 0.99 ** torch.arange(len(c))).sum() for c in chunks]).reshape(n, 1)
    start = torch.arange(n).reshape(n, 1) * k
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[-1] = True
    return TensorDict({"obs": torch.zeros(n, 1), STEP_KEY: start, ("next", "obs"): torch.zeros(n, 1),
                       ("next", STEP_KEY): start + torch.tensor([len(c) for c in chunks]).reshape(n, 1),
                       ("next", "reward"): reward, ("next", "done"): done, ("next", "terminated"): done & success,
                       ("next", "truncated"): done & (not success), ("next", "success"): done & success}, [n])


@pytest.mark.parametrize("absorbing", [False, True])
def test_absorbing_success_makes_finishing_worth_more_than_lingering(absorbing):
    """PickCube-v1's dense reward pays ~0.57 per step with the cube at the goal, 1 on the success step, which ends the
    episode. Lingering for the 50 steps outscores succeeding at step 18 unless the success is absorbing."""
    from torchrl.modules import ValueOperator
    from torchrl.objectives.value import GAE

    critic = torch.nn.Linear(1, 1)
    torch.nn.init.zeros_(critic.weight), torch.nn.init.zeros_(critic.bias)  # V = 0: the advantage is the return
    gae = GAE(gamma=0.99 ** 5, lmbda=1.0, value_network=ValueOperator(critic, in_keys=["obs"]), average_gae=False)
    cfg = OmegaConf.create({"advantage": {"absorbing_success": absorbing, "gamma": 0.99}})
    first = {}
    for name, episode in [("linger", _chunk_episode([0.57] * 50, False)), ("finish", _chunk_episode([0.57] * 17 + [1.0], True))]:
        raw = episode.get(("next", "reward")).clone()
        recipe_utils().absorb_success(cfg, episode)
        changed = ~torch.isclose(episode.get(("next", "reward")), raw)
        assert changed.tolist() == (episode.get(("next", "success")) if absorbing else torch.zeros_like(changed)).tolist()
        with torch.no_grad():
            first[name] = float(gae(episode).get(ADVANTAGE_KEY)[0])
    assert (first["finish"] > first["linger"]) == absorbing
    # the discounted returns from the first step; the success's chunk ran 3 steps, it gains 0.99 ** 3 / (1 - 0.99)
    # discounted by the 15 steps before it
    assert first["linger"] == pytest.approx(0.57 * (1 - 0.99 ** 50) / 0.01, rel=1e-4)
    finish = 0.57 * (1 - 0.99 ** 17) / 0.01 + 0.99 ** 17 + (0.99 ** 18 / 0.01 if absorbing else 0.0)
    assert first["finish"] == pytest.approx(finish, rel=1e-4)


def test_the_critic_learns_the_demonstrations_returns(model, pick_demos):
    """value.pretrain_steps: the targets are each demonstration step's discounted return (the planner's episodes end in
    success, which then keeps paying 1 / (1 - gamma) when absorbing), and a few steps of regression fit them better."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.keys import IMAGE_KEY, STATE_KEY

    utils, demos = recipe_utils(), DemoBuffer.open(pick_demos)
    cfg = OmegaConf.load(RECIPE.parent / "config" / "toy.yaml")
    cfg.value.lr, cfg.value.pretrain_steps = 3e-3, 40
    bounds, stored = demos.episode_bounds(), demos.storage[: len(demos)]
    cfg.advantage.absorbing_success = False
    plain = utils.demo_value_targets(cfg, demos)
    cfg.advantage.absorbing_success = True
    absorbing = utils.demo_value_targets(cfg, demos)
    for start, stop in bounds:
        rewards = stored[start:stop].get(("next", "reward")).reshape(-1)
        discount = 0.99 ** torch.arange(stop - start)
        assert bool(stored[stop - 1].get(("next", "success")).all())  # every planner episode ends in success
        assert float(plain[start]) == pytest.approx(float((rewards * discount).sum()), rel=1e-4)
        assert float(absorbing[start] - plain[start]) == pytest.approx(0.99 ** (stop - start) / 0.01, rel=1e-4)
        assert float(plain[stop - 1]) == pytest.approx(float(rewards[-1]))  # the success step: its reward alone

    torch.manual_seed(0)
    value_op, value_optim = utils.make_value(cfg, model, demos)
    batch = stored.select(IMAGE_KEY, STATE_KEY).clone()

    def error() -> float:
        with torch.no_grad():
            return float(torch.nn.functional.mse_loss(value_op(batch.clone()).get("state_value").reshape(-1), absorbing))

    before = error()
    assert utils.pretrain_value(cfg, value_op, value_optim, demos) is not None
    assert error() < 0.5 * before
    cfg.value.pretrain_steps = 0
    assert utils.pretrain_value(cfg, value_op, value_optim, demos) is None  # the default: nothing done


def test_privileged_critic_standardises_its_input_by_running_moments():
    """Moments merged batch by batch equal those of all the states at once; the value step feeds them; without
    ``normalize`` (or before any state) the MLP reads the raw state."""
    from mmada_rl.keys import PRIVILEGED_STATE_KEY, VALUE_TARGET_KEY
    from mmada_rl.policy.value import PrivilegedValueNetwork, make_value_operator, value_step

    utils = recipe_utils()
    torch.manual_seed(0)
    states = torch.randn(50, 6) * torch.tensor([0.01, 0.1, 1.0, 10.0, 30.0, 0.5]) + torch.arange(6.0)
    net = PrivilegedValueNetwork(6, hidden=8)
    assert torch.equal(net.normalized(states), states)  # nothing observed yet
    for chunk in states.split([7, 20, 23]):
        net.observe(chunk)
    assert int(net.count) == 50
    torch.testing.assert_close(net.mean.float(), states.mean(0))
    expected = ((states - states.mean(0)) / states.std(0)).clamp(-5, 5)
    torch.testing.assert_close(net.normalized(states), expected, rtol=1e-4, atol=1e-5)
    unclipped = PrivilegedValueNetwork(6, hidden=8, clip=math.inf)
    unclipped.observe(states)
    far = (states.mean(0) + 10 * states.std(0)).unsqueeze(0)  # ten standard deviations out in every dimension
    torch.testing.assert_close(unclipped.normalized(far), torch.full((1, 6), 10.0), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(net.normalized(far), torch.full((1, 6), 5.0))
    with pytest.raises(ValueError, match="clip must be positive"):
        PrivilegedValueNetwork(6, clip=0.0)
    raw = PrivilegedValueNetwork(6, hidden=8, normalize=False)
    raw.observe(states)
    assert torch.equal(raw.normalized(states), states)

    value_op = make_value_operator(PrivilegedValueNetwork(6, hidden=8))
    rows = TensorDict({PRIVILEGED_STATE_KEY: states, VALUE_TARGET_KEY: torch.ones(50, 1)}, batch_size=[50])
    optimizer = torch.optim.Adam(value_op.parameters(), lr=1e-3)
    value_step(value_op, optimizer, rows[:10], rows[:10].get(VALUE_TARGET_KEY))
    value_step(value_op, optimizer, rows[10:], rows[10:].get(VALUE_TARGET_KEY))
    assert int(value_op.module.count) == 50 and "module.count" in value_op.state_dict()


def test_standardized_critic_learns_large_targets_faster_and_answers_in_their_units():
    """``value.normalize_targets``: the critic's targets' running moments are those of every target seen, its output is
    the network's times their std plus their mean, the moments are saved with the weights; on targets around 60 (a
    fine-tuning run's scale) the same steps leave it with a far smaller error than the plain critic."""
    from omegaconf import OmegaConf

    from mmada_rl.keys import PRIVILEGED_STATE_KEY, VALUE_TARGET_KEY
    from mmada_rl.policy.value import PrivilegedValueNetwork, StandardizedValue, make_value_operator, value_step

    utils = recipe_utils()
    cfg = OmegaConf.load(RECIPE.parent / "config" / "toy.yaml")
    cfg.value.input, cfg.env.task = "privileged_state", "PickCube-v1"
    assert not isinstance(utils.make_value(cfg, None, None)[0].module, StandardizedValue)  # the default: off
    cfg.value.normalize_targets = True
    value_op, _ = utils.make_value(cfg, None, None)
    assert isinstance(value_op.module, StandardizedValue)
    assert isinstance(value_op.module.network, PrivilegedValueNetwork)

    torch.manual_seed(0)
    states = torch.randn(400, 6)
    targets = (60 + 25 * torch.tanh(states[:, :2].sum(-1, keepdim=True))).reshape(-1, 1)
    rows = TensorDict({PRIVILEGED_STATE_KEY: states, VALUE_TARGET_KEY: targets}, batch_size=[400])
    fit, held_out = rows[:300], rows[300:]

    def fitted(standardized: bool):
        torch.manual_seed(1)
        net = PrivilegedValueNetwork(6, hidden=32)
        op = make_value_operator(StandardizedValue(net) if standardized else net)
        optimizer = torch.optim.Adam(op.parameters(), lr=3e-4)
        for step in range(60):  # what a run's critic gets in its first fifteen iterations
            batch = fit[(step * 32) % 300:][:32]
            value_step(op, optimizer, batch, batch.get(VALUE_TARGET_KEY))
        with torch.no_grad():
            error = float(torch.nn.functional.mse_loss(op(held_out.clone()).get("state_value"), held_out.get(VALUE_TARGET_KEY)))
        return op, error

    standard, standard_error = fitted(True)
    _, plain_error = fitted(False)
    assert standard_error < 0.1 * plain_error, (standard_error, plain_error)
    assert standard_error < float(held_out.get(VALUE_TARGET_KEY).var())  # better than the constant mean

    value = standard.module
    seen = torch.cat([fit[(step * 32) % 300:][:32].get(VALUE_TARGET_KEY) for step in range(60)])
    torch.testing.assert_close(value.mean.float(), seen.mean())
    torch.testing.assert_close(value.target_variance(), seen.var(), rtol=1e-4, atol=1e-4)
    x = states[:5]
    torch.testing.assert_close(value(x), value.network(x) * seen.std() + seen.mean(), rtol=1e-4, atol=1e-3)
    assert int(value.network.count) == len(seen)  # the inputs still reach the network's own moments
    copy = make_value_operator(StandardizedValue(PrivilegedValueNetwork(6, hidden=32)))
    copy.load_state_dict(standard.state_dict())
    torch.testing.assert_close(copy.module(x), value(x))


def test_absorbing_success_reward_refuses_an_undiscounted_value():
    from mmada_rl.objectives.advantages import absorbing_success_reward

    reward, success = torch.zeros(2, 1), torch.tensor([[False], [True]])
    with pytest.raises(ValueError, match="0 < gamma < 1"):
        absorbing_success_reward(reward, success, torch.tensor([5, 5]), gamma=1.0)
    with pytest.raises(ValueError, match="success must be shaped as reward"):
        absorbing_success_reward(reward, success.reshape(-1), torch.tensor([5, 5]), gamma=0.99)


# -- reward-weighted loss -----------------------------------------------------------------
def _two_chunks(model: MMaDAModel, toy_pretrain_run) -> TensorDict:
    """Two rows with the same observation and different action tokens, every target masked."""
    from mmada_rl.keys import IMAGE_KEY, INSTRUCTION_KEY, STATE_KEY

    env = make_env("PickCube-v1")
    obs = env.reset(seed=0)
    env.close()
    window = TensorDict({IMAGE_KEY: obs[IMAGE_KEY].expand(2, -1, -1, -1), STATE_KEY: obs[STATE_KEY].expand(2, -1)}, [2])
    window.set(INSTRUCTION_KEY, [obs[INSTRUCTION_KEY]] * 2)
    window.set(("goal", "image"), obs[IMAGE_KEY].expand(2, -1, -1, -1))
    layout = model.layout
    per = (model.config.chunk_size, layout.config.tokens_per_action)
    tokens = torch.stack([torch.zeros(per, dtype=torch.long), torch.ones(per, dtype=torch.long)])
    ids = model.sequence(window, action_tokens=tokens)
    noisy = ids.clone()
    targets = layout.target_positions
    noisy[:, targets] = layout.vocab.mask_id
    corrupted = torch.zeros_like(ids, dtype=torch.bool)
    corrupted[:, targets] = True
    return TensorDict({SEQUENCE_KEY: ids, NOISY_SEQUENCE_KEY: noisy, CORRUPTED_KEY: corrupted,
                       NOISE_LEVEL_KEY: torch.ones(2), ADVANTAGE_KEY: torch.tensor([1.0, -1.0])}, [2])


def _action_log_likelihood(loss_fn, td) -> torch.Tensor:
    """Mean log-probability of each row's action tokens (fixed full masking)."""
    with torch.no_grad():
        s = loss_fn.score(td)
    is_action = s.segment == ACTION_SEGMENT
    logp = -s.ce
    out = torch.zeros(2).index_add(0, s.rows[is_action], logp[is_action])
    return out / torch.zeros(2).index_add(0, s.rows[is_action], torch.ones(int(is_action.sum())))


@pytest.mark.parametrize("weighting", ["signed", "exp", "binary"])
def test_one_update_favours_high_advantage_tokens(model, toy_pretrain_run, weighting):
    import copy

    net = copy.deepcopy(model.denoiser).train()
    loss_fn = RewardWeightedDiffusionLoss(net, weighting=weighting, temperature=1.0, goal_weight=0.0)
    td = _two_chunks(model, toy_pretrain_run)
    before = _action_log_likelihood(loss_fn, td)
    optim = torch.optim.SGD(net.parameters(), lr=0.5)
    losses = loss_fn(td)
    optim.zero_grad()
    (losses["loss_action"] + losses["loss_goal"]).backward()
    optim.step()
    after = _action_log_likelihood(loss_fn, td)
    change = after - before
    assert change[0] > 0  # the high-advantage chunk became more likely
    assert change[0] > change[1]
    if weighting == "signed":
        assert change[1] < 0  # and the negative-advantage one less likely
        assert float(losses["negative_fraction"]) == 0.5


def test_demo_rows_take_demo_weight_and_online_rows_need_an_advantage(model, toy_pretrain_run):
    loss_fn = RewardWeightedDiffusionLoss(model.denoiser, weighting="exp", temperature=0.5, demo_weight=2.0)
    td = _two_chunks(model, toy_pretrain_run).set(IS_DEMO_KEY, torch.tensor([True, False]))
    weights = loss_fn.sample_weights(td, 2, torch.device("cpu"))
    torch.testing.assert_close(weights, torch.tensor([2.0, float(torch.exp(torch.tensor(-2.0)))]))
    with pytest.raises(KeyError, match="advantage"):
        loss_fn.sample_weights(td.exclude(ADVANTAGE_KEY), 2, torch.device("cpu"))
    # standardised over the online rows of the batch: temperature in units of their std
    online = TensorDict({ADVANTAGE_KEY: torch.tensor([0.1, 0.2, 0.3]), IS_DEMO_KEY: torch.zeros(3, dtype=torch.bool)}, [3])
    std_fn = RewardWeightedDiffusionLoss(model.denoiser, weighting="signed", temperature=1.0, standardize_advantage=True)
    torch.testing.assert_close(std_fn.sample_weights(online, 3, torch.device("cpu")), torch.tensor([-1.0, 0.0, 1.0]))


def test_action_mean_weight_scores_the_demonstration_rows_alone(model, toy_pretrain_run):
    """``action_mean_weight``: the L1 error of the expected action bins, on the demonstrations' rows only and
    unweighted by advantages (as pretraining scored them); no such term without demonstrations."""
    loss_fn = RewardWeightedDiffusionLoss(model.denoiser, weighting="signed", action_mean_weight=2.0)
    assert "loss_action_mean" in loss_fn.out_keys
    assert "loss_action_mean" not in RewardWeightedDiffusionLoss(model.denoiser).out_keys
    td = _two_chunks(model, toy_pretrain_run).set(IS_DEMO_KEY, torch.tensor([True, False]))
    out, s = loss_fn(td), loss_fn.score(td)
    demo_actions = (s.segment == ACTION_SEGMENT) & (s.sample == 0)
    expected = 2.0 * loss_fn.action_mean_error(s.logits[demo_actions], s.targets[demo_actions]).mean()
    assert expected > 0
    torch.testing.assert_close(out["loss_action_mean"], expected)
    online = loss_fn(td.set(IS_DEMO_KEY, torch.tensor([False, False])))
    assert float(online["loss_action_mean"].detach()) == 0.0


def test_binary_weights_keep_only_positive_advantages():
    from mmada_rl.objectives.reward_weighted import advantage_weights

    adv = torch.tensor([-2.0, 0.0, 0.3, 50.0])
    torch.testing.assert_close(advantage_weights(adv, "binary", temperature=0.1), torch.tensor([0.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="weighting"):
        advantage_weights(adv, "softmax")


def test_episode_returns_as_advantages_wait_for_the_episode_to_end():
    """estimator=return: every decision of an episode gets that episode's return, once it has ended."""
    groups = recipe_utils().EpisodeGroups(1, relative=False)

    def batch(rewards, dones, seeds):
        n = len(rewards)
        return TensorDict({("next", "reward"): torch.tensor(rewards).reshape(n, 1), ("next", "done"): torch.tensor(dones).reshape(n, 1),
                           GROUP_KEY: torch.tensor(seeds).reshape(n, 1)}, [n])

    first = groups.add(batch([0.0, 0.0, 1.0, 0.0], [False, False, True, False], [5, 5, 5, 6]))
    assert len(first) == 1 and first[0].shape == (3,)
    assert first[0].get(ADVANTAGE_KEY).tolist() == [1.0, 1.0, 1.0]  # a successful episode (sparse reward)
    assert groups.add(batch([0.0, 0.0], [False, False], [6, 6])) == []  # episode 2 still running
    (second,) = groups.add(batch([0.0], [True], [6]))
    assert second.shape == (4,) and second.get(ADVANTAGE_KEY).tolist() == [0.0] * 4  # failed: filtered out by binary weights


def test_returns_to_go_as_advantages_discount_each_decisions_future():
    """estimator=return_to_go: each decision gets its own discounted return to the episode's end, once it has ended."""
    groups = recipe_utils().EpisodeGroups(1, relative=False, discount=0.5)

    def batch(rewards, dones, seed):
        n = len(rewards)
        return TensorDict({("next", "reward"): torch.tensor(rewards).reshape(n, 1), ("next", "done"): torch.tensor(dones).reshape(n, 1),
                           GROUP_KEY: torch.full((n, 1), seed)}, [n])

    assert groups.add(batch([1.0, 2.0], [False, False], 5)) == []  # the episode runs on into the next batch
    (episode,) = groups.add(batch([4.0, 8.0], [False, True], 5))
    # G_3 = 8, G_2 = 4 + 0.5 * 8, G_1 = 2 + 0.5 * 8, G_0 = 1 + 0.5 * 6
    assert episode.get(ADVANTAGE_KEY).tolist() == [4.0, 6.0, 8.0, 8.0]
    assert episode.get(VALUE_TARGET_KEY).reshape(-1).tolist() == [4.0, 6.0, 8.0, 8.0]
    with pytest.raises(ValueError, match="one rollout per initial state"):
        recipe_utils().EpisodeGroups(2, relative=True, discount=0.5)


def test_decision_index_baseline_scores_returns_to_go_against_recent_episodes_at_the_same_index():
    """advantage.baseline_episodes: a successful episode as fast as the recent ones scores 0 at every decision (its
    early chunks are not pushed down for being far from the success), a faster one above, a failed one below."""
    discount = 0.5
    success = lambda n: returns_to_go(torch.tensor([0.0] * (n - 1) + [8.0]), discount)  # noqa: E731
    baseline = DecisionIndexBaseline(episodes=3)
    for _ in range(3):
        typical = baseline(success(3))
    torch.testing.assert_close(typical, torch.zeros(3))  # as the kept episodes went: nothing to learn
    assert success(3).tolist() == [2.0, 4.0, 8.0]  # standardised in a batch, the first two would be pushed down
    faster = baseline(success(2))
    assert (faster > 0).all()
    failed = baseline(torch.zeros(4))
    assert (failed[:3] < 0).all() and failed[3] == 0  # index 3: no other kept episode reached it
    assert len(baseline) == 3  # the window keeps the last three episodes
    restored = DecisionIndexBaseline(episodes=3)
    restored.load_state_dict(baseline.state_dict())
    torch.testing.assert_close(restored(success(3)), baseline(success(3)))  # a resumed run scores as it would have
    shorter = DecisionIndexBaseline(episodes=2)  # resumed with a shorter window: the two most recent episodes
    shorter.load_state_dict(baseline.state_dict())
    assert len(shorter) == 2 and torch.equal(shorter.window[-1], baseline.window[-1])
    with pytest.raises(ValueError, match="at least one episode"):
        DecisionIndexBaseline(episodes=0)
    with pytest.raises(ValueError, match="needs a discount"):
        recipe_utils().EpisodeGroups(1, relative=False, baseline=DecisionIndexBaseline(2))


def test_weight_goal_applies_the_row_weights_to_the_goal_tokens(model, toy_pretrain_run):
    td = _two_chunks(model, toy_pretrain_run)
    plain = RewardWeightedDiffusionLoss(model.denoiser, weighting="binary")
    weighted = RewardWeightedDiffusionLoss(model.denoiser, weighting="binary", weight_goal=True)
    with torch.no_grad():
        both = float(plain(td.clone().set(ADVANTAGE_KEY, torch.tensor([1.0, 1.0])))["loss_goal"])
        assert float(weighted(td.clone().set(ADVANTAGE_KEY, torch.tensor([1.0, 1.0])))["loss_goal"]) == pytest.approx(both)
        assert float(weighted(td.clone().set(ADVANTAGE_KEY, torch.tensor([-1.0, -1.0])))["loss_goal"]) == 0.0
        # failed rows (weight 0) leave the goal loss of the plain variant unchanged
        assert float(plain(td.clone().set(ADVANTAGE_KEY, torch.tensor([-1.0, -1.0])))["loss_goal"]) == pytest.approx(both)
        half = float(weighted(td.clone().set(ADVANTAGE_KEY, torch.tensor([1.0, -1.0])))["loss_goal"])
    assert 0.0 < half < both  # only the first row's goal tokens count (same observation, so about half)


def test_kl_penalty_is_zero_at_the_reference_and_grows_when_the_policy_moves(model, toy_pretrain_run):
    import copy

    net = copy.deepcopy(model.denoiser)
    loss_fn = RewardWeightedDiffusionLoss(net, reference=model.denoiser, kl_coef=1.0)
    td = _two_chunks(model, toy_pretrain_run)
    assert float(loss_fn(td)["loss_kl"].detach()) == pytest.approx(0.0, abs=1e-5)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    assert float(loss_fn(td)["loss_kl"].detach()) > 1e-3
    with pytest.raises(ValueError, match="reference"):
        RewardWeightedDiffusionLoss(net, kl_coef=1.0)


# -- path PPO ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sampled_chunks(model):
    """Two chunks sampled by the toy policy in a real PickCube-v1 env, with their decoding paths."""
    import copy

    env = make_env("PickCube-v1", max_episode_steps=10)
    actor = MMaDAActor(copy.deepcopy(model))
    penv = make_policy_env(env, actor, chunk_gamma=0.99)
    # Seeded, in a forked generator: the same two chunks whichever tests ran before, and no change to theirs.
    with torch.random.fork_rng(), set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        torch.manual_seed(0)
        penv.env.set_seed(0)
        rollout = penv.env.rollout(2, penv.policy, break_when_any_done=False)
    env.close()
    return rollout


@pytest.mark.parametrize("denoising_steps", [None, 2])
def test_path_ppo_ratio_is_one_at_unchanged_parameters_and_an_update_raises_good_paths(model, sampled_chunks, denoising_steps):
    import copy

    rollout = sampled_chunks.clone()
    path = rollout[DECODING_PATH_KEY]
    recorded = rollout["vla_action", "log_probs"]
    net = copy.deepcopy(model.denoiser).eval()
    with torch.no_grad():
        torch.testing.assert_close(path_log_prob(net, path.reshape(-1)).reshape(recorded.shape), recorded, rtol=1e-5, atol=1e-4)
    rollout.set(ADVANTAGE_KEY, torch.tensor([1.0, 1.0]))
    loss_fn = PathPPOLoss(net, ratio_level="step", denoising_steps=denoising_steps)
    torch.manual_seed(0)  # the loss draws its replayed steps from torch's generator
    out = loss_fn(rollout)
    assert float(out["ratio_mean"]) == pytest.approx(1.0, abs=1e-4)
    assert float(out["approx_kl"]) == pytest.approx(0.0, abs=1e-4)
    optim = torch.optim.SGD(net.parameters(), lr=0.05)
    out["loss_objective"].backward()
    optim.step()
    flat = path.reshape(-1)
    steps = None
    if denoising_steps is not None:  # the same draw as the loss's: only those steps were pushed up
        torch.manual_seed(0)
        steps = sample_steps(flat.committed, denoising_steps)
        recorded = select_steps(flat.log_probs, steps).sum((-2, -1)).reshape(recorded.shape)
    with torch.no_grad():
        after = path_log_prob(net, flat, steps=steps).reshape(recorded.shape)
    # One small step ascends the objective's gradient, the sum of the (replayed) path log-probabilities; a single
    # path's may fall when the two share parameters, so the claim is on their sum.
    assert after.sum() > recorded.sum()
    with pytest.raises(ValueError, match="ratio_level"):
        PathPPOLoss(net, ratio_level="chunk")
    with pytest.raises(ValueError, match="denoising_steps"):
        PathPPOLoss(net, ratio_level="path", denoising_steps=2)


def test_path_ppo_on_the_action_tokens_alone_ignores_the_goal_commits(model, sampled_chunks):
    import copy

    rollout = sampled_chunks.clone()
    rollout.set(ADVANTAGE_KEY, torch.tensor([1.0, -1.0]))
    net = copy.deepcopy(model.denoiser).eval()
    layout = net.layout
    is_action = torch.isin(layout.target_positions, layout.action_positions)  # (T,)
    path = rollout[DECODING_PATH_KEY]
    assert (path.committed & ~is_action).any() and (path.committed & is_action).any()  # goal and action commits
    with torch.no_grad():  # an update has moved the policy: ratios differ from 1
        for p in net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    actions_only = PathPPOLoss(net, ratio_level="step", tokens="action")(rollout)
    # the same objective on "all" tokens of a path whose goal commits are erased
    erased = rollout.clone()
    erased_path = erased[DECODING_PATH_KEY]
    erased_path.log_probs = torch.where(erased_path.committed & is_action, erased_path.log_probs, 0.0)
    erased_path.committed = erased_path.committed & is_action
    erased.set(DECODING_PATH_KEY, erased_path)
    reference = PathPPOLoss(net, ratio_level="step", tokens="all")(erased)
    everything = PathPPOLoss(net, ratio_level="step", tokens="all")(rollout)
    for key in ("loss_objective", "approx_kl", "ratio_mean"):
        torch.testing.assert_close(actions_only[key], reference[key])
    assert not torch.isclose(actions_only["approx_kl"], everything["approx_kl"])
    with pytest.raises(ValueError, match="tokens"):
        PathPPOLoss(net, tokens="goal")


def test_replaying_some_decoding_steps_scores_them_exactly(model, sampled_chunks):
    path = sampled_chunks[DECODING_PATH_KEY].reshape(-1)
    num = path.num_steps
    with torch.no_grad():
        full = path_log_prob(model.denoiser, path, per_token=True)  # (B, N, T)
        torch.testing.assert_close(full, path.log_probs, rtol=1e-5, atol=1e-4)
        steps = sample_steps(path.committed, 3, generator=torch.Generator().manual_seed(0))
        part = path_log_prob(model.denoiser, path, per_token=True, steps=steps)
    assert steps.shape == (path.shape[0], 3) and (steps.diff(dim=-1) > 0).all()  # distinct, ordered
    assert path.committed.any(-1).gather(1, steps).all()  # only steps that committed a token
    torch.testing.assert_close(part, select_steps(full, steps))
    # every step is drawn equally often
    counts = torch.zeros(num)
    generator = torch.Generator().manual_seed(1)
    committed = torch.ones(1, num, 4, dtype=torch.bool)
    for _ in range(2000):
        counts[sample_steps(committed, 2, generator=generator)[0]] += 1
    assert (counts / counts.sum() - 1 / num).abs().max() < 0.03
    # a step that committed nothing is only drawn when too few others are left
    committed[0, 0] = False
    assert 0 not in sample_steps(committed, num - 1)[0].tolist()
    with pytest.raises(ValueError, match="decoding steps"):
        sample_steps(committed, num + 1)


# -- demo/online mix ---------------------------------------------------------------------------
def test_demo_online_ratio_holds_in_sampled_batches(model, pick_demos):
    utils = recipe_utils()
    cfg = OmegaConf.create({"seed": 0, "demos": {"ratio": 0.25}, "replay_buffer": {"batch_size": 8, "capacity": 64}})
    n_online, n_demo = utils.split_batch(cfg)
    assert (n_online, n_demo) == (6, 2)
    from mmada_rl.data import DemoBuffer

    windows = utils.make_demo_windows(cfg, DemoBuffer.open(pick_demos), model)
    online = utils.make_online_buffer(cfg)
    L, K = model.layout.length, model.config.chunk_size
    online.extend(TensorDict({SEQUENCE_KEY: torch.zeros(20, L, dtype=torch.long), ACTION_IS_PAD_KEY: torch.zeros(20, K, dtype=torch.bool),
                              ADVANTAGE_KEY: torch.randn(20)}, [20]))
    for _ in range(3):
        batch = utils.mixed_batch(model, online.sample(), windows)
        assert batch.shape == (8,)
        assert int(batch[IS_DEMO_KEY].sum()) == 2
        assert (batch[SEQUENCE_KEY][batch[IS_DEMO_KEY]] != 0).any()  # real demonstration sequences
    # demos.ratio=1: the no-RL control takes the same updates on demonstrations only
    control = OmegaConf.merge(cfg, {"demos": {"ratio": 1.0}})
    assert utils.split_batch(control) == (0, 8)
    batch = utils.mixed_batch(model, None, utils.make_demo_windows(control, DemoBuffer.open(pick_demos), model))
    assert batch.shape == (8,) and bool(batch[IS_DEMO_KEY].all())


def test_demo_windows_skip_what_the_pretraining_run_skipped(toy_pretrain_run, model, pick_demos, tmp_path):
    """``demos.skip_*=null`` takes the pretraining run's ``data.skip_*``; a value given overrides it."""
    utils = recipe_utils()
    from mmada_rl.data import DemoBuffer

    checkpoint = tmp_path / "checkpoint"  # a pretraining checkpoint whose run skipped the idle starts and pauses
    checkpoint.mkdir()
    (checkpoint / "model").symlink_to(utils.resolve_model_dir(toy_pretrain_run))
    (checkpoint / "config.json").write_text(json.dumps({"data": {"skip_idle_start": True, "skip_pauses": 0.01,
                                                                 "skip_grasp_hold": 0.05}}))
    cfg = OmegaConf.create({"seed": 0, "pretrained": str(checkpoint), "demos": {"ratio": 1.0, "skip_idle_start": None,
                            "skip_pauses": None, "skip_grasp_hold": None}, "replay_buffer": {"batch_size": 8}})
    assert utils.demo_window_skips(cfg) == {"skip_idle_start": True, "skip_pauses": 0.01, "skip_grasp_hold": 0.05,
                                            "grasp_hold_gripper_only": False, "teacher_labels": False}
    overridden = OmegaConf.merge(cfg, {"demos": {"skip_pauses": 0.0}})
    assert utils.demo_window_skips(overridden) == {"skip_idle_start": True, "skip_pauses": 0.0, "skip_grasp_hold": 0.05,
                                                   "grasp_hold_gripper_only": False, "teacher_labels": False}
    (tmp_path / "saved").mkdir()  # a model saved on its own, without a run's config beside it
    (tmp_path / "saved" / "policy").symlink_to(utils.resolve_model_dir(toy_pretrain_run))
    bare = OmegaConf.merge(cfg, {"pretrained": str(tmp_path / "saved" / "policy")})
    assert utils.demo_window_skips(bare) == {"skip_idle_start": False, "skip_pauses": 0.0, "skip_grasp_hold": 0.0,
                                             "grasp_hold_gripper_only": False, "teacher_labels": False}
    assert utils.demo_window_skips(OmegaConf.merge(cfg, {"pretrained": str(toy_pretrain_run)})) == utils.WINDOW_SKIPS

    demos = DemoBuffer.open(pick_demos)
    expected = no_start_steps(demos, skip_idle_start=True, skip_pauses=0.01, skip_grasp_hold=0.05)
    assert expected.any() and not expected.all()
    sampler = utils.make_demo_windows(cfg, demos, model).sampler
    torch.testing.assert_close(sampler.no_start, expected)
    assert utils.make_demo_windows(bare, demos, model).sampler.no_start is None
    # the hold's windows scored on the gripper alone: inherited like the others, and only for ordered bins
    gripper_only = OmegaConf.merge(cfg, {"demos": {"grasp_hold_gripper_only": True}})
    assert utils.demo_window_skips(gripper_only)["grasp_hold_gripper_only"] is True
    with pytest.raises(ValueError, match=r"grasp_hold_gripper_only .* needs ordered bin tokens"):
        utils.make_demo_windows(gripper_only, demos, model)
    # a student distilled on a teacher's labels keeps them; demonstrations without them are refused
    (checkpoint / "config.json").write_text(json.dumps({"data": {"teacher_labels": True}}))
    assert utils.demo_window_skips(cfg)["teacher_labels"] is True
    with pytest.raises(ValueError, match="does not hold; write a relabelled copy first: mmada-rl relabel"):
        utils.make_demo_windows(cfg, demos, model)
    assert utils.demo_window_skips(OmegaConf.merge(cfg, {"demos": {"teacher_labels": False}}))["teacher_labels"] is False


def test_mixed_batches_flag_the_gripper_only_demo_windows_and_no_online_row(model, pick_demos):
    """Demonstration windows that start in the grasp hold score their gripper alone; online chunks score everything."""
    utils = recipe_utils()
    from mmada_rl.data import DemoBuffer, make_window_buffer

    cfg = OmegaConf.create({"seed": 0, "demos": {"ratio": 0.5}, "replay_buffer": {"batch_size": 400, "capacity": 400}})
    windows = make_window_buffer(DemoBuffer.open(pick_demos), model.config.chunk_size, 200, seed=0,
                                 skip_grasp_hold=0.05, grasp_hold_gripper_only=True)
    online = utils.make_online_buffer(cfg)
    L, K = model.layout.length, model.config.chunk_size
    online.extend(TensorDict({SEQUENCE_KEY: torch.zeros(200, L, dtype=torch.long),
                              ACTION_IS_PAD_KEY: torch.zeros(200, K, dtype=torch.bool), ADVANTAGE_KEY: torch.randn(200)}, [200]))
    batch = utils.mixed_batch(model, online.sample(), windows)
    flags, demo = batch[ACTION_GRIPPER_ONLY_KEY], batch[IS_DEMO_KEY]
    assert not flags[~demo].any() and flags[demo].any() and not flags[demo].all()


def test_fine_tuning_keeps_the_pretraining_regularisers(toy_pretrain_run, model, pick_demos, tmp_path):
    """``loss.proprio_drop_prob``, ``loss.proprio_drop_keep_dims``, ``loss.action_mean_weight`` and
    ``demos.random_shift`` null: the pretraining run's state dropout, expected-bin loss and image shift; a value given
    overrides them; a bare saved model has none."""
    from mmada_rl.data import DemoBuffer, RandomShift

    utils = recipe_utils()
    checkpoint = tmp_path / "checkpoint"  # a pretraining checkpoint whose run dropped the state and shifted the images
    checkpoint.mkdir()
    (checkpoint / "model").symlink_to(utils.resolve_model_dir(toy_pretrain_run))
    (checkpoint / "config.json").write_text(json.dumps({
        "loss": {"proprio_drop_prob": 0.3, "proprio_drop_keep_dims": [26, 27, 28], "action_mean_weight": 0.0},
        "replay_buffer": {"random_shift": 4}}))
    cfg = OmegaConf.merge(OmegaConf.load(RECIPE.parent / "config" / "toy.yaml"), {"pretrained": str(checkpoint)})
    keep = model.proprio_drop_index([26, 27, 28])
    assert keep is not None and len(keep) == len(model.proprio_index) - 3
    options = utils.pretraining_loss_options(cfg, model)
    assert options == {"proprio_drop_prob": 0.3, "proprio_drop_index": keep, "action_mean_weight": 0.0}
    loss = utils.make_loss(cfg, model)
    assert loss.proprio_drop_prob == 0.3 and loss.proprio_drop_index.tolist() == keep
    assert utils.demo_random_shift(cfg) == 4
    demos = DemoBuffer.open(pick_demos)
    assert any(isinstance(t, RandomShift) for t in utils.make_demo_windows(cfg, demos, model).transform)
    # a value given overrides the pretraining run's
    off = OmegaConf.merge(cfg, {"loss": {"proprio_drop_prob": 0.0}, "demos": {"random_shift": 0}})
    assert utils.pretraining_loss_options(off, model)["proprio_drop_prob"] == 0.0
    assert not any(isinstance(t, RandomShift) for t in utils.make_demo_windows(off, demos, model).transform)
    with pytest.raises(ValueError, match=r"needs ordered bin tokens \(tokenizers.action_type=bins\), "
                                         r"not a VQActionTokenizer"):
        utils.pretraining_loss_options(OmegaConf.merge(cfg, {"loss": {"action_mean_weight": 1.0}}), model)
    every = model.proprio_index.tolist()
    with pytest.raises(ValueError, match=r"loss.proprio_drop_keep_dims=\[.*\] keeps every state dimension"):
        utils.pretraining_loss_options(OmegaConf.merge(cfg, {"loss": {"proprio_drop_keep_dims": every}}), model)
    with pytest.raises(ValueError, match=r"state dimensions \[99\] are not in the sequence"):
        utils.pretraining_loss_options(OmegaConf.merge(cfg, {"loss": {"proprio_drop_keep_dims": [99]}}), model)
    # the toy pretraining run itself used neither
    plain = OmegaConf.merge(cfg, {"pretrained": str(toy_pretrain_run)})
    assert utils.pretraining_loss_options(plain, model) == {"proprio_drop_prob": 0.0, "proprio_drop_index": None,
                                                            "action_mean_weight": 0.0}
    assert utils.demo_random_shift(plain) == 0


def seeing_model(model: MMaDAModel) -> MMaDAModel:
    """``model`` rebuilt (fresh weights) with its own CNN over the observation image."""
    from mmada_rl.policy import MMaDAConfig, Tokenizers

    overrides = {"cross_attention_to_visual": True, "visual_encoder_channels": [8, 16, 32]}
    config = MMaDAConfig(**{**model.config.__dict__, "denoiser_overrides": overrides})
    return MMaDAModel(config, Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer,
                                         model.proprio_tokenizer))


def mixed_image_batch(utils, seeing: MMaDAModel, pick_demos, cfg) -> TensorDict:
    """A loss batch of random online rows (with images) and demonstration windows, ``cfg.demos.ratio`` of them demos."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY

    online = utils.make_online_buffer(cfg)
    L, K, size = seeing.layout.length, seeing.config.chunk_size, seeing.image_size
    online.extend(TensorDict({SEQUENCE_KEY: torch.zeros(20, L, dtype=torch.long), ACTION_IS_PAD_KEY: torch.zeros(20, K, dtype=torch.bool),
                              ADVANTAGE_KEY: torch.randn(20),
                              VISUAL_FEATURES_KEY: torch.randint(0, 255, (20, 3, size, size), dtype=torch.uint8)}, [20]))
    return utils.mixed_batch(seeing, online.sample(), utils.make_demo_windows(cfg, DemoBuffer.open(pick_demos), seeing))


def test_mixed_batches_carry_the_images_of_a_policy_with_its_own_cnn(model, pick_demos):
    """With ``visual_encoder_channels`` every row, online or demonstration, brings the image its CNN reads."""
    from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY

    utils = recipe_utils()
    seeing = seeing_model(model)
    cfg = OmegaConf.create({"seed": 0, "demos": {"ratio": 0.25}, "replay_buffer": {"batch_size": 8, "capacity": 64}})
    batch = mixed_image_batch(utils, seeing, pick_demos, cfg)
    size = seeing.image_size
    assert batch[VISUAL_FEATURES_KEY].shape == (8, 3, size, size)
    loss = RewardWeightedDiffusionLoss(seeing.denoiser)(batch)
    loss["loss_action"].backward()
    assert seeing.denoiser.visual_encoder.cnn[0].weight.grad.abs().sum() > 0


def test_a_cnn_frozen_while_pretraining_stays_frozen_while_fine_tuning(toy_pretrain_run, model, pick_demos, tmp_path):
    """``optim.freeze_visual_encoder=null`` follows the pretraining run's ``model.visual_encoder_freeze``, a value
    overrides it; an update then leaves the fixed CNN as it was and moves the rest of the denoiser."""
    from mmada_rl.training import optimizer_step

    utils = recipe_utils()
    checkpoint = tmp_path / "checkpoint"  # a pretraining checkpoint whose run kept a copied CNN fixed
    checkpoint.mkdir()
    (checkpoint / "model").symlink_to(utils.resolve_model_dir(toy_pretrain_run))
    (checkpoint / "config.json").write_text(json.dumps({"model": {"visual_encoder_freeze": True}}))
    cfg = OmegaConf.create({"seed": 0, "pretrained": str(checkpoint), "optim": {"lr": 1e-3, "weight_decay": 0.01,
                            "freeze_visual_encoder": None}, "demos": {"ratio": 0.25},
                            "replay_buffer": {"batch_size": 8, "capacity": 64}})
    assert utils.freezes_visual_encoder(cfg)
    assert not utils.freezes_visual_encoder(OmegaConf.merge(cfg, {"optim": {"freeze_visual_encoder": False}}))
    assert not utils.freezes_visual_encoder(OmegaConf.merge(cfg, {"pretrained": str(toy_pretrain_run)}))  # not frozen there

    seeing = seeing_model(model)
    optimizer = utils.make_optim(cfg, seeing)
    before = {k: v.clone() for k, v in seeing.denoiser.state_dict().items()}
    losses = RewardWeightedDiffusionLoss(seeing.denoiser)(mixed_image_batch(utils, seeing, pick_demos, cfg))
    optimizer_step(losses, seeing.denoiser.parameters(), optimizer, grad_clip=1.0)
    after = seeing.denoiser.state_dict()
    cnn = [k for k in before if k.startswith("visual_encoder.cnn.")]
    assert len(cnn) == 12 and all(torch.equal(before[k], after[k]) for k in cnn)
    assert any(not torch.equal(before[k], after[k]) for k in before if k not in cnn)

    trainable = seeing_model(model)
    utils.make_optim(OmegaConf.merge(cfg, {"optim": {"freeze_visual_encoder": False}}), trainable)
    assert all(p.requires_grad for p in trainable.denoiser.visual_encoder.parameters())
    with pytest.raises(ValueError, match="this policy has none"):
        utils.make_optim(cfg, MMaDAModel.load(utils.resolve_model_dir(toy_pretrain_run)))  # it reads image tokens


def test_execution_noise_explores_around_the_greedy_chunk_and_stores_the_executed_tokens(model):
    """DART-style exploration: the greedy chunk plus noise on the arm (the gripper exact), re-tokenized so that
    the stored tokens decode to exactly what the env executes; the same generator seed repeats the noise."""
    env = make_env("PickCube-v1", max_episode_steps=10)
    actor = MMaDAActor(model, execute_steps=3)
    obs = env.reset(seed=0)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        greedy = actor(obs.clone()).get(("vla_action", "chunk"))
        noisy = [ExecutionNoise(actor, 0.1, generator=torch.Generator().manual_seed(s))(obs.clone()) for s in (0, 0, 1)]
        penv = make_policy_env(env, actor, execute_steps=3, chunk_gamma=0.99)
        policy = ExecutionNoise(penv.policy, 0.1, generator=torch.Generator().manual_seed(0))
        rollout = penv.env.rollout(2, policy, break_when_any_done=False)
    env.close()
    tokenizer = model.action_tokenizer
    for td in noisy:
        chunk = td.get(("vla_action", "chunk"))
        torch.testing.assert_close(tokenizer.decode(td.get(("vla_action", "tokens"))), chunk)
        torch.testing.assert_close(td.get("action"), chunk[:3])  # the executed steps are the chunk's first k
        assert torch.equal(chunk[:, 6], greedy[:, 6])  # the gripper is left exact
        moved = (chunk[:, :6] - greedy[:, :6]).abs()
        assert moved.max() > 0.02 and moved.mean() < 0.3  # noise of std 0.1, plus the bins' rounding
    assert torch.equal(noisy[0]["vla_action", "chunk"], noisy[1]["vla_action", "chunk"])
    assert not torch.equal(noisy[0]["vla_action", "chunk"], noisy[2]["vla_action", "chunk"])
    # in a rollout, every decision's stored tokens decode to the actions the env ran
    assert rollout.shape == (2,) and int(rollout["next", "step_count"][-1]) == 6
    torch.testing.assert_close(tokenizer.decode(rollout["vla_action", "tokens"])[:, :3], rollout["action"])
    with pytest.raises(ValueError, match="std must be > 0"):
        ExecutionNoise(actor, 0.0)


# -- the recipe as users run it -------------------------------------------------------------------
COMMON = ["eval.episodes=1", "eval.max_episode_steps=10", "env.max_episode_steps=10", "collector.total_env_steps=30",
          "collector.decisions_per_batch=2",
          "checkpoint.interval=1", "checkpoint.keep=5"]


@pytest.fixture(scope="module")
def rwr_run(toy_pretrain_run, pick_demos, tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("finetune") / "rwr"
    proc = run_recipe(*toy_args(toy_pretrain_run, pick_demos, run_dir, COMMON))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir


def test_rwr_recipe_collects_updates_evaluates_and_checkpoints(rwr_run):
    history = json.loads((rwr_run / "eval_history.json").read_text())
    assert [h["env_steps"] for h in history] == [0, 30]  # before training and at the end of the budget
    assert all(0.0 <= h["success_once"] <= 1.0 and h["episodes"] == 1 for h in history)
    assert history[-1]["updates"] == 2 * 3  # two updates per iteration, three iterations of two 5-step chunks
    assert (rwr_run / "online_buffer").exists() and (rwr_run / "logs").exists()
    ckpts = sorted(p.name for p in (rwr_run / "checkpoints").iterdir())
    assert ckpts[-1] == "step_00000003"


def test_seed_report_reads_a_fine_tuning_run_from_its_eval_history(rwr_run, tmp_path):
    seeds = load_script("benchmarks/seeds.py")
    history = json.loads((rwr_run / "eval_history.json").read_text())
    assert seeds.main(["--group", "fine-tuned", str(rwr_run), "--group", "at start", f"{rwr_run}@0",
                       "--name", "ft", "--out", str(tmp_path)]) == 0
    last, first = (g["seeds"][0] for g in json.loads((tmp_path / "ft.json").read_text())["groups"])
    assert (last["step"], last["episodes"], last["success_once"]) == (30, 1, history[-1]["success_once"])
    assert first["step"] == 0 and first["success_once"] == history[0]["success_once"]
    assert last["seed"] == 0  # the run's own seed, from its checkpoint's config
    with pytest.raises(ValueError, match=r"no evaluation at env step 7 \(it logged: 0, 30\)"):
        seeds.main(["--group", "x", f"{rwr_run}@7", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="no @raw"):
        seeds.main(["--group", "x", f"{rwr_run}@raw", "--out", str(tmp_path)])


def test_a_fine_tuning_evaluation_keeps_its_episodes_and_pairs_with_an_evaluation_of_its_checkpoint(rwr_run, tmp_path):
    """Each eval_history.json record keeps its episodes (env seed, success); benchmarks/paired.py pairs the run's
    evaluations with each other and with `mmada-rl eval` of its last checkpoint on the same episodes, which
    succeeds in the same ones (greedy decoding, no moving average)."""
    history = json.loads((rwr_run / "eval_history.json").read_text())
    for record in history:
        assert [e["seed"] for e in record["per_episode"]] == [EVAL_SEED_BASE]
        assert record["success_once"] == sum(e["success_once"] for e in record["per_episode"]) / record["episodes"]
    checkpoint = latest_checkpoint(rwr_run)
    evaluated = subprocess.run([sys.executable, "-m", "mmada_rl.cli", "eval", "--checkpoint", str(checkpoint),
                                "--task", "PickCube-v1", "--episodes", "1", "--max-episode-steps", "10",
                                "--num-threads", "1", "--out", str(tmp_path / "eval")],
                               cwd=REPO, capture_output=True, text=True, timeout=600)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    paired = load_script("benchmarks/paired.py")
    assert paired.main(["--arm", "pretrained", f"{rwr_run}@0", "--arm", "fine-tuned", str(rwr_run),
                        "--arm", "its checkpoint", str(tmp_path / "eval" / "eval.json"), "--contrast", "2", "3",
                        "--contrast", "1", "2", "--name", "p", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "p.json").read_text())
    first, last = round(history[0]["success_once"]), round(history[-1]["success_once"])
    assert [arm["successes"] for arm in report["arms"]] == [[first], [last], [last]]
    same = report["contrasts"][0]
    assert same["only_first"] == same["only_second"] == 0 and same["pairs"] == 1
    with pytest.raises(ValueError, match="logged no evaluation at env step 7"):
        paired.main(["--arm", "a", f"{rwr_run}@7", "--arm", "b", str(rwr_run), "--out", str(tmp_path)])


def test_resume_continues_from_the_saved_counters(rwr_run, toy_pretrain_run, pick_demos, tmp_path):
    """Stopped after two iterations and resumed to the budget, the run is ``rwr_run`` bit for bit: the weights,
    optimizers, RNGs and online buffer are restored, and each iteration is one whole episode, so the one state not
    saved, the simulator's, is a fresh episode either way, from the initial state after those the first part began,
    as in the uninterrupted run (not the run's first one again)."""
    resumed = tmp_path / "resumed"
    args = toy_args(toy_pretrain_run, pick_demos, resumed, COMMON)
    older = tmp_path / "older"  # a checkpoint from before the count was saved: the envs start again, as it says
    shutil.copytree(rwr_run / "checkpoints" / "step_00000002", older / "checkpoints" / "step_00000002")
    state_file = older / "checkpoints" / "step_00000002" / TRAINER_FILE
    state = torch.load(state_file, weights_only=False)
    del state["extra"]["initial_states_begun"]
    torch.save(state, state_file)
    first, proc, old = run_recipes(
        [*args, "collector.total_env_steps=20"], [*args, "checkpoint.resume=true"],
        toy_args(toy_pretrain_run, pick_demos, older, [*COMMON, "checkpoint.resume=true", "collector.total_env_steps=20",
                                                       "eval.episodes=0"]))  # nothing left to run
    assert first.returncode == 0, first.stderr[-3000:]
    assert _checkpoint_extra(resumed / "checkpoints" / "step_00000002")["initial_states_begun"] == 2
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "iteration 2, 20 env steps, 4 online rows; training episodes continue from initial state 2" in proc.stdout
    history = json.loads((resumed / "eval_history.json").read_text())
    assert [h["env_steps"] for h in history] == [0, 20, 30] and history[-1]["updates"] == 6
    for key in ("chunk_reward", "loss", "grad_norm"):
        assert _logged(resumed, key) == _logged(rwr_run, key)
    assert _checkpoint_extra(resumed / "checkpoints" / "step_00000003")["initial_states_begun"] == 3

    assert old.returncode == 0, old.stderr[-3000:]
    assert "they start again from env.train_seed" in old.stdout


def _checkpoint_extra(path: Path) -> dict:
    """What a fine-tuning checkpoint keeps beside the weights: counters, history, initial states begun."""
    return load_checkpoint(path).trainer_state["extra"]


def _logged(run_dir: Path, name: str) -> list[tuple[str, str]]:
    """A run's CSV log of one ``train/`` scalar, as its (step, value) rows."""
    rows = (run_dir / "logs" / "scalars" / "train" / f"{name}.csv").read_text().split()
    return [tuple(row.split(",")[:2]) for row in rows]


NOISY_RETURN_TO_GO = ["eval.episodes=0", "collector.action_noise=0.1", "advantage.estimator=return_to_go",
                      "loss.rwr.weighting=signed", "loss.rwr.standardize_advantage=true"]
FAILING = [*COMMON, "eval.episodes=0", "debug.fail_after_env_steps=8", "env.num_workers=2"]


@pytest.fixture(scope="module")
def overlap_runs(toy_pretrain_run, pick_demos, tmp_path_factory) -> tuple[Path, dict[str, RecipeRun]]:
    """Runs with ``collector.overlap``, all in one process: each mode's toy run and its resumption to 50 env
    steps; each mode's run with execution noise; a run whose env worker fails (last). Returns their root directory
    (each run in ``root / name``) and each run's output by name."""
    root = tmp_path_factory.mktemp("overlap")
    runs = {}
    for overlap in ("true", "process"):
        runs[overlap] = [*COMMON, f"collector.overlap={overlap}"]
        runs[f"{overlap}_resumed"] = [*COMMON[:3], "collector.total_env_steps=50", "collector.decisions_per_batch=2",
                                      "checkpoint.interval=1", "checkpoint.keep=5", "checkpoint.resume=true",
                                      f"collector.overlap={overlap}"]
    for overlap in ("thread", "process"):
        runs[f"noisy_{overlap}"] = [*COMMON, *NOISY_RETURN_TO_GO, f"collector.overlap={overlap}"]
    runs["failing_process"] = [*FAILING, "collector.overlap=process"]
    done = run_recipes(*(toy_args(toy_pretrain_run, pick_demos, root / name.removesuffix("_resumed"), overrides)
                         for name, overrides in runs.items()))
    return root, dict(zip(runs, done))


@pytest.mark.parametrize("overlap, where", [("true", "a background thread"), ("process", "a process of its own")])
def test_overlapped_collection_trains_evaluates_checkpoints_and_resumes(rwr_run, overlap_runs, overlap, where):
    """collector.overlap: the same run as ``rwr_run`` with each next batch collected during the updates."""
    root, runs = overlap_runs
    run_dir, proc, resumed = root / overlap, runs[overlap], runs[f"{overlap}_resumed"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"each batch is collected in {where} while the previous batch's updates run" in proc.stdout
    assert "done: 30 env steps, 6 updates" in proc.stdout
    history = json.loads((run_dir / "eval_history.json").read_text())  # the first run's evaluations, the resumed one's
    assert [(h["env_steps"], h["updates"]) for h in history] == [(0, 0), (30, 6), (50, 10)]
    if overlap == "true":
        # the first batch is collected before any update, by the pretrained weights and the same RNG draws as the
        # sequential run's; later ones by weights one iteration older than the sequential run's (a process samples
        # its tokens from its own RNG)
        assert _logged(run_dir, "chunk_reward")[0] == _logged(rwr_run, "chunk_reward")[0]
    timing = run_dir / "logs" / "scalars" / "time"
    collected = [float(row.split(",")[1]) for row in (timing / "collect_ahead_s.csv").read_text().split()]
    iterations = [float(row.split(",")[1]) for row in (timing / "iteration_s.csv").read_text().split()]
    assert len(collected) == len(iterations) == 3 + 2 and all(s > 0 for s in collected + iterations)
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == [f"step_0000000{i}" for i in range(1, 6)]
    rng = load_checkpoint(run_dir / "checkpoints" / "step_00000003").trainer_state["rng"]["generators"]
    if overlap == "process":  # the tokens sampled in the collector's process: their RNG state came back and is saved
        fresh = recipe_utils().make_sampling_generator(OmegaConf.create({"seed": 0}))
        assert not torch.equal(rng["sampling"], fresh.get_state())
    else:  # they draw from the learner's own torch RNG, saved as "torch"
        assert "sampling" not in rng
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "iteration 3, 30 env steps" in resumed.stdout and "done: 50 env steps, 10 updates" in resumed.stdout
    assert "training episodes continue from initial state 3" in resumed.stdout


def test_overlapped_collection_with_execution_noise_is_the_same_run_in_a_thread_and_in_a_process(overlap_runs):
    """Greedy chunks with their own noise RNG draw nothing from the RNG the updates use, and the collector's process
    continues the learner's noise RNG: the run in a thread and in a process are the same, bit for bit."""
    root, runs = overlap_runs
    logs = []
    for name in ("noisy_thread", "noisy_process"):
        assert runs[name].returncode == 0, runs[name].stderr[-3000:]
        logs.append([_logged(root / name, key) for key in ("chunk_reward", "loss", "grad_norm")])
    assert logs[0] == logs[1] and len(logs[0][1]) == 3


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:  # the process ended meanwhile
        return b""


def test_overlap_benchmark_times_both_loops_on_real_fine_tuning_runs(toy_pretrain_run, pick_demos, tmp_path):
    bench = load_script("benchmarks/finetune_overlap.py", "finetune_overlap")
    assert bench.main(["--pretrained", str(toy_pretrain_run), "--demos", str(pick_demos), "--method",
                       "mmada_gae_noise_absorbing", "--iterations", "3", "--skip", "1", "--rounds", "1",
                       "--steps-per-iteration", "10", "--override", "collector.decisions_per_batch=2",
                       "--override", "optim.updates_per_batch=2", "--override", "env.max_episode_steps=10",
                       "--modes", "false", "process", "--collect-beside", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "finetune_overlap.json").read_text())
    rows = {r["label"]: r for r in result["results"]}
    assert list(rows) == ["sequential, 1 thread", "overlapped in a process, 1 thread",
                          "sequential, 1 thread, beside a collection-only process"]
    assert [r["beside"] for r in result["runs"]] == [False, False, True]
    # the collection-only run was stopped with its env workers when the timed run ended
    assert not [p for p in Path("/proc").glob("[0-9]*/cmdline") if b"_b1_collector" in _read_bytes(p)]
    assert rows["sequential, 1 thread"]["ratio_to_first"] == 1.0 and rows["sequential, 1 thread"]["median_collect_ahead_s"] is None
    overlapped = rows["overlapped in a process, 1 thread"]
    assert overlapped["median_collect_ahead_s"] > 0 and overlapped["median_iteration_s"] > 0
    assert all(run["iterations"] == 2 and run["env_steps_per_iteration"] == 10 for run in result["runs"])
    assert (tmp_path / "finetune_overlap.png").stat().st_size > 0
    assert "Reproduce:" in (tmp_path / "finetune_overlap.md").read_text()


def test_weight_average_is_evaluated_and_saved_beside_the_unchanged_training_and_resumes(
        rwr_run, toy_pretrain_run, pick_demos, tmp_path):
    averaged, resumed = tmp_path / "ema", tmp_path / "resumed"
    averaging = [*COMMON, "ema.enabled=true"]
    # the resumed run: the same run stopped after iteration 2 (the averaged run's first two, bit for bit:
    # test_resume_continues_from_the_saved_counters), then continued to the budget
    proc, stopped, again = run_recipes(
        toy_args(toy_pretrain_run, pick_demos, averaged, averaging),
        toy_args(toy_pretrain_run, pick_demos, resumed, [*averaging, "collector.total_env_steps=20"]),
        toy_args(toy_pretrain_run, pick_demos, resumed, [*averaging, "checkpoint.resume=true"]))
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("chunk_reward", "loss", "grad_norm"):  # the same rollouts and updates as the run without an average
        assert _logged(averaged, name) == _logged(rwr_run, name)

    def decay(n: int) -> float:  # Diffusion Policy's warm-up, from the first update on
        return 0.0 if n <= 1 else 1 - n ** -0.75

    # each iteration logs the mean decay of its two updates
    expected = [(decay(2 * i - 1) + decay(2 * i)) / 2 for i in (1, 2, 3)]
    assert [float(v) for _, v in _logged(averaged, "ema_decay")] == pytest.approx(expected)
    history = json.loads((averaged / "eval_history.json").read_text())
    assert [h["env_steps"] for h in history] == [0, 30] and history[-1]["updates"] == 6
    # the checkpoint's own weights are the plain run's; its model is their average
    check_average_beside_own_weights(averaged / "checkpoints" / "step_00000003", rwr_run / "checkpoints" / "step_00000003",
                                     updates=6)

    # from iteration 2: the average and the own weights continue where they were
    assert stopped.returncode == 0 and again.returncode == 0, (stopped.stderr + again.stderr)[-3000:]
    assert "iteration 2, 20 env steps" in again.stdout
    own_again = torch.load(resumed / "checkpoints" / "step_00000003" / "trainer.pt", weights_only=False)["extra"]
    assert own_again["ema_updates"] == 6
    assert _logged(resumed, "ema_decay")[-1] == _logged(averaged, "ema_decay")[-1]  # updates 5 and 6, not 1 and 2


VARIANTS = [
    ("ppo_group", ["algo=ppo", "advantage.estimator=group", "advantage.group_size=2", "collector.decisions_per_batch=2",
                   "loss.ppo.denoising_steps=2", "eval.episodes=1", "eval.max_episode_steps=4", "eval.sample_temperature=1.0",
                   "loss.ppo.demo_coef=0.5", "loss.ppo.tokens=action"],
     40),
    ("filtered_self_imitation", ["env.reward=sparse", "advantage.estimator=return", "loss.rwr.weighting=binary",
                                 "loss.rwr.normalize_weights=true", "eval.episodes=0"], 30),
    ("noisy_self_imitation", ["env.reward=sparse", "advantage.estimator=return", "loss.rwr.weighting=binary",
                              "loss.rwr.normalize_weights=true", "loss.rwr.weight_goal=true", "collector.action_noise=0.1",
                              "eval.episodes=0"], 30),
    ("noisy_gae_signed", ["advantage.estimator=gae", "loss.rwr.weighting=signed", "loss.rwr.standardize_advantage=true",
                          "loss.rwr.normalize_weights=true", "loss.rwr.weight_goal=true", "collector.action_noise=0.1",
                          "eval.episodes=0", "value.pretrain_steps=3"], 30),
    ("noisy_privileged_critic", ["advantage.estimator=gae", "value.input=privileged_state", "loss.rwr.weighting=signed",
                           "loss.rwr.standardize_advantage=true", "collector.action_noise=0.1", "eval.episodes=0"], 30),
    ("noisy_privileged_standardized", ["advantage.estimator=gae", "value.input=privileged_state",
                                       "value.normalize_targets=true", "loss.rwr.weighting=signed",
                                       "loss.rwr.standardize_advantage=true", "collector.action_noise=0.1",
                                       "eval.episodes=0"], 30),
    ("noisy_return_to_go", ["advantage.estimator=return_to_go", "loss.rwr.weighting=signed",
                            "loss.rwr.standardize_advantage=true", "collector.action_noise=0.1", "eval.episodes=0",
                            "optim.lr=1e-4", "optim.lr_decay=cosine"], 30),
    ("noisy_return_to_go_bf16", ["advantage.estimator=return_to_go", "loss.rwr.weighting=signed",
                                 "loss.rwr.standardize_advantage=true", "collector.action_noise=0.1", "eval.episodes=0",
                                 "optim.precision=bf16"], 30),
    ("noisy_return_to_go_baseline", ["advantage.estimator=return_to_go", "advantage.baseline_episodes=4",
                                     "loss.rwr.weighting=signed", "loss.rwr.normalize_weights=true",
                                     "collector.action_noise=0.1", "eval.episodes=0"], 30),
]


#: The ensemble's partner: the toy pretraining run's first checkpoint.
PARTNER = Path("checkpoints") / "step_00000003" / "model"
NOISY_SIGNED_PRIVILEGED = ["eval.episodes=0", "value.input=privileged_state", "loss.rwr.weighting=signed",
                           "loss.rwr.standardize_advantage=true", "collector.action_noise=0.1"]


@dataclass
class VariantRuns:
    root: Path  # each run in root / name
    runs: dict[str, RecipeRun]  # each run's output by name
    partner: dict[str, torch.Tensor]  # the ensemble partner's denoiser weights before the runs


@pytest.fixture(scope="module")
def variant_runs(toy_pretrain_run, pick_demos, tmp_path_factory) -> VariantRuns:
    """Toy runs from ``toy_pretrain_run``, all in one process: each of ``VARIANTS``; the critic warm-up's; acting
    with a frozen partner (``ensemble``) and the two configurations that refuse one."""
    root = tmp_path_factory.mktemp("variants")
    partner = {k: v.clone() for k, v in MMaDAModel.load(toy_pretrain_run / PARTNER).denoiser.state_dict().items()}
    ensemble = f"collector.ensemble_with=['{toy_pretrain_run / PARTNER}']"
    runs = {name: [*overrides, "env.max_episode_steps=10", f"collector.total_env_steps={steps}"]
            for name, overrides, steps in VARIANTS}
    runs["critic_warmup"] = [*COMMON, *NOISY_SIGNED_PRIVILEGED, "value.warmup_env_steps=20"]
    runs["ensemble"] = [*COMMON, *NOISY_SIGNED_PRIVILEGED, ensemble]
    runs["ensemble_without_noise"] = ["collector.action_noise=0", ensemble]
    runs["ensemble_with_ppo"] = ["algo=ppo", "collector.action_noise=0", ensemble]
    done = run_recipes(*(toy_args(toy_pretrain_run, pick_demos, root / name, overrides) for name, overrides in runs.items()))
    return VariantRuns(root, dict(zip(runs, done)), partner)


@pytest.mark.parametrize("name, overrides, steps", VARIANTS)
def test_advantage_variants_run(variant_runs, toy_pretrain_run, pick_demos, name, overrides, steps):
    """Episode-level advantages: PPO with group-relative returns (evaluated with sampled decoding); RWR imitating
    the successful rollouts. Per-chunk ones: the noisy rollouts' chunks weighted by their GAE advantages, signed."""
    root, proc = variant_runs.root, variant_runs.runs[name]
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"{steps} env steps" in proc.stdout and "0 updates" not in proc.stdout
    # the start-up line describes the updates this algorithm makes (PPO trains on fresh decisions only)
    assert ("epochs over each iteration's decisions" in proc.stdout) == (name == "ppo_group")
    assert ("exploration: greedy chunks + N(0, 0.1^2)" in proc.stdout) == name.startswith("noisy")
    if name == "noisy_gae_signed":  # a value network was trained (first on the demos) and some chunks were pushed down
        assert "value network fitted to the demonstrations' returns: 3 steps" in proc.stdout
        assert (root / name / "logs" / "scalars" / "value" / "pretrain_loss.csv").read_text().strip()
        scalars = root / name / "logs" / "scalars" / "train"
        assert (scalars / "value_loss.csv").read_text().strip()
        assert any(float(line.split(",")[1]) > 0 for line in (scalars / "negative_fraction.csv").read_text().splitlines())
    if name == "noisy_return_to_go":  # no critic was fitted, and the stored advantages are the returns to go
        scalars = root / name / "logs" / "scalars" / "train"
        assert not (scalars / "value_loss.csv").exists() and (scalars / "advantage_abs.csv").read_text().strip()
        rows = load_script("benchmarks/finetune_gradients.py").load_online_rows(root / name / "online_buffer")
        assert len(rows) and torch.equal(rows.get(ADVANTAGE_KEY).reshape(-1), rows.get(VALUE_TARGET_KEY).reshape(-1))
        # optim.lr_decay=cosine: each iteration's rate, logged at its env steps, falls to 0.1 x 1e-4 at the budget
        lrs = [tuple(map(float, line.split(","))) for line in (scalars / "lr.csv").read_text().split()]
        assert len(lrs) >= 2 and all(b[1] < a[1] for a, b in zip(lrs, lrs[1:]))
        assert lrs[0][1] < 1e-4 and lrs[-1][0] >= steps and lrs[-1][1] == pytest.approx(1e-5)
    if name == "noisy_return_to_go_bf16":  # the updates' forward pass in bfloat16: finite losses, float32 weights
        scalars = root / name / "logs" / "scalars" / "train"
        losses = [float(line.split(",")[1]) for line in (scalars / "loss.csv").read_text().split()]
        assert losses and all(math.isfinite(v) for v in losses)
        assert all(w.dtype == torch.float32 for w in weights(latest_checkpoint(root / name)).values())
    if name == "noisy_return_to_go_baseline":  # returns to go stored as value targets, relative ones as advantages
        rows = load_script("benchmarks/finetune_gradients.py").load_online_rows(root / name / "online_buffer")
        advantage, to_go = rows.get(ADVANTAGE_KEY).reshape(-1), rows.get(VALUE_TARGET_KEY).reshape(-1)
        assert len(rows) and not torch.equal(advantage, to_go)
        kept = load_checkpoint(root / name).trainer_state["extra"]["advantage_baseline"]
        assert kept["episodes"] == 4 and 2 <= len(kept["window"]) <= 4  # checkpointed for a resume
        common = toy_args(toy_pretrain_run, pick_demos, root / name,
                          [*(o for o in overrides if not o.startswith("advantage.baseline_episodes")),
                           "env.max_episode_steps=10", "checkpoint.resume=true"])
        shorter, off = run_recipes(
            [*common, "advantage.baseline_episodes=2", f"collector.total_env_steps={steps + 30}"],
            [*common, "advantage.baseline_episodes=0", "loss.rwr.standardize_advantage=true",
             f"collector.total_env_steps={steps + 30}"])  # the budget spent: it loads and stops
        assert shorter.returncode == 0, shorter.stderr[-3000:]
        kept = load_checkpoint(root / name).trainer_state["extra"]["advantage_baseline"]
        assert kept["episodes"] == 2 and len(kept["window"]) == 2  # the resumed run's own window length
        assert off.returncode == 0, off.stderr[-3000:]
        assert "the checkpoint's decision-index baseline (2 episodes) is not used" in off.stdout
    if name == "noisy_privileged_critic":  # GAE's critic read the simulator's state, the policy its pixels
        scalars = root / name / "logs" / "scalars" / "train"
        assert (scalars / "value_loss.csv").read_text().strip()
        value = load_checkpoint(root / name).trainer_state["extra"]["value"]
        first = next(v for k, v in value.items() if k.endswith("mlp.0.weight"))
        assert first.shape[-1] == 70  # PickCube-v1's privileged state
        assert float(value["module.count"]) > 0 and float(value["module.sum_sq"].sum()) > 0  # its input moments
        # benchmarks/critic_fit.py refits such a critic on the run's stored states and value targets
        bench = load_script("benchmarks/critic_fit.py", "critic_fit")
        out = root / "critic_fit"
        assert bench.main(["--online", str(root / name / "online_buffer"), "--steps", "3", "--holdout", "0.5",
                           "--batch-size", "4", "--hidden", "16", "--online-batch", "1", "--online-epochs", "2",
                           "--out", str(out)]) == 0
        fitted = json.loads((out / "critic_fit.json").read_text())
        assert fitted["fitted"] + fitted["held_out"] == fitted["rows"] >= 4
        assert list(fitted["results"]) == ["raw", "standardised", "standardised, clipped to [-5, 5]"]
        assert all(math.isfinite(r["held_out_mse"]) and r["held_out_mse"] >= 0 for r in fitted["results"].values())
        assert list(fitted["in_order"]) == ["targets as they are", "standardised targets (value.normalize_targets)"]
        assert all(r["batches"] == fitted["rows"] and len(r["error_by_fifth"]) == 5 for r in fitted["in_order"].values())
        assert len(fitted["advantage_target_correlation_by_fifth"]) == 5
        assert (out / "critic_fit.png").stat().st_size > 0
    if name == "noisy_privileged_standardized":  # the checkpoint holds the critic's target and input moments
        value = load_checkpoint(root / name).trainer_state["extra"]["value"]
        assert float(value["module.count"]) > 0 and float(value["module.sum_sq"]) > 0  # the value targets'
        assert float(value["module.network.count"]) > 0  # the states'
    if name == "ppo_group":  # evaluated before and after, sampling the tokens at T = 1
        history = json.loads((root / name / "eval_history.json").read_text())
        assert [h["sample_temperature"] for h in history] == [1.0, 1.0] and history[-1]["env_steps"] == steps
        # the anchor: every PPO minibatch also scored the demonstrations' denoising loss (half the toy batch of 8)
        assert "each with 4 demo windows (demo_coef 0.5)" in proc.stdout
        anchor = (root / name / "logs" / "scalars" / "train" / "loss_demo_action.csv").read_text().splitlines()
        assert anchor and all(float(line.split(",")[1]) > 0 for line in anchor)
        # PPO's diagnostics are logged once per iteration, as means over its gradient steps
        clip = (root / name / "logs" / "scalars" / "train" / "clip_fraction.csv").read_text().splitlines()
        assert clip and all(0.0 <= float(line.split(",")[1]) <= 1.0 for line in clip)


def test_acting_with_frozen_partners_collects_the_ensemble_chunk_and_trains_the_policy_alone(
        toy_pretrain_run, model, variant_runs):
    """``collector.ensemble_with``: the fine-tuned policy acts as one MMaDAEnsemble with frozen pretrained policies
    (itself first, the very object the optimizer updates); the run trains it alone and leaves the partners as
    they were; without noise, or with PPO, the option is refused."""
    utils = recipe_utils()
    partner_dir = toy_pretrain_run / PARTNER
    cfg = OmegaConf.create({"device": "cpu", "collector": {"ensemble_with": [str(partner_dir)]}})
    behaviour = utils.make_behaviour(cfg, model)
    assert isinstance(behaviour, MMaDAEnsemble) and len(behaviour.members) == 2 and behaviour.members[0] is model
    partner = behaviour.members[1]
    assert not any(p.requires_grad for p in partner.parameters()) and not partner.denoiser.training
    assert utils.make_behaviour(OmegaConf.create({"collector": {"ensemble_with": []}}), model) is model
    env = make_env("PickCube-v1", max_episode_steps=10)
    obs = env.reset(seed=0)
    env.close()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        acted = MMaDAActor(behaviour)(obs.clone()).get(("vla_action", "chunk"))
        alone = [MMaDAActor(m)(obs.clone()).get(("vla_action", "chunk")) for m in (model, partner)]
    torch.testing.assert_close(acted[..., :6], (alone[0][..., :6] + alone[1][..., :6]) / 2)  # the arm: their mean

    runs = variant_runs.runs
    run_dir, proc = variant_runs.root / "ensemble", runs["ensemble"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "exploration: the greedy mean chunk of this policy and 1 frozen others + N(0, 0.1^2)" in proc.stdout
    assert "done: 30 env steps, 6 updates" in proc.stdout
    trained = MMaDAModel.load(run_dir / "checkpoints" / "step_00000003" / "model").denoiser.state_dict()
    assert any(not torch.equal(t, trained[k]) for k, t in model.denoiser.state_dict().items())
    after = MMaDAModel.load(partner_dir).denoiser.state_dict()
    assert all(torch.equal(t, after[k]) for k, t in variant_runs.partner.items())
    # every stored decision holds the executed (ensemble + noise) chunk's tokens, under the fine-tuned policy's tokenizer
    assert len(saved_online_buffer(run_dir)) == 6
    for bad in (runs["ensemble_without_noise"], runs["ensemble_with_ppo"]):
        assert bad.returncode != 0 and "collector.ensemble_with acts with the greedy chunk averaged" in bad.stderr


def saved_online_buffer(run_dir: Path):
    """The online buffer a fine-tuning run saved in ``run_dir``, loaded as the recipe resumes it: the recipe's
    ``make_online_buffer`` on the config of the run's newest checkpoint."""
    buffer = recipe_utils().make_online_buffer(OmegaConf.create(load_checkpoint(run_dir).config))
    buffer.loads(run_dir / "online_buffer")
    return buffer


def test_critic_warmup_trains_the_critic_alone_and_keeps_its_rollouts_out_of_the_buffer(model, variant_runs):
    """``value.warmup_env_steps=20`` of a 30-step budget (three iterations of 10): the critic learns on every
    iteration's rollouts, the policy only on the last one's, and the online buffer holds only that iteration's
    decisions (the first two were scored by the cold critic)."""
    run_dir, proc = variant_runs.root / "critic_warmup", variant_runs.runs["critic_warmup"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "the critic alone learns for the first 20 env steps" in proc.stdout
    assert "done: 30 env steps, 2 updates" in proc.stdout  # two updates per iteration, the last iteration only
    scalars = run_dir / "logs" / "scalars" / "train"
    assert len((scalars / "value_loss.csv").read_text().split()) == 3
    assert [line.split(",")[0] for line in (scalars / "critic_warmup.csv").read_text().split()] == ["10", "20"]
    # the policy after the warm-up iterations is the pretrained one, bit for bit; the critic has moved
    warm = MMaDAModel.load(run_dir / "checkpoints" / "step_00000002" / "model").denoiser.state_dict()
    assert all(torch.equal(tensor, warm[name]) for name, tensor in model.denoiser.state_dict().items())
    values = [load_checkpoint(run_dir / "checkpoints" / f"step_0000000{i}").trainer_state["extra"]["value"]
              for i in (1, 2)]
    assert any(not torch.equal(values[0][k], values[1][k]) for k in values[0] if k.endswith("weight"))
    final = MMaDAModel.load(run_dir / "checkpoints" / "step_00000003" / "model").denoiser.state_dict()
    assert any(not torch.equal(tensor, final[name]) for name, tensor in model.denoiser.state_dict().items())
    assert len(saved_online_buffer(run_dir)) == 2  # collector.decisions_per_batch of the one iteration after the warm-up


@pytest.mark.parametrize("overlap", ["false", "process"])  # a thread's error reaches the same except (test_collect_ahead)
def test_env_failure_ends_the_run_with_a_clear_message_and_a_loadable_buffer(toy_pretrain_run, pick_demos, tmp_path,
                                                                             request, overlap):
    """Collected by the recipe's own process, from the command line; in a collector process, the last of the
    overlap runs' process."""
    if overlap == "false":
        run_dir = tmp_path / "failing"
        proc = run_recipe(*toy_args(toy_pretrain_run, pick_demos, run_dir, [*FAILING, "collector.overlap=false"]))
    else:
        root, runs = request.getfixturevalue("overlap_runs")
        run_dir, proc = root / "failing_process", runs["failing_process"]
    assert proc.returncode != 0
    assert "collection failed after" in proc.stderr and "injected env failure" in proc.stderr
    assert "checkpoint.resume=true" in proc.stderr
    buffer = saved_online_buffer(run_dir)
    assert len(buffer) > 0 and SEQUENCE_KEY in buffer[:1].keys(True, True)


BAD_CONFIGS = [
    (["algo=sac"], "algo='sac' is not a fine-tuning algorithm"),
    (["pretrained=null"], "pretrained=null"),
    (["demos.ratio=1.5"], "demos.ratio must lie in [0, 1]"),
    (["demos.ratio=1.0", "algo=ppo"], "needs algo=rwr"),
    (["algo=ppo", "loss.ppo.ratio_level=path", "loss.ppo.denoising_steps=2"], "the path ratio needs every step"),
    (["algo=ppo", "loss.ppo.demo_coef=1.0", "demos.ratio=0"], "raise demos.ratio"),
    (["algo=ppo", "collector.action_noise=0.1"], "path-likelihood PPO needs the sampled paths"),
    (["collector.action_noise=-0.1"], "collector.action_noise must be >= 0"),
    (["device=cuda"], "the fine-tuning recipe runs on the CPU only"),
    (["advantage.gamma=1.0"], "it needs advantage.gamma < 1"),
    (["value.pretrain_steps=-1"], "value.pretrain_steps must be >= 0"),
    (["value.pretrain_steps=5", "advantage.estimator=group"], "uses none: use advantage.estimator=gae"),
    (["value.input=pixels"], "use observation or privileged_state"),
    (["value.input=privileged_state", "advantage.estimator=return"], "uses no critic"),
    (["value.input=privileged_state", "value.pretrain_steps=5"], "hold no privileged state"),
    (["value.warmup_env_steps=-1"], "value.warmup_env_steps must be >= 0"),
    (["loss.action_mean_weight=1"], "needs ordered bin tokens (tokenizers.action_type=bins), not a VQActionTokenizer"),
    (["demos.random_shift=-1"], "demos.random_shift=-1 must be a whole number of pixels >= 0"),
    (["value.warmup_env_steps=10", "advantage.estimator=return"], "use advantage.estimator=gae or value.warmup_env_steps=0"),
    (["optim.lr_decay=linear"], "optim.lr_decay='linear'; use constant or cosine"),
    (["optim.min_lr_ratio=2"], "optim.min_lr_ratio must lie in [0, 1]"),
    (["advantage.baseline_episodes=8"], "a decision-index baseline (> 0) compares returns to go"),
    (["advantage.estimator=return_to_go", "advantage.baseline_episodes=-1"], "advantage.baseline_episodes=-1"),
    (["optim.precision=fp16"], "precision must be one of fp32, bf16, got 'fp16'"),
    (["algo=ppo", "optim.precision=bf16"], "so PPO's ratios would not start at 1"),
    (["algo=ppo", "collector.overlap=true"], "so PPO's ratios would not start at 1 on the fresh batch"),
    (["algo=ppo", "collector.overlap=process"], "collector.overlap=process collects each batch by the weights of one"),
    (["collector.overlap=sideways"], "collector.overlap='sideways'; use false, thread (or true) or process."),
]


@pytest.fixture(scope="module")
def bad_config_errors(toy_pretrain_run, pick_demos, tmp_path_factory) -> dict[str, str | None]:
    """The error the recipe ends each of ``BAD_CONFIGS`` with, all run in one process (tests/recipe_runs.py)."""
    return errors_by_config(RECIPE, BAD_CONFIGS, partial(toy_args, toy_pretrain_run, pick_demos),
                            tmp_path_factory.mktemp("bad_configs"))


@pytest.mark.parametrize("overrides, message", BAD_CONFIGS)
def test_bad_configs_fail_with_one_clear_error(bad_config_errors, overrides, message):
    check_error(bad_config_errors, overrides, message)


def test_a_bad_config_on_the_command_line_exits_with_its_message(toy_pretrain_run, pick_demos, tmp_path):
    overrides, message = BAD_CONFIGS[0]
    proc = run_recipe(*toy_args(toy_pretrain_run, pick_demos, tmp_path / "bad", overrides))
    assert proc.returncode != 0 and message in proc.stderr


def test_comparison_benchmark_builds_resumable_commands_and_reports_real_runs(rwr_run, tmp_path):
    compare = load_script("benchmarks/compare/compare.py")
    runs = tmp_path / "runs"
    out = compare.run_dir(runs, "PickCube-v1", "mmada_rwr", 0)
    fresh = compare.command("mmada_rwr", "PickCube-v1", 0, 1000, out, "runs/pretrain_{task}_s{seed}", 5, 500)
    assert "pretrained=runs/pretrain_PickCube-v1_s0" in fresh and "collector.total_env_steps=1000" in fresh
    assert "checkpoint.resume=true" not in fresh and "demos.dir=data/PickCube-v1" in fresh
    # the methods recorded before success became absorbing keep their setting; the new one takes the recipe's default
    assert "advantage.absorbing_success=false" in fresh
    assert "advantage.absorbing_success=true" in compare.command("mmada_gae_noise_absorbing", "PickCube-v1", 0, 1000, out,
                                                                 "x", 5, 500)
    privileged = compare.command("mmada_gae_noise_privileged", "PickCube-v1", 0, 1000, out, "x", 5, 500)
    assert "value.input=privileged_state" in privileged and not any("normalize_privileged" in a for a in privileged)
    raw = compare.command("mmada_gae_noise_privileged_raw", "PickCube-v1", 0, 1000, out, "x", 5, 500)
    assert "value.input=privileged_state" in raw and "value.normalize_privileged=false" in raw
    # the methods recorded before fine-tuning kept the pretraining regularisers turn them off; the _keep ones do not
    off = {"loss.proprio_drop_prob=0", "loss.action_mean_weight=0", "demos.random_shift=0"}
    assert off <= set(privileged) and off <= set(compare.command("mmada_demos_only", "PickCube-v1", 0, 1000, out, "x", 5, 500))
    keep = compare.command("mmada_gae_noise_privileged_keep", "PickCube-v1", 0, 1000, out, "x", 5, 500)
    assert set(privileged) - set(keep) == off and set(keep) <= set(privileged)  # those three alone differ
    assert not off & set(compare.command("mmada_demos_only_keep", "PickCube-v1", 0, 1000, out, "x", 5, 500))
    # the method run with its collector in a process of its own differs from it in that override alone
    headline = compare.command("mmada_return_to_go_noise_keep_lr1e4_gripper_ema", "PickCube-v1", 0, 1000, out, "x", 5, 500)
    ahead = compare.command("mmada_return_to_go_noise_keep_lr1e4_gripper_ema_process", "PickCube-v1", 0, 1000, out, "x",
                            5, 500)
    assert [a for a in ahead if a != "collector.overlap=process"] == headline and len(ahead) == len(headline) + 1
    # a method's no-RL control differs from it in the demonstrations' share of each minibatch alone; its smaller online
    # share, its longer moving average, its lower learning rate and its smaller exploration noise differ from it in that
    # share, the EMA's exponent, the rate or the noise alone (the override added, and the one it replaces where it
    # replaces one; the rest in the same order)
    for task, method, variant, replaced, override in (
            ("PushCube-v1", "mmada_return_to_go_noise_keep_lr1e4_ema", "mmada_demos_only_keep_lr1e4_ema", None,
             "demos.ratio=1.0"),
            ("PushCube-v1", "mmada_return_to_go_noise_keep_lr1e4_ema", "mmada_return_to_go_noise_keep_lr1e4_ema_demos075",
             None, "demos.ratio=0.75"),
            ("PickCube-v1", "mmada_return_to_go_noise_keep_lr1e4_gripper_ema",
             "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_long", None, "ema.power=0.9"),
            ("PickCube-v1", "mmada_return_to_go_noise_keep_lr1e4_gripper_ema",
             "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_demos075", None, "demos.ratio=0.75"),
            ("PickCube-v1", "mmada_return_to_go_noise_keep_lr1e4_gripper_ema", "mmada_return_to_go_noise_keep_gripper_ema",
             "optim.lr=1e-4", "optim.lr=3e-5"),
            ("PickCube-v1", "mmada_return_to_go_noise_keep_gripper_ema",
             "mmada_return_to_go_noise_keep_gripper_ema_noise002", "collector.action_noise=0.05",
             "collector.action_noise=0.02")):
        base = compare.command(method, task, 1, 1000, out, "x", 5, 500)
        changed = compare.command(variant, task, 1, 1000, out, "x", 5, 500)
        assert override in changed and (replaced is None or replaced in base), variant
        assert [a for a in changed if a != override] == [a for a in base if a != replaced], variant
        assert len(changed) == len(base) + (replaced is None), variant
    narrow = compare.command("mmada_rwr", "PickCube-v1", 1, 1000, out, "runs/p_s{seed}", 5, 500, "data/{task}-fov{seed}")
    assert "demos.dir=data/PickCube-v1-fov1" in narrow and "pretrained=runs/p_s1" in narrow
    bc = compare.command("bc", "PickCube-v1", 0, 0, out, "x", 5, 500, "y")
    assert "data.dir=y" in bc and not any(a.startswith("demos.dir") for a in bc)
    long = compare.command("diffusion_policy_24k", "PickCube-v1", 0, 0, out, "x", 5, 500, "y")  # 4x the steps
    assert {"algo=diffusion_policy", "optim.total_steps=24000", "data.dir=y"} <= set(long)
    narrow_demos = tmp_path / "demos_fov45"  # PPO from pixels sees through the camera of the shared demonstrations
    narrow_demos.mkdir()
    BufferMetadata(task="PickCube-v1", control_mode="pd_ee_delta_pose", obs_mode="rgb", image_size=64, action_dim=7,
                   state_dim=29, camera_fov=45.0).save(narrow_demos)
    assert "env.camera_fov=45" in compare.command("ppo_rgb", "PickCube-v1", 0, 1000, out, "x", 5, 500, str(narrow_demos))
    assert {f"data.dir={narrow_demos}", "env.camera_fov=45"} <= set(compare.command("bc", "PickCube-v1", 0, 0, out, "x", 5, 500,
                                                                                    str(narrow_demos)))
    sac = compare.command("sac_rlpd_state", "PickCube-v1", 0, 1000, out, "x", 5, 500, str(narrow_demos))
    assert not any(a.startswith("env.camera_fov") for a in sac)  # the state baselines: their own state demonstrations
    assert [a for a in sac if a.startswith("data.dir")] == ["data.dir=data/state/PickCube-v1"]
    for method in ("sac_rlpd_state", "iql_state", "bc_state", "diffusion_policy_state"):
        cmd = compare.command(method, "PickCube-v1", 2, 1000, out, "x", 5, 500, str(narrow_demos),
                              state_demos="data/dart/state/{task}-s{seed}")
        assert [a for a in cmd if a.startswith("data.dir")] == ["data.dir=data/dart/state/PickCube-v1-s2"]
    assert not any(a.startswith("data.dir") for a in compare.command("ppo_rgb", "PickCube-v1", 0, 1000, out, "x", 5, 500))
    assert not any(a.startswith("env.camera_fov") for a in compare.command("ppo_rgb", "PickCube-v1", 0, 1000, out, "x", 5, 500))
    # the ensemble method acts with the policies pretrained with the other --ensemble-seeds, its own seed skipped
    ens = compare.command("mmada_gae_noise_privileged_keep_ensemble", "PickCube-v1", 1, 1000, out, "runs/p_s{seed}", 5, 500,
                          ensemble_seeds=[0, 1, 2])
    assert "collector.ensemble_with=['runs/p_s0','runs/p_s2']" in ens and "pretrained=runs/p_s1" in ens
    assert set(ens) - set(keep) == {"collector.ensemble_with=['runs/p_s0','runs/p_s2']", "seed=1", "pretrained=runs/p_s1"}
    assert not any("ensemble_with" in a for a in compare.command("mmada_gae_noise_privileged_keep", "PickCube-v1", 0, 1000,
                                                                 out, "x", 5, 500, ensemble_seeds=[0, 1]))
    with pytest.raises(SystemExit):  # an ensemble method with no partner: refused before any run starts
        compare.main(["run", "--methods", "mmada_gae_noise_privileged_keep_ensemble", "--seeds", "0", "--ensemble-seeds", "0"])
    sampled = compare.command("mmada_ppo_group", "PickCube-v1", 0, 1000, out, "x", 5, 500, eval_sample_temperature=1.0)
    assert "eval.sample_temperature=1.0" in sampled and "eval.sample_temperature=1.0" not in fresh
    assert not any(a.startswith("eval.sample") for a in compare.command("bc", "PickCube-v1", 0, 0, out, "x", 5, 500,
                                                                        eval_sample_temperature=1.0))
    import shutil

    shutil.copytree(rwr_run, out)  # a real (toy) fine-tuning run in the benchmark's layout
    assert "checkpoint.resume=true" in compare.command("mmada_rwr", "PickCube-v1", 0, 1000, out, "x", 5, 500)
    assert compare.finished(out, True, 30) and not compare.finished(out, True, 1000)  # a larger budget extends it
    assert not compare.finished(runs / "absent", False, 0)
    second = compare.run_dir(runs, "PickCube-v1", "mmada_rwr", 1)  # a second seed: the report averages them
    shutil.copytree(rwr_run, second)
    record = json.loads((second / "eval_history.json").read_text())
    record[0]["success_once"] = 1.0 - record[0]["success_once"]  # so the mean differs from either seed
    (second / "eval_history.json").write_text(json.dumps(record))
    assert compare.main(["report", "--runs", str(runs), "--out", str(tmp_path / "results"), "--at", "0", "30"]) == 0
    table = (tmp_path / "results" / "compare.md").read_text()
    assert "reward-weighted diffusion (ours)" in table and "| 30 |" in table
    assert "at equal online env steps" in table and "| 0.50 |" in table  # seeds at s and 1 - s at env step 0
    history = [{"env_steps": 0, "success_once": 0.2}, {"env_steps": 4135, "success_once": 0.5}]
    assert compare.success_at(history, 4000) == 0.5 and compare.success_at(history, 0) == 0.2
    assert compare.success_at(history, 8000) is None  # no evaluation within 10% of it
    assert (tmp_path / "results" / "compare.png").stat().st_size > 0
    payload = json.loads((tmp_path / "results" / "compare.json").read_text())
    assert payload["results"]["PickCube-v1"]["mmada_rwr"]["histories"]["s0"][-1]["env_steps"] == 30
    # the training rollouts: the episodes the run's sampled policy ended while collecting, pooled per window
    ended = compare.logged(out, "train/episodes")
    assert ended and max(ended) <= 30
    rollouts = payload["results"]["PickCube-v1"]["mmada_rwr"]["rollouts"]["s0"]
    assert sum(n for _, n in rollouts) == sum(ended.values()) and all(0 <= k <= n for k, n in rollouts)
    assert "Training rollouts" in table
    scalars = tmp_path / "resumed_run" / "logs" / "scalars" / "train"  # interrupted after 30, resumed from 10
    scalars.mkdir(parents=True)
    (scalars / "episodes.csv").write_text("10,2\n20,2\n30,4\n20,1\n30,2\n40,2\n")
    (scalars / "success_rate.csv").write_text("10,0.5\n20,1.0\n30,0.25\n20,1.0\n30,0.5\n40,0.0\n")
    assert compare.logged(tmp_path / "resumed_run", "train/episodes") == {10: 2, 20: 1, 30: 2, 40: 2}
    assert compare.training_rollouts(tmp_path / "resumed_run", 20) == [(2, 3), (1, 4)]
    assert compare.training_rollouts(tmp_path / "absent", 20) == []
    with pytest.raises(SystemExit):
        compare.main(["report", "--runs", str(runs), "--window", "0"])
    # a second, named run directory (the same method from another starting point) reported beside the first
    other = tmp_path / "other_runs"
    shutil.copytree(rwr_run, compare.run_dir(other, "PickCube-v1", "mmada_rwr", 0))
    both = tmp_path / "both"
    assert compare.main(["report", "--runs", str(runs), f"block-causal={other}", "--out", str(both), "--at", "30"]) == 0
    payload = json.loads((both / "compare.json").read_text())
    entries = payload["results"]["PickCube-v1"]
    assert set(entries) == {"mmada_rwr", "mmada_rwr@block-causal"} and payload["runs"]["block-causal"] == str(other)
    assert list(entries["mmada_rwr@block-causal"]["histories"]) == ["s0"] and len(entries["mmada_rwr"]["histories"]) == 2
    table = (both / "compare.md").read_text()
    assert "reward-weighted diffusion (ours) [block-causal]" in table
    own = entries["mmada_rwr@block-causal"]["histories"]["s0"][-1]["success_once"]
    assert f"| {own:.2f} |" in table.split("at equal online env steps")[1].split("[block-causal]")[1].splitlines()[0]
    for bad in ([str(runs), str(other)], [f"=={other}"], [f"x={runs}", f"x={other}"]):  # two unnamed; no name; one name twice
        with pytest.raises(SystemExit):
            compare.main(["report", "--runs", *bad, "--out", str(tmp_path / "bad")])


def test_comparison_help_lists_every_method_with_its_label(capsys):
    compare = load_script("benchmarks/compare/compare.py")
    with pytest.raises(SystemExit):
        compare.main(["run", "--help"])
    text = capsys.readouterr().out
    assert "--methods METHOD [METHOD ...]" in text
    listed = text.split("methods:\n", 1)[1].splitlines()
    assert [line.split()[0] for line in listed if line.strip()] == list(compare.METHODS)
    assert "SAC + demos (RLPD) [privileged state (reference)]" in text
    with pytest.raises(SystemExit):
        compare.main(["run", "--methods", "no_such_method"])
    assert "invalid choice: 'no_such_method'" in capsys.readouterr().err


def test_gradient_diagnostic_reads_a_real_run(rwr_run, toy_pretrain_run, pick_demos, tmp_path):
    bench = load_script("benchmarks/finetune_gradients.py")
    code = bench.main(["--pretrained", str(toy_pretrain_run), "--online", str(rwr_run / "online_buffer"), "--demos", str(pick_demos),
                       "--minibatches", "3", "--batch-size", "1", "--out", str(tmp_path)])
    assert code == 0
    result = json.loads((tmp_path / "finetune_gradients.json").read_text())
    assert result["online_rows"] == 6 and set(result["sources"]) == {
        "demonstrations", "online, advantage > 0", "online, all rows", "online, all rows, zero-mean signed advantage weights"}
    for by_part in result["sources"].values():
        for r in by_part.values():
            assert r["minibatches"] == 3 and len(r["cos_pairs_all"]) == 3 and -1 <= r["cos_pairs"] <= 1 and r["mean_norm"] > 0
    with pytest.raises(FileNotFoundError, match="no online buffer"):
        bench.main(["--pretrained", str(toy_pretrain_run), "--online", str(tmp_path), "--demos", str(pick_demos)])


def test_replayed_steps_benchmark_measures_cost_and_fidelity(toy_pretrain_run, tmp_path):
    bench = load_script("benchmarks/path_ppo_steps.py")
    code = bench.main(["--pretrained", str(toy_pretrain_run), "--task", "PickCube-v1", "--decisions", "2", "--steps", "1",
                       "--draws", "2", "--out", str(tmp_path)])
    assert code == 0
    result = json.loads((tmp_path / "path_ppo_steps.json").read_text())
    (record,) = result["records"]
    assert record["denoising_steps"] == 1 and record["num_steps"] > 1
    assert -1 <= record["cos_to_full_min"] <= record["cos_to_full_mean"] <= 1 and record["norm_ratio_mean"] > 0
    assert (tmp_path / "path_ppo_steps.png").exists() and "1 of" in (tmp_path / "path_ppo_steps.md").read_text()
    with pytest.raises(SystemExit):  # as many replayed steps as the policy decodes: no subset
        bench.main(["--pretrained", str(toy_pretrain_run), "--task", "PickCube-v1", "--decisions", "1",
                    "--steps", str(record["num_steps"]), "--out", str(tmp_path)])


@pytest.mark.parametrize("config, method, task, demos", [
    ("pickcube_cpu", "mmada_return_to_go_noise_keep_lr1e4_gripper_ema", "PickCube-v1", "data/dart/PickCube-v1-fov45"),
    ("pushcube_cpu", "mmada_return_to_go_noise_keep_lr1e4_ema_demos075", "PushCube-v1", "data/dart/PushCube-v1-fov60"),
])
def test_task_config_is_the_recorded_method_of_its_figure(config, method, task, demos):
    """``--config-name pickcube_cpu`` is ``maniskill.yaml`` with the overrides of the comparison's
    ``mmada_return_to_go_noise_keep_lr1e4_gripper_ema`` (the 0.54 -> 0.74 runs), ``pushcube_cpu`` with those of
    ``mmada_return_to_go_noise_keep_lr1e4_ema_demos075`` (the 0.93 -> 0.90 runs), each on its pretraining config's
    DART demonstrations and run names, evaluated every 10k env steps."""
    from hydra import compose, initialize_config_dir

    compare = load_script("benchmarks/compare/compare.py")
    args = compare.METHODS[method][2]
    assert args[:3] == ["recipes/finetune/finetune.py", "--config-name", "maniskill"]
    with initialize_config_dir(config_dir=str(RECIPE.parent / "config"), version_base=None):
        # the comparison names the task on each run's command line
        ours, recorded = compose(config_name=config), compose(config_name="maniskill", overrides=[*args[3:], f"env.task={task}"])
    assert (ours.pretrained, ours.demos.dir, ours.demos.action_noise) == (f"runs/{config}_s0", demos, 0.1)
    assert (ours.env.task, ours.eval.interval_env_steps, ours.eval.episodes) == (task, 10000, 50)
    for cfg in (ours, recorded):  # what the comparison sets per run, and where the files go
        for key in ("run_dir", "pretrained", "demos.dir", "demos.action_noise", "eval.interval_env_steps", "eval.episodes"):
            OmegaConf.update(cfg, key, None)
    assert OmegaConf.to_container(ours) == OmegaConf.to_container(recorded)
