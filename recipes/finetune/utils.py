"""Factories and data plumbing of the fine-tuning recipe: each ``make_*`` turns one config section into objects."""
from __future__ import annotations

import copy
import json
from dataclasses import asdict
from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
from torchrl.envs import Transform
from torchrl.envs.utils import ExplorationType
from torchrl.objectives.value import GAE

from mmada_rl import training
from mmada_rl.baselines import NormalizationStats
from mmada_rl.baselines.encoders import EncoderConfig
from mmada_rl.data import WINDOW_SKIPS, DemoBuffer, RandomShift, check_shift, make_window_buffer, window_skips
from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY
from mmada_rl.diffusion.schedules import check_probability
from mmada_rl.diffusion.sampler import MaskedDiffusionSampler, SamplerConfig
from mmada_rl.envs.maniskill import EnvConfig, make_env, privileged_state_dim
from mmada_rl.evaluation import EVAL_SEED_BASE, resolve_model_dir
from mmada_rl.envs.maniskill import WORKER_SEED_STRIDE
from mmada_rl.keys import (
    ACTION_GRIPPER_ONLY_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_TOKENS_KEY,
    ADVANTAGE_KEY,
    GOAL_IMAGE_KEY,
    GROUP_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    IS_DEMO_KEY,
    PRIVILEGED_STATE_KEY,
    SEQUENCE_KEY,
    STATE_KEY,
    STEP_KEY,
    SUCCESS_KEY,
    VALUE_TARGET_KEY,
)
from mmada_rl.objectives import MaskedDiffusionLoss, PathPPOLoss, RewardWeightedDiffusionLoss
from mmada_rl.objectives.advantages import (
    DecisionIndexBaseline,
    absorbing_success_reward,
    group_relative_advantages,
    returns_to_go,
)
from mmada_rl.policy import ExecutionNoise, MMaDAActor, MMaDAEnsemble, MMaDAModel
from mmada_rl.policy.actor import DECODING_PATH_KEY
from mmada_rl.policy.execution import PolicyEnv, make_policy_env
from mmada_rl.policy.value import (
    PrivilegedValueNetwork,
    StandardizedValue,
    ValueNetwork,
    make_value_operator,
    value_step,
)
from mmada_rl.training.checkpoint import CONFIG_FILE
from mmada_rl.training.demos import open_demos

PREFIX = "[finetune]"
ALGOS = ("rwr", "ppo")
ESTIMATORS = ("gae", "group", "return", "return_to_go")
#: what GAE's critic reads: the policy's observation (image and proprio state) or the simulator's privileged state
VALUE_INPUTS = ("observation", "privileged_state")
#: the policy's learning rate over the env-step budget (``optim.lr_decay``): ``optim.lr`` throughout, or a cosine decay
LR_DECAYS = ("constant", "cosine")


def check_config(cfg: DictConfig) -> None:
    """Fail early, with one sentence, on settings that cannot work together."""
    training.require_cpu(cfg, "fine-tuning")
    if cfg.algo not in ALGOS:
        raise ValueError(f"algo={cfg.algo!r} is not a fine-tuning algorithm; use algo=rwr or algo=ppo.")
    if cfg.advantage.estimator not in ESTIMATORS:
        raise ValueError(f"advantage.estimator={cfg.advantage.estimator!r}; use gae, group, return or return_to_go.")
    baseline_episodes = int(cfg.advantage.get("baseline_episodes", 0))
    if baseline_episodes < 0 or (baseline_episodes > 0 and cfg.advantage.estimator != "return_to_go"):
        raise ValueError(f"advantage.baseline_episodes={baseline_episodes!r}: a decision-index baseline (> 0) compares "
                         "returns to go (advantage.estimator=return_to_go); 0 turns it off.")
    if cfg.pretrained is None:
        raise ValueError("pretrained=null: pass the pretraining run (pretrained=runs/pretrain_...) or a checkpoint/model directory.")
    if not 0.0 <= float(cfg.demos.ratio) <= 1.0:
        raise ValueError(f"demos.ratio must lie in [0, 1], got {cfg.demos.ratio!r}.")
    if float(cfg.demos.ratio) == 1.0 and cfg.algo != "rwr":
        raise ValueError("demos.ratio=1 (updates on demonstrations only, the no-RL control) needs algo=rwr.")
    noise = action_noise(cfg)
    if noise < 0:
        raise ValueError(f"collector.action_noise must be >= 0 (0: sampled tokens), got {noise!r}.")
    if ensemble_partners(cfg) and not (noise > 0 and cfg.algo == "rwr"):
        raise ValueError("collector.ensemble_with acts with the greedy chunk averaged over the policies (no member's "
                         "sample): it needs algo=rwr and collector.action_noise > 0 to explore around that chunk.")
    if noise > 0 and cfg.algo != "rwr":
        raise ValueError("collector.action_noise > 0 stores the executed actions' tokens, which no decoding path produced; "
                         "path-likelihood PPO needs the sampled paths: use algo=rwr or collector.action_noise=0.")
    training.autocast(cfg.optim.precision)  # an unknown optim.precision fails here
    if cfg.optim.precision != "fp32" and cfg.algo != "rwr":
        raise ValueError(f"optim.precision={cfg.optim.precision} computes the updates' log-probabilities in lower precision "
                         "than the sampler recorded them, so PPO's ratios would not start at 1: use algo=rwr or "
                         "optim.precision=fp32.")
    overlap = collects_ahead(cfg)  # an unknown collector.overlap fails here
    if overlap and cfg.algo != "rwr":
        raise ValueError(f"collector.overlap={overlap} collects each batch by the weights of one iteration earlier, so "
                         "PPO's ratios would not start at 1 on the fresh batch it trains on: use algo=rwr or "
                         "collector.overlap=false.")
    if cfg.algo == "ppo" and float(cfg.loss.ppo.demo_coef) < 0:
        raise ValueError(f"loss.ppo.demo_coef must be >= 0, got {cfg.loss.ppo.demo_coef!r}.")
    if cfg.algo == "ppo" and float(cfg.loss.ppo.demo_coef) > 0 and split_batch(cfg)[1] == 0:
        raise ValueError("loss.ppo.demo_coef > 0 draws demos.ratio x replay_buffer.batch_size demonstration windows per "
                         "minibatch; with demos.ratio=0 that is none: raise demos.ratio.")
    value_steps = int(cfg.value.get("pretrain_steps") or 0)
    if value_steps < 0:
        raise ValueError(f"value.pretrain_steps must be >= 0, got {value_steps}.")
    if value_steps > 0 and cfg.advantage.estimator != "gae":
        raise ValueError(f"value.pretrain_steps > 0 fits GAE's critic, but advantage.estimator={cfg.advantage.estimator} "
                         "uses none: use advantage.estimator=gae or value.pretrain_steps=0.")
    warmup = critic_warmup_steps(cfg)
    if warmup < 0:
        raise ValueError(f"value.warmup_env_steps must be >= 0, got {warmup}.")
    if warmup > 0 and cfg.advantage.estimator != "gae":
        raise ValueError(f"value.warmup_env_steps > 0 trains GAE's critic alone first, but advantage.estimator="
                         f"{cfg.advantage.estimator} uses none: use advantage.estimator=gae or value.warmup_env_steps=0.")
    if value_input(cfg) not in VALUE_INPUTS:
        raise ValueError(f"value.input={value_input(cfg)!r}; use observation or privileged_state.")
    if privileged_critic(cfg) and cfg.advantage.estimator != "gae":
        raise ValueError(f"value.input=privileged_state chooses what GAE's critic reads, but advantage.estimator="
                         f"{cfg.advantage.estimator} uses no critic: use advantage.estimator=gae or value.input=observation.")
    if privileged_critic(cfg) and value_steps > 0:
        raise ValueError("value.pretrain_steps > 0 fits the critic on the demonstrations, which hold no privileged state: "
                         "use value.pretrain_steps=0 or value.input=observation.")
    if absorbs_success(cfg) and not 0.0 < float(cfg.advantage.gamma) < 1.0:
        raise ValueError(f"advantage.absorbing_success=true values a success at 1 / (1 - gamma): it needs "
                         f"advantage.gamma < 1, got {cfg.advantage.gamma!r}.")
    if cfg.optim.lr_decay not in LR_DECAYS:
        raise ValueError(f"optim.lr_decay={cfg.optim.lr_decay!r}; use constant or cosine.")
    if not 0.0 <= float(cfg.optim.min_lr_ratio) <= 1.0:
        raise ValueError(f"optim.min_lr_ratio must lie in [0, 1], got {cfg.optim.min_lr_ratio!r}.")
    check_train_seeds(cfg)


# -- policy -------------------------------------------------------------------------
def load_pretrained(cfg: DictConfig) -> MMaDAModel:
    """The pretrained policy (a pretraining run directory, a checkpoint, or a saved model)."""
    return MMaDAModel.load(resolve_model_dir(cfg.pretrained), device=cfg.device)


def action_noise(cfg: DictConfig) -> float:
    """``collector.action_noise`` (0 when absent): the std of the Gaussian exploration around greedy chunks."""
    return float(cfg.collector.get("action_noise") or 0.0)


OVERLAP_MODES = ("thread", "process")


def collects_ahead(cfg: DictConfig) -> str | None:
    """``collector.overlap``: where the next batch is collected while this one's updates run, ``"thread"`` (also
    ``true``) or ``"process"``; ``None`` for false (the default): collection and updates take turns."""
    mode = cfg.collector.get("overlap", False)
    if mode is False or mode is None:
        return None
    if mode is True:
        return "thread"
    if mode not in OVERLAP_MODES:
        raise ValueError(f"collector.overlap={mode!r}; use false, thread (or true) or process.")
    return str(mode)


def critic_warmup_steps(cfg: DictConfig) -> int:
    """``value.warmup_env_steps`` (0 when absent): the online env steps on which GAE's critic learns alone."""
    return int(cfg.value.get("warmup_env_steps") or 0)


def exploration_sampler(cfg: DictConfig, model: MMaDAModel) -> MaskedDiffusionSampler:
    """The model's sampler at ``collector.temperature``, used while collecting only; with
    ``collector.action_noise > 0`` the model's own sampler (greedy chunks, then noise).

    Evaluation keeps the model's own sampler: greedy decoding commits positions in
    order of their (temperature-scaled) confidence, so the temperature changes
    greedy chunks too, and every evaluation must use the same one.
    """
    if action_noise(cfg) > 0:
        return model.sampler
    sampler = asdict(model.sampler.config)
    sampler["temperature"] = float(cfg.collector.temperature)
    return MaskedDiffusionSampler(SamplerConfig(**sampler))


def make_env_config(cfg: DictConfig, model: MMaDAModel) -> EnvConfig:
    e = cfg.env
    return EnvConfig(
        task=e.task, image_size=model.image_size, camera_fov=model.config.camera_fov_for(e.task), control_mode=e.control_mode,
        reward=e.reward,
        max_episode_steps=e.max_episode_steps, num_workers=int(e.num_workers), train_seed=int(e.train_seed),
        group_size=int(cfg.advantage.group_size) if cfg.advantage.estimator == "group" else 1,
        privileged_state=privileged_critic(cfg),
    )


class FailAfterSteps(Transform):
    """Fault injection for tests: raise inside the env after ``steps`` steps."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps, self.count = int(steps), 0

    def _step(self, tensordict, next_tensordict):
        self.count += 1
        if self.count > self.steps:
            raise RuntimeError(f"injected env failure after {self.steps} steps (debug.fail_after_env_steps)")
        return next_tensordict

    def _reset(self, tensordict, tensordict_reset):
        return tensordict_reset


class _FailAfter:
    def __init__(self, steps: int) -> None:
        self.steps = steps

    def __call__(self) -> FailAfterSteps:
        return FailAfterSteps(self.steps)


def initial_states_begun(batch: TensorDictBase, cfg: DictConfig, begun: int = 0) -> int:
    """How many initial states the training envs have begun, once ``batch`` is collected: the most of any worker.

    Worker ``w``'s ``i``-th initial state is seed ``env.train_seed + w * WORKER_SEED_STRIDE + i``
    (:class:`~mmada_rl.envs.maniskill.SeedSchedule`), read from the batch's episode seeds; ``begun`` is the count
    before it. Checkpoints keep the count, so that a resumed run's envs start new initial states
    (:func:`with_initial_states_begun`) instead of the run's first ones again."""
    index = (batch.get(GROUP_KEY).reshape(-1) - int(cfg.env.train_seed)) % WORKER_SEED_STRIDE
    return max(int(begun), int(index.max()) + 1 if index.numel() else 0)


def with_initial_states_begun(cfg: DictConfig, begun: int) -> DictConfig:
    """``cfg`` with every training worker's first initial state ``begun`` further on (``env.train_seed + begun``):
    the config a resumed run builds its training envs from. ``cfg`` itself when ``begun`` is 0.

    Raises:
        ValueError: if the shifted seeds would reach the next worker's or the evaluation seeds.
    """
    if not begun:
        return cfg
    if begun >= WORKER_SEED_STRIDE:
        raise ValueError(f"{begun} initial states begun per worker reach the next worker's seeds "
                         f"(each worker has {WORKER_SEED_STRIDE}); start a new run with another env.train_seed.")
    shifted = copy.deepcopy(cfg)
    shifted.env.train_seed = int(cfg.env.train_seed) + int(begun)
    check_train_seeds(shifted)
    return shifted


def check_train_seeds(cfg: DictConfig) -> None:
    """The training envs' seeds (``env.train_seed`` onwards, :data:`WORKER_SEED_STRIDE` per worker) stay below the
    evaluation seeds."""
    last = int(cfg.env.train_seed) + int(cfg.env.num_workers) * WORKER_SEED_STRIDE
    if last > EVAL_SEED_BASE:
        raise ValueError(f"env.train_seed={cfg.env.train_seed} with {cfg.env.num_workers} workers reaches seed {last}, "
                         f"into the evaluation seeds (>= {EVAL_SEED_BASE}); lower it.")


def make_noise_generator(cfg: DictConfig) -> torch.Generator | None:
    """The RNG of :class:`~mmada_rl.policy.ExecutionNoise` (checkpointed with the run), or ``None`` without noise."""
    return torch.Generator().manual_seed(int(cfg.seed)) if action_noise(cfg) > 0 else None


def ensemble_partners(cfg: DictConfig) -> list[str]:
    """``collector.ensemble_with``: the frozen policies the fine-tuned one acts together with (none by default)."""
    return [str(p) for p in (cfg.collector.get("ensemble_with") or [])]


def make_behaviour(cfg: DictConfig, model: MMaDAModel) -> MMaDAModel | MMaDAEnsemble:
    """What acts while collecting: ``model`` itself, or with ``collector.ensemble_with`` an
    :class:`~mmada_rl.policy.MMaDAEnsemble` of ``model`` (first: its tokenizer encodes the executed chunk) and
    those policies, loaded frozen. The ensemble holds ``model`` itself, so every update reaches the acting
    ensemble; evaluation and checkpoints are of ``model`` alone."""
    partners = ensemble_partners(cfg)
    if not partners:
        return model
    frozen = [MMaDAModel.load(resolve_model_dir(p), device=cfg.device).eval().requires_grad_(False) for p in partners]
    return MMaDAEnsemble([model, *frozen])


def make_policy_env_for(cfg: DictConfig, model: MMaDAModel, noise_generator: torch.Generator | None = None) -> PolicyEnv:
    """The training env: chunks of ``execute_steps`` actions, each with its discounted reward sum; with
    ``collector.action_noise > 0`` the policy is the actor wrapped in :class:`~mmada_rl.policy.ExecutionNoise`,
    and with ``collector.ensemble_with`` the actor runs :func:`make_behaviour`'s ensemble."""
    fail = cfg.debug.fail_after_env_steps
    env = make_env(make_env_config(cfg, model), extra_transform=_FailAfter(int(fail)) if fail else None)
    actor = MMaDAActor(make_behaviour(cfg, model), execute_steps=cfg.collector.execute_steps)
    penv = make_policy_env(env, actor, chunk_gamma=float(cfg.advantage.gamma))
    if action_noise(cfg) > 0:
        penv = penv._replace(policy=ExecutionNoise(penv.policy, action_noise(cfg), generator=noise_generator))
    return penv


def acting_policy(cfg: DictConfig, model: MMaDAModel) -> MMaDAModel:
    """What acts while ``model`` trains (``collector.overlap``): a frozen copy of it in eval mode
    (:func:`~mmada_rl.training.acting_copy`) with the exploration sampler."""
    acting = training.acting_copy(model)
    acting.sampler = exploration_sampler(cfg, acting)
    return acting


SAMPLING_SEED_OFFSET = 7919  # the collector process's torch RNG (sampled decoding): seed + this


def make_sampling_generator(cfg: DictConfig) -> torch.Generator:
    """The RNG of the tokens :class:`ActingCollector`'s process samples (``collector.overlap=process``), held by the
    learner and checkpointed with the run: its state travels with each batch request and back, so a resumed run
    continues the draws. Seeded from ``seed + SAMPLING_SEED_OFFSET``, a stream apart from the learner's."""
    return torch.Generator().manual_seed(int(cfg.seed) + SAMPLING_SEED_OFFSET)


class ActingCollector:
    """Builds, in the collector's own process (``collector.overlap=process``), what collects there: a frozen copy of
    the pretrained policy with the exploration sampler, its noise RNG, the training env and TorchRL's collector.
    The learner's weights and the RNGs' states arrive with each batch request
    (:class:`~mmada_rl.training.CollectAheadProcess`): ``noise`` (:func:`make_noise_generator`) and ``sampling``
    (:func:`make_sampling_generator`), the state of the process's own torch RNG, which the tokens sampled at
    ``collector.temperature`` draw from. Picklable: it holds the config only."""

    def __init__(self, cfg: DictConfig) -> None:
        self.cfg = cfg

    def __call__(self) -> training.CollectorParts:
        cfg = self.cfg
        acting = acting_policy(cfg, load_pretrained(cfg))
        generator = make_noise_generator(cfg)
        collector = make_collector(cfg, make_policy_env_for(cfg, acting, generator))
        generators = {"sampling": torch.default_generator} | ({"noise": generator} if generator is not None else {})
        return training.CollectorParts(iter(collector), acting, generators, collector.shutdown)


def make_collector(cfg: DictConfig, penv: PolicyEnv) -> Collector:
    """TorchRL's collector running the actor with sampled decoding, or greedy decoding when
    ``collector.action_noise > 0`` explores by noise on the executed actions instead."""
    exploration = ExplorationType.DETERMINISTIC if action_noise(cfg) > 0 else ExplorationType.RANDOM
    return Collector(
        penv.env, penv.policy, frames_per_batch=int(cfg.collector.decisions_per_batch), total_frames=-1,
        exploration_type=exploration, device="cpu",
    )


# -- value and advantages -------------------------------------------------------------
def value_input(cfg: DictConfig) -> str:
    """What GAE's critic reads (``value.input``, one of :data:`VALUE_INPUTS`; ``observation`` when unset)."""
    return cfg.value.get("input", VALUE_INPUTS[0])


def privileged_critic(cfg: DictConfig) -> bool:
    """Whether GAE's critic reads the simulator's privileged state (``value.input=privileged_state``); the training
    env then also gives it, and the policy still reads only its own observation."""
    return value_input(cfg) == "privileged_state"


def make_value(cfg: DictConfig, model: MMaDAModel, demos: DemoBuffer):
    """Chunk-level value network as a ``ValueOperator``, with its optimizer: an encoder of the image and the proprio
    state and an MLP head, or (``value.input=privileged_state``) an MLP over the simulator's state; with
    ``value.normalize_targets`` it learns the standardised targets (:class:`~mmada_rl.policy.value.StandardizedValue`)."""
    if privileged_critic(cfg):
        net = PrivilegedValueNetwork(privileged_state_dim(cfg.env.task), hidden=int(cfg.value.hidden),
                                     normalize=bool(cfg.value.get("normalize_privileged", True)))
    else:
        stats = NormalizationStats.from_buffer(demos)
        net = ValueNetwork(EncoderConfig(**cfg.value.encoder), image_size=model.image_size,
                           state_dim=demos.metadata.state_dim, hidden=int(cfg.value.hidden),
                           state_mean=stats.state_mean, state_std=stats.state_std)
    if cfg.value.get("normalize_targets", False):
        net = StandardizedValue(net)
    operator = make_value_operator(net).to(cfg.device)
    optimizer = training.make_optimizer(operator.parameters(), lr=float(cfg.value.lr), weight_decay=0.0)
    return operator, optimizer


def demo_value_targets(cfg: DictConfig, demos: DemoBuffer) -> torch.Tensor:
    """The discounted return from every stored demonstration step (``advantage.gamma`` per step), float ``[N]`` in
    storage order: the value the critic should give the demonstrator's states. An episode that ended in success
    continues at ``1 / (1 - gamma)`` with ``advantage.absorbing_success`` (as the online chunks do), at 0 otherwise."""
    gamma, stored = float(cfg.advantage.gamma), demos.storage[: len(demos)]
    targets = torch.zeros(len(demos))
    for start, stop in demos.episode_bounds():
        last = stored[stop - 1]
        success = bool(last.get(("next", SUCCESS_KEY)).any()) and bool(last.get(("next", "terminated")).any())
        final = 1.0 / (1.0 - gamma) if success and absorbs_success(cfg) else 0.0
        targets[start:stop] = returns_to_go(stored[start:stop].get(("next", "reward")).reshape(-1), gamma, final)
    return targets


def pretrain_value(cfg: DictConfig, value_op, value_optim, demos: DemoBuffer) -> float | None:
    """``value.pretrain_steps`` regression steps of the critic on the demonstrations' returns
    (:func:`demo_value_targets`, minibatches of ``value.batch_size`` steps drawn with the run's seed), before any
    online data, so that the first advantages are not the returns of a critic that still says 0. Returns the
    mean loss of the last tenth of the steps (None: 0 steps, nothing done)."""
    from tqdm.auto import tqdm

    steps = int(cfg.value.get("pretrain_steps") or 0)
    if steps == 0:
        return None
    targets, stored = demo_value_targets(cfg, demos), demos.storage[: len(demos)]
    generator = torch.Generator().manual_seed(int(cfg.seed))
    size, losses = int(cfg.value.batch_size), []
    for _ in tqdm(range(steps), desc="value on the demonstrations' returns", unit="step"):
        idx = torch.randint(len(demos), (size,), generator=generator)
        losses.append(value_step(value_op, value_optim, stored[idx], targets[idx]))
    tail = losses[-max(1, steps // 10):]
    return sum(tail) / len(tail)


def decision_discount(cfg: DictConfig, model: MMaDAModel) -> float:
    """The discount between consecutive decisions, ``gamma ** k``: they are ``k`` env steps apart (``k`` executed
    actions per chunk, the whole chunk unless ``collector.execute_steps``)."""
    k = int(cfg.collector.execute_steps or model.config.chunk_size)
    return float(cfg.advantage.gamma) ** k


def make_gae(cfg: DictConfig, value_operator, model: MMaDAModel) -> GAE:
    """TorchRL's GAE over decisions, discounted by :func:`decision_discount`."""
    return GAE(gamma=decision_discount(cfg, model), lmbda=float(cfg.advantage.lmbda), value_network=value_operator,
               average_gae=False)


def executed_steps(batch: TensorDictBase) -> torch.Tensor:
    """Env steps each decision executed (``k``, fewer when the episode ended inside the chunk), long ``[*B]``."""
    return (batch.get(("next", STEP_KEY)) - batch.get(STEP_KEY)).reshape(batch.shape)


def absorbs_success(cfg: DictConfig) -> bool:
    """``advantage.absorbing_success`` (false when absent)."""
    return bool(cfg.advantage.get("absorbing_success", False))


def absorb_success(cfg: DictConfig, batch: TensorDictBase) -> None:
    """With ``advantage.absorbing_success``, add to each chunk that ended its episode in success the discounted value of
    staying there at the best per-step reward (:func:`~mmada_rl.objectives.advantages.absorbing_success_reward`), in
    place, before any advantage is computed; a no-op otherwise."""
    if not absorbs_success(cfg):
        return
    key = ("next", "reward")
    reward = batch.get(key)
    success = batch.get(("next", SUCCESS_KEY)) & batch.get(("next", "terminated"))
    batch.set(key, absorbing_success_reward(reward, success.reshape(reward.shape), executed_steps(batch),
                                            float(cfg.advantage.gamma)))


def decision_rows(model: MMaDAModel, batch: TensorDictBase) -> TensorDict:
    """Training rows of collected decisions (flattened to ``[N]``).

    The clean sequence holds the sampled action tokens and, as goal, the frame
    actually observed after the executed steps (``o_{t+K}`` when the whole chunk
    ran; the episode's last frame when it ended inside the chunk, as the
    demonstrations clip it). Chunk steps that were not executed are padding.
    """
    flat = batch.reshape(-1)
    window = flat.select(IMAGE_KEY, STATE_KEY, INSTRUCTION_KEY, strict=False)
    if model.config.predict_goal:
        window.set(GOAL_IMAGE_KEY, flat.get(("next", *IMAGE_KEY)))
    ids = model.sequence(window, action_tokens=flat.get(ACTION_TOKENS_KEY))
    steps = executed_steps(flat)  # (N,)
    is_pad = torch.arange(model.config.chunk_size)[None, :] >= steps[:, None]  # (N, K)
    rows = TensorDict(
        {SEQUENCE_KEY: ids, ACTION_IS_PAD_KEY: is_pad, IMAGE_KEY: flat.get(IMAGE_KEY), STATE_KEY: flat.get(STATE_KEY)},
        batch_size=[ids.shape[0]],
    )
    visual = model.visual_input(flat)  # the observation images, with cross-attention
    if visual is not None:
        rows.set(VISUAL_FEATURES_KEY, visual)
    if PRIVILEGED_STATE_KEY in flat.keys(include_nested=True):  # what a privileged critic regresses on
        rows.set(PRIVILEGED_STATE_KEY, flat.get(PRIVILEGED_STATE_KEY))
    rows.set(DECODING_PATH_KEY, flat.get(DECODING_PATH_KEY))
    for key in (ADVANTAGE_KEY, VALUE_TARGET_KEY):
        rows.set(key, flat.get(key).reshape(ids.shape[0], -1)[:, 0] if key == ADVANTAGE_KEY else flat.get(key).reshape(ids.shape[0], 1))
    return rows


class EpisodeGroups:
    """Monte-Carlo advantages: hold decisions until every episode of an initial-state group has ended.

    Episode ``e`` of a worker starts from seed ``train_seed + w * stride + e // G``
    (``EnvConfig.group_size = G``), so a group is ``G`` consecutive episodes of one
    worker. Each episode's return is the sum of its chunk rewards; the advantage of
    every decision of an episode is its return standardised within the group
    (``relative=True``, GRPO-style) or the return itself (``relative=False``,
    ``G = 1``: with a sparse success reward, 1 for a successful episode, 0 otherwise).

    With ``discount`` (the per-decision discount ``gamma ** k``; ``G = 1``, not relative)
    each decision's advantage is instead its own discounted return from that chunk to
    the episode's end (REINFORCE's reward-to-go), ``G_t = r_t + discount * G_{t+1}``:
    no critic, so no bootstrap either, and an episode cut by the time limit counts
    nothing after its last step. With ``baseline`` (a :class:`DecisionIndexBaseline`)
    the advantage is that return to go relative to the recent episodes' at the same
    decision index, in units of their spread; the value target stays ``G_t``.
    """

    def __init__(self, group_size: int, relative: bool = True, discount: float | None = None,
                 baseline: DecisionIndexBaseline | None = None) -> None:
        if discount is not None and (group_size != 1 or relative):
            raise ValueError("per-decision returns (discount) take one rollout per initial state and no group baseline.")
        if baseline is not None and discount is None:
            raise ValueError("a decision-index baseline compares returns to go: it needs a discount.")
        self.group_size, self.relative, self.discount, self.baseline = int(group_size), bool(relative), discount, baseline
        self.running: dict[int, list[TensorDictBase]] = {}  # worker -> decisions of its unfinished episode
        self.groups: dict[int, list[TensorDictBase]] = {}  # seed -> finished episodes

    def add(self, batch: TensorDictBase) -> list[TensorDictBase]:
        """Add a collector batch (``[T]`` or ``[W, T]``); return the episodes whose groups completed."""
        batch = batch if batch.ndim == 2 else batch.unsqueeze(0)
        ready = []
        for worker in range(batch.shape[0]):
            traj = batch[worker]
            ends = traj.get(("next", "done")).reshape(-1).nonzero().reshape(-1).tolist()
            start = 0
            for end in ends:
                pieces = self.running.pop(worker, []) + [traj[start : end + 1]]
                episode = torch.cat(pieces)
                start = end + 1
                seed = int(episode.get(GROUP_KEY).reshape(-1)[-1])
                group = self.groups.setdefault(seed, [])
                group.append(episode)
                if len(group) == self.group_size:
                    ready += self._finish(self.groups.pop(seed), seed)
            if start < traj.shape[0]:
                self.running.setdefault(worker, []).append(traj[start:])
        return ready

    def _finish(self, episodes: list[TensorDictBase], seed: int) -> list[TensorDictBase]:
        if self.discount is not None:
            for ep in episodes:
                to_go = returns_to_go(ep.get(("next", "reward")).reshape(-1), self.discount)
                advantage = to_go if self.baseline is None else self.baseline(to_go)
                ep.set(ADVANTAGE_KEY, advantage.reshape(ep.shape))
                ep.set(VALUE_TARGET_KEY, to_go.reshape(*ep.shape, 1))
            return episodes
        returns = torch.stack([ep.get(("next", "reward")).sum() for ep in episodes])
        adv = group_relative_advantages(returns, torch.full_like(returns, seed, dtype=torch.long)) if self.relative else returns
        for ep, a, ret in zip(episodes, adv, returns):
            ep.set(ADVANTAGE_KEY, a.expand(ep.shape).clone())
            ep.set(VALUE_TARGET_KEY, ret.expand(*ep.shape, 1).clone())
        return episodes


def make_episode_groups(cfg: DictConfig, model: MMaDAModel) -> EpisodeGroups | None:
    """Critic-free advantages: group-relative (``group``) or plain (``return``) episode returns, or each decision's
    discounted return to the episode's end (``return_to_go``, discount ``gamma ** k`` per decision; relative to the
    last ``advantage.baseline_episodes`` episodes' at the same decision index when that is > 0); ``None`` for GAE."""
    if cfg.advantage.estimator == "group":
        return EpisodeGroups(int(cfg.advantage.group_size))
    if cfg.advantage.estimator == "return_to_go":
        episodes = int(cfg.advantage.get("baseline_episodes", 0))
        baseline = DecisionIndexBaseline(episodes) if episodes > 0 else None
        return EpisodeGroups(1, relative=False, discount=decision_discount(cfg, model), baseline=baseline)
    return EpisodeGroups(1, relative=False) if cfg.advantage.estimator == "return" else None


# -- data -------------------------------------------------------------------------------
def make_online_buffer(cfg: DictConfig) -> TensorDictReplayBuffer:
    """Recent training rows (RWR samples them uniformly; PPO uses each batch once)."""
    return TensorDictReplayBuffer(storage=LazyTensorStorage(int(cfg.replay_buffer.capacity)), sampler=RandomSampler(),
                                  batch_size=max(1, split_batch(cfg)[0]))


def open_demo_buffer(cfg: DictConfig, model: MMaDAModel) -> DemoBuffer:
    env = EnvConfig(task=cfg.env.task, image_size=model.image_size, camera_fov=model.config.camera_fov_for(cfg.env.task),
                    control_mode=cfg.env.control_mode)
    return open_demos(cfg.demos.dir, env, collect_episodes=int(cfg.demos.collect_episodes),
                      action_noise=float(cfg.demos.action_noise), workers=int(cfg.demos.collect_workers),
                      prefix=f"{PREFIX} ")


def split_batch(cfg: DictConfig) -> tuple[int, int]:
    """(online, demo) samples per update: ``demos.ratio`` of the batch comes from the demonstrations."""
    total = int(cfg.replay_buffer.batch_size)
    demo = int(round(float(cfg.demos.ratio) * total))
    return total - demo, demo


def pretraining_config(cfg: DictConfig) -> dict:
    """The pretraining run's configuration (its checkpoint's ``config.json``); empty for a bare saved model."""
    pretrained = cfg.get("pretrained")
    saved = resolve_model_dir(pretrained).parent / CONFIG_FILE if pretrained is not None else None
    return json.loads(saved.read_text()) if saved is not None and saved.is_file() else {}


def demo_window_skips(cfg: DictConfig) -> dict:
    """The window options (:data:`~mmada_rl.data.windows.WINDOW_SKIPS`) of the demonstration windows: ``demos.<option>``,
    or where that is null (the default), the pretraining run's ``data.<option>`` (its checkpoint's ``config.json``),
    so fine-tuning keeps drawing the windows the policy was pretrained on; off for a bare saved model."""
    data = pretraining_config(cfg).get("data", {})
    given = {name: cfg.demos.get(name) for name in WINDOW_SKIPS}
    return window_skips({**data, **{name: value for name, value in given.items() if value is not None}})


def demo_random_shift(cfg: DictConfig) -> int:
    """``demos.random_shift``, or where that is null (the default) the pretraining run's ``replay_buffer.random_shift``
    (0 for a bare saved model): the pixels the demonstration windows' images are shifted by, as pretraining shifted them."""
    pad = cfg.demos.get("random_shift")
    if pad is None:
        pad = pretraining_config(cfg).get("replay_buffer", {}).get("random_shift", 0)
    return check_shift(pad, "demos.random_shift")


def make_demo_windows(cfg: DictConfig, demos: DemoBuffer, model: MMaDAModel):
    """Chunk windows of the demonstrations (``None`` when ``demos.ratio`` is 0), with :func:`demo_window_skips` and
    the image shift of :func:`demo_random_shift`."""
    _, n_demo = split_batch(cfg)
    if n_demo == 0:
        return None
    skips = demo_window_skips(cfg)
    if skips["grasp_hold_gripper_only"]:
        model.action_tokenizer.require_ordered_bins("grasp_hold_gripper_only scores the gripper's token of each action")
    windows = make_window_buffer(demos, model.config.chunk_size, n_demo, seed=int(cfg.seed), **skips)
    pad = demo_random_shift(cfg)
    if pad:
        windows.append_transform(RandomShift(pad, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY]))
    return windows


def mixed_batch(model: MMaDAModel, online: TensorDictBase | None, demo_windows) -> TensorDict:
    """Online rows and demonstration windows in one loss batch (``is_demo`` marks the demos).

    ``online=None``: demonstrations only (``demos.ratio=1``, the control that
    takes the same updates without learning from the online data).
    """
    keys = [SEQUENCE_KEY, ACTION_IS_PAD_KEY, ADVANTAGE_KEY]
    if model.denoiser.config.encodes_images:
        keys.append(VISUAL_FEATURES_KEY)  # the observation images the denoiser's CNN reads
    parts = [] if online is None else [online.select(*keys).set(IS_DEMO_KEY, torch.zeros(online.shape[0], dtype=torch.bool))]
    if demo_windows is not None:
        rows = model.loss_inputs(demo_windows.sample())
        n = rows.shape[0]
        parts.append(rows.set(ADVANTAGE_KEY, torch.zeros(n)).set(IS_DEMO_KEY, torch.ones(n, dtype=torch.bool)))
        if online is not None and ACTION_GRIPPER_ONLY_KEY in rows.keys(True):  # online chunks score every entry
            parts[0].set(ACTION_GRIPPER_ONLY_KEY, torch.zeros(online.shape[0], dtype=torch.bool))
    return torch.cat(parts)


# -- losses ------------------------------------------------------------------------------
#: the pretraining regularisers (``loss.<option>`` of both recipes) fine-tuning keeps unless told otherwise
PRETRAINING_LOSS_OPTIONS = ("proprio_drop_prob", "proprio_drop_keep_dims", "action_mean_weight")


def pretraining_loss_options(cfg: DictConfig, model: MMaDAModel) -> dict:
    """:class:`~mmada_rl.objectives.MaskedDiffusionLoss` options for the demonstration (and online) rows: state
    dropout (``proprio_drop_prob``, ``proprio_drop_index`` from ``proprio_drop_keep_dims``) and ``action_mean_weight``,
    each ``loss.<option>``, or where that is null (the default) the pretraining run's ``loss.<option>`` (its checkpoint's
    ``config.json``; off for a bare saved model): the demonstration updates then train the loss the policy was
    pretrained with, not one without the regularisers that made it generalise."""
    saved = pretraining_config(cfg).get("loss", {})
    given = {name: cfg.loss.get(name) for name in PRETRAINING_LOSS_OPTIONS}
    option = {name: saved.get(name) if given[name] is None else given[name] for name in PRETRAINING_LOSS_OPTIONS}
    prob, weight = float(option["proprio_drop_prob"] or 0.0), float(option["action_mean_weight"] or 0.0)
    keep = [int(d) for d in option["proprio_drop_keep_dims"] or []]
    check_probability("loss.proprio_drop_prob", prob)
    if weight < 0:
        raise ValueError(f"loss.action_mean_weight={weight} must be >= 0 (0: off).")
    if weight > 0:
        model.action_tokenizer.require_ordered_bins(f"loss.action_mean_weight={weight} scores the expected bin of "
                                                    "each action token")
    index = model.proprio_drop_index(keep, name="loss.proprio_drop_keep_dims") if prob > 0 else None
    return {"proprio_drop_prob": prob, "proprio_drop_index": index, "action_mean_weight": weight}


def make_loss(cfg: DictConfig, model: MMaDAModel):
    if cfg.algo == "rwr":
        r = cfg.loss.rwr
        reference = copy.deepcopy(model.denoiser) if float(r.kl_coef) > 0 else None
        return RewardWeightedDiffusionLoss(
            model.denoiser, weighting=r.weighting, temperature=float(r.temperature), max_weight=float(r.max_weight),
            max_negative_nll=float(r.max_negative_nll), demo_weight=float(r.demo_weight),
            normalize_weights=bool(r.normalize_weights), standardize_advantage=bool(r.standardize_advantage),
            reference=reference, kl_coef=float(r.kl_coef), weight_goal=bool(r.weight_goal),
            schedule=cfg.loss.schedule, goal_weight=float(cfg.loss.goal_weight), **pretraining_loss_options(cfg, model),
        )
    p = cfg.loss.ppo
    return PathPPOLoss(model.denoiser, clip_epsilon=float(p.clip_epsilon), ratio_level=p.ratio_level,
                       normalize_advantage=bool(p.normalize_advantage), denoising_steps=p.denoising_steps,
                       tokens=p.tokens)


def make_demo_anchor(cfg: DictConfig, model: MMaDAModel) -> MaskedDiffusionLoss | None:
    """PPO's anchor to the demonstrations: the plain masked-diffusion loss (action and goal tokens), scaled by
    ``loss.ppo.demo_coef``, on demonstration windows added to every PPO minibatch; None for RWR (its batches mix the
    demonstrations in already) or when the coefficient is 0."""
    coef = float(cfg.loss.ppo.demo_coef) if cfg.algo == "ppo" else 0.0
    if coef == 0:
        return None
    options = pretraining_loss_options(cfg, model)
    options["action_mean_weight"] *= coef
    return MaskedDiffusionLoss(model.denoiser, schedule=cfg.loss.schedule, action_weight=coef,
                               goal_weight=coef * float(cfg.loss.goal_weight), condition_weight=0.0, **options)


def freezes_visual_encoder(cfg: DictConfig) -> bool:
    """``optim.freeze_visual_encoder``, or where null (the default) the pretraining run's ``model.visual_encoder_freeze``:
    a CNN copied from a baseline and kept fixed while pretraining stays fixed while fine-tuning."""
    given = cfg.optim.get("freeze_visual_encoder")
    if given is not None:
        return bool(given)
    return bool(pretraining_config(cfg).get("model", {}).get("visual_encoder_freeze", False))


def make_optim(cfg: DictConfig, model: MMaDAModel):
    """AdamW over the denoiser; its image CNN left out (``requires_grad`` off) where :func:`freezes_visual_encoder`."""
    if freezes_visual_encoder(cfg):
        if model.denoiser.visual_encoder is None:
            raise ValueError("optim.freeze_visual_encoder=true fixes the denoiser's own CNN, but this policy has none "
                             "(it reads image tokens): set optim.freeze_visual_encoder=false or null.")
        model.denoiser.visual_encoder.cnn.requires_grad_(False)
        print("[finetune] the denoiser's CNN stays fixed (optim.freeze_visual_encoder)")
    return training.make_optimizer(model.denoiser.parameters(), lr=float(cfg.optim.lr), weight_decay=float(cfg.optim.weight_decay))


def learning_rate(cfg: DictConfig, env_steps: int) -> float:
    """The policy's learning rate after ``env_steps`` of the budget: ``optim.lr`` throughout, or with
    ``optim.lr_decay=cosine`` decayed along a cosine to ``optim.min_lr_ratio`` of it at
    ``collector.total_env_steps`` (a function of the env steps, so a resumed run picks up where it was)."""
    lr = float(cfg.optim.lr)
    if cfg.optim.lr_decay == "constant":
        return lr
    progress = env_steps / int(cfg.collector.total_env_steps)
    return lr * training.cosine_decay(progress, float(cfg.optim.min_lr_ratio))


def make_logger(cfg: DictConfig, run_dir: Path):
    return training.make_logger(cfg.logger.backend, run_dir)
