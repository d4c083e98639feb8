"""Factories of the RL-baseline recipe (``online.py``): each ``make_*`` turns one config section into objects.

The per-algorithm parts are small: :func:`make_networks` and :func:`make_loss`
pick TorchRL's ``ClipPPOLoss`` + ``GAE``, ``SACLoss`` or ``IQLLoss``;
:func:`make_updater` returns :class:`PPOUpdater` (on-policy epochs over each
collected batch) or :class:`OffPolicyUpdater` (demo/online replay, update-to-data
ratio, soft target updates; SAC/RLPD and IQL share it).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.objectives import ClipPPOLoss, IQLLoss, SACLoss, SoftUpdate
from torchrl.objectives.value import GAE

from mmada_rl import training
from mmada_rl.baselines.rl import OneStepChunkActor, RLAgent, RLNetworkConfig, make_actor, make_qvalue, make_value, observation_keys
from mmada_rl.data import DemoBuffer
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.keys import ACTION_KEY, STATE_KEY
from mmada_rl.training import make_optimizer
from mmada_rl.training.demos import open_demos

PREFIX = "[online]"
#: The baselines: on-policy PPO from scratch, SAC with demos (RLPD), IQL offline -> online.
ALGOS = ("ppo", "sac", "iql")
#: Observations each algorithm gets by default: PPO sees what our policy sees; SAC/IQL are privileged-state references.
DEFAULT_OBS_MODE = {"ppo": "rgb", "sac": "state", "iql": "state"}


def check_config(cfg: DictConfig) -> None:
    """Fail before anything is built, with one sentence per bad value."""
    training.require_cpu(cfg, "online RL baselines'")
    if cfg.algo not in ALGOS:
        raise ValueError(f"algo={cfg.algo!r} is not an RL baseline; use algo=ppo, algo=sac or algo=iql.")
    total, batch = int(cfg.collector.total_env_steps), int(cfg.collector.frames_per_batch)
    if batch < 1 or total < batch or total % batch:
        raise ValueError(f"collector.total_env_steps={total} must be a positive multiple of collector.frames_per_batch={batch}.")
    for name in ("interval", "offline_interval"):
        if int(cfg.checkpoint[name]) < 1:
            raise ValueError(f"checkpoint.{name} must be >= 1, got {cfg.checkpoint[name]!r}.")
    if cfg.algo == "ppo" and batch % int(cfg.loss.ppo.minibatch_size):
        raise ValueError(f"collector.frames_per_batch={batch} must be a multiple of loss.ppo.minibatch_size={cfg.loss.ppo.minibatch_size}.")
    fraction = cfg.replay_buffer.demo_fraction
    if fraction is not None and not 0.0 <= float(fraction) <= 1.0:
        raise ValueError(f"replay_buffer.demo_fraction must lie in [0, 1] (or null: proportional), got {fraction!r}.")


def obs_mode(cfg: DictConfig) -> str:
    """``env.obs_mode``, or the algorithm's default when it is null."""
    return cfg.env.obs_mode or DEFAULT_OBS_MODE[cfg.algo]


def make_env_config(cfg: DictConfig, episodes_done: int = 0) -> EnvConfig:
    """The training env; episode ``e`` is reset with seed ``train_seed + e`` (resumes continue the sequence)."""
    env = OmegaConf.to_container(cfg.env)
    first = env.pop("train_seed")
    first = 10_000 + 20_000 * int(cfg.seed) if first is None else int(first)  # disjoint from demo (0..) and eval (1e6..) seeds
    return EnvConfig(**{**env, "obs_mode": obs_mode(cfg), "train_seed": first + episodes_done})


# -- data -----------------------------------------------------------------------
def transition_keys(mode: str) -> list:
    obs = observation_keys(mode)
    return [*obs, ACTION_KEY, *(("next", *k) for k in obs), ("next", "reward"), ("next", "done"), ("next", "terminated")]


def make_demos(cfg: DictConfig, env_cfg: EnvConfig) -> DemoBuffer | None:
    """The demonstrations of ``data.dir`` for SAC/IQL (collected first when missing), ``None`` for PPO (from scratch)."""
    if cfg.algo == "ppo":
        return None
    path = Path(cfg.data.dir or Path(cfg.data.root) / ("state" if env_cfg.obs_mode == "state" else "") / env_cfg.task)
    want = int(cfg.data.collect_episodes)
    # planners need the task's own episode length, whatever the training episodes are cut to
    record = EnvConfig(**{**env_cfg.to_dict(), "train_seed": None, "max_episode_steps": None})
    demos = open_demos(path, record, collect_episodes=want, prefix=f"{PREFIX} ")
    if demos.metadata.reward != env_cfg.reward:
        raise ValueError(f"demos in {path} carry {demos.metadata.reward!r} rewards but env.reward={env_cfg.reward!r}; "
                         f"use env.reward={demos.metadata.reward} or collect demos with that reward.")
    return demos


def make_demo_replay(demos: DemoBuffer | None, mode: str, action_spec) -> TensorDictReplayBuffer | None:
    """The demo transitions in memory; actions pulled inside the TanhNormal's open box (log-probs stay finite)."""
    if demos is None:
        return None
    data = demos.storage[: len(demos)].select(*transition_keys(mode)).to_tensordict()
    low, high = action_spec.space.low, action_spec.space.high
    margin = 1e-4 * (high - low)
    data.set(ACTION_KEY, data.get(ACTION_KEY).clamp(low + margin, high - margin))
    replay = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)))
    replay.extend(data)
    return replay


def make_online_replay(cfg: DictConfig) -> TensorDictReplayBuffer:
    """Off-policy: the online transitions (``replay_buffer.capacity``); PPO: one batch, minibatches without replacement."""
    if cfg.algo == "ppo":
        return TensorDictReplayBuffer(storage=LazyTensorStorage(int(cfg.collector.frames_per_batch)),
                                      sampler=SamplerWithoutReplacement(), batch_size=int(cfg.loss.ppo.minibatch_size))
    return TensorDictReplayBuffer(storage=LazyTensorStorage(int(cfg.replay_buffer.capacity)))


# -- networks and losses ----------------------------------------------------------
class Networks(NamedTuple):
    config: RLNetworkConfig
    actor: torch.nn.Module
    qvalue: torch.nn.Module | None
    value: torch.nn.Module | None


def make_networks(cfg: DictConfig, env, demos: DemoBuffer | None) -> Networks:
    """Actor and critics sized by the env; the state is standardised with the demos' moments when there are demos."""
    mode = obs_mode(cfg)
    state_dim = int(env.observation_spec[STATE_KEY].shape[-1])
    if demos is not None and demos.metadata.state_dim != state_dim:
        raise ValueError(f"demos in {demos.path} have {demos.metadata.state_dim}-d states but the env gives {state_dim}-d "
                         f"ones (obs_mode={mode}); collect demos in that observation mode.")
    model = OmegaConf.to_container(cfg.model)
    config = RLNetworkConfig(obs_mode=mode, state_dim=state_dim, action_dim=int(env.action_spec.shape[-1]),
                             image_size=int(cfg.env.image_size), state_dependent_scale=cfg.algo != "ppo",
                             camera_fov=cfg.env.camera_fov if mode == "rgb" else None, **model)
    stats = None
    if demos is not None:
        states = demos.storage[: len(demos)].get(STATE_KEY).float()
        stats = (states.mean(0), states.std(0))
    actor = make_actor(config, env.action_spec, stats)
    qvalue = make_qvalue(config, stats) if cfg.algo in ("sac", "iql") else None
    value = make_value(config, stats) if cfg.algo in ("ppo", "iql") else None
    return Networks(config, actor, qvalue, value)


class Loss(NamedTuple):
    module: torch.nn.Module
    target_updater: SoftUpdate | None  # SAC / IQL
    advantage: GAE | None  # PPO


def make_loss(cfg: DictConfig, nets: Networks, action_spec) -> Loss:
    """TorchRL's ``ClipPPOLoss`` (+ ``GAE``), ``SACLoss`` or ``IQLLoss`` over the networks."""
    gamma, c = float(cfg.loss.gamma), cfg.loss[cfg.algo]
    if cfg.algo == "ppo":
        module = ClipPPOLoss(nets.actor, nets.value, clip_epsilon=float(c.clip_epsilon), entropy_bonus=float(c.entropy_coeff) > 0,
                             entropy_coeff=float(c.entropy_coeff), critic_coeff=float(c.critic_coeff),
                             loss_critic_type=c.loss_critic_type, normalize_advantage=bool(c.normalize_advantage))
        advantage = GAE(gamma=gamma, lmbda=float(c.gae_lambda), value_network=nets.value, average_gae=False)
        return Loss(module, None, advantage)
    if cfg.algo == "sac":
        module = SACLoss(nets.actor, nets.qvalue, num_qvalue_nets=int(c.num_qvalue_nets), loss_function=c.loss_function,
                         alpha_init=float(c.alpha_init), action_spec=action_spec, target_entropy=c.target_entropy)
    else:
        module = IQLLoss(nets.actor, nets.qvalue, nets.value, num_qvalue_nets=int(c.num_qvalue_nets), loss_function=c.loss_function,
                         temperature=float(c.temperature), expectile=float(c.expectile))
    module.make_value_estimator(gamma=gamma)
    return Loss(module, SoftUpdate(module, tau=float(c.tau)), None)


def make_optim(cfg: DictConfig, loss: Loss) -> torch.optim.AdamW:
    """One AdamW over every trained parameter of the loss (SAC's temperature without weight decay)."""
    o = cfg.optim
    decayed = [p for n, p in loss.module.named_parameters() if "log_alpha" not in n]
    groups = [{"params": decayed}]
    alpha = [p for n, p in loss.module.named_parameters() if "log_alpha" in n]
    if alpha:
        groups.append({"params": alpha, "weight_decay": 0.0})
    return make_optimizer(groups, lr=float(o.lr), weight_decay=float(o.weight_decay), betas=tuple(o.betas))


# -- updates --------------------------------------------------------------------
def _mean(rows: list[dict]) -> dict:
    return {k: sum(r[k] for r in rows) / len(rows) for k in rows[0]} if rows else {}


class PPOUpdater:
    """GAE on each collected batch, then ``epochs`` passes of ``ClipPPOLoss`` over minibatches (early stop at ``target_kl``)."""

    def __init__(self, loss: Loss, optimizer, replay: TensorDictReplayBuffer, *, epochs: int, max_grad_norm: float,
                 target_kl: float | None) -> None:
        self.loss, self.optimizer, self.replay = loss, optimizer, replay
        self.epochs, self.max_grad_norm, self.target_kl = epochs, max_grad_norm, target_kl

    def __call__(self, batch: TensorDictBase, env_steps: int) -> tuple[int, dict]:
        with torch.no_grad():
            self.loss.advantage(batch)  # (*B, T): advantage, value_target
        data = batch.reshape(-1).exclude("language_instruction", "collector")
        self.replay.empty()
        self.replay.extend(data)
        rows, per_epoch = [], len(data) // self.replay.batch_size
        for _ in range(self.epochs):
            kl = []
            for _ in range(per_epoch):
                out = self.loss.module(self.replay.sample())
                total = sum(v for k, v in out.items() if k.startswith("loss_"))
                self.optimizer.zero_grad(set_to_none=True)
                total.backward()
                grad = torch.nn.utils.clip_grad_norm_(self.loss.module.parameters(), self.max_grad_norm)
                self.optimizer.step()
                kl.append(float(out["kl_approx"]))
                rows.append({f"train/{k}": float(out[k].detach()) for k in ("loss_objective", "loss_critic", "clip_fraction", "kl_approx")}
                            | {"train/grad_norm": float(grad)})
            if self.target_kl and sum(kl) / len(kl) > self.target_kl:
                break
        return len(rows), _mean(rows)


class OffPolicyUpdater:
    """SAC / IQL updates on batches mixing demos and online transitions.

    Every env step buys ``utd_ratio`` gradient updates once ``learning_starts``
    env steps have been collected. A batch holds ``demo_fraction`` demos (RLPD's
    symmetric sampling: 0.5), or, with ``demo_fraction=None``, demos in
    proportion to their share of all stored transitions (one pooled buffer, IQL's
    offline-to-online fine-tuning).
    """

    def __init__(self, loss: Loss, optimizer, online: TensorDictReplayBuffer, demos: TensorDictReplayBuffer | None, *,
                 mode: str, batch_size: int, demo_fraction: float | None, utd_ratio: float, learning_starts: int) -> None:
        self.loss, self.optimizer, self.online, self.demos = loss, optimizer, online, demos
        self.keys = transition_keys(mode)
        self.batch_size, self.demo_fraction = batch_size, demo_fraction
        self.utd_ratio, self.learning_starts = utd_ratio, learning_starts

    def sample(self) -> TensorDictBase:
        n_demos, n_online = len(self.demos) if self.demos is not None else 0, len(self.online)
        if n_demos + n_online == 0:
            raise RuntimeError("no transitions to learn from: no demos and no online data yet.")
        share = n_demos / (n_demos + n_online) if self.demo_fraction is None else float(self.demo_fraction)
        k = self.batch_size if n_online == 0 else 0 if n_demos == 0 else round(self.batch_size * share)
        parts = [self.demos.sample(k)] if k else []
        if self.batch_size - k:
            parts.append(self.online.sample(self.batch_size - k))
        return torch.cat(parts) if len(parts) > 1 else parts[0]

    def update(self, num_updates: int) -> dict:
        rows = []
        for _ in range(num_updates):
            out = self.loss.module(self.sample())
            total = sum(v for k, v in out.items() if k.startswith("loss_"))
            self.optimizer.zero_grad(set_to_none=True)
            total.backward()
            self.optimizer.step()
            self.loss.target_updater.step()
            rows.append({f"train/{k}": float(v.detach().mean()) for k, v in out.items()})
        return _mean(rows)

    def __call__(self, batch: TensorDictBase, env_steps: int) -> tuple[int, dict]:
        self.online.extend(batch.reshape(-1).select(*self.keys))
        if env_steps < self.learning_starts:
            return 0, {}
        n = max(1, round(batch.numel() * self.utd_ratio))
        return n, self.update(n)


def make_updater(cfg: DictConfig, loss: Loss, optimizer, online, demos):
    c = cfg.loss[cfg.algo]
    if cfg.algo == "ppo":
        return PPOUpdater(loss, optimizer, online, epochs=int(c.epochs), max_grad_norm=float(c.max_grad_norm),
                          target_kl=c.target_kl and float(c.target_kl))
    fraction = cfg.replay_buffer.demo_fraction
    return OffPolicyUpdater(loss, optimizer, online, demos, mode=obs_mode(cfg), batch_size=int(cfg.replay_buffer.batch_size),
                            demo_fraction=None if fraction is None else float(fraction), utd_ratio=float(c.utd_ratio),
                            learning_starts=int(cfg.collector.init_random_frames) if cfg.algo == "sac" else 0)


# -- collection, logging, checkpoints, evaluation ---------------------------------
def make_collector(cfg: DictConfig, env, actor, env_steps: int) -> Collector | None:
    """The training collector for the remaining env-step budget; ``None`` when the budget is spent.

    SAC starts with ``init_random_frames`` uniform random actions; PPO and IQL act with their own policy from the
    first step (IQL's is the offline-trained one: random actions would enter its advantage-weighted regression).
    """
    if env_steps >= int(cfg.collector.total_env_steps):
        return None
    random_frames = max(0, int(cfg.collector.init_random_frames) - env_steps) if cfg.algo == "sac" else 0
    return Collector(env, actor, frames_per_batch=int(cfg.collector.frames_per_batch),
                     total_frames=int(cfg.collector.total_env_steps) - env_steps, init_random_frames=random_frames,
                     auto_register_policy_transforms=False)  # a Markov actor needs no InitTracker / primer


def make_logger(cfg: DictConfig, run_dir: Path):
    return training.make_logger(cfg.logger.backend, run_dir)


class Progress(NamedTuple):
    env_steps: int = 0
    updates: int = 0
    episodes: int = 0
    wall_s: float = 0.0


def resume(cfg: DictConfig, run_dir: Path, agent: RLAgent, optimizer, online: TensorDictReplayBuffer) -> Progress:
    """Restore weights, optimizer, RNG states and the online replay buffer from ``checkpoint.resume``."""
    ckpt = training.resume_training(cfg.checkpoint.resume, run_dir, load_weights=agent.load, optimizer=optimizer)
    if ckpt is None:
        return Progress()
    extra = ckpt.trainer_state["extra"]
    if extra.get("replay_buffer") is not None:
        online.extend(extra["replay_buffer"])
    progress = Progress(**{k: extra[k] for k in Progress._fields})
    print(f"{PREFIX} resumed from {ckpt.path} at env step {progress.env_steps} (update {progress.updates})")
    return progress


def _stored_transitions(replay: TensorDictReplayBuffer) -> TensorDictBase:
    """The filled part of the storage, oldest first (the storage itself is allocated at full capacity)."""
    n = len(replay)
    data = replay.storage[:n]
    if n == replay.storage.max_size:  # wrapped around: the writer's cursor marks the oldest transition
        cursor = replay._writer._cursor % n
        data = torch.cat([data[cursor:], data[:cursor]])
    return data.clone()


def save(cfg: DictConfig, run_dir: Path, agent: RLAgent, optimizer, online, progress: Progress, config: dict) -> Path:
    """An atomic checkpoint named by the update count; off-policy runs keep their online replay buffer in it."""
    keep_buffer = cfg.algo != "ppo" and bool(cfg.checkpoint.save_replay_buffer) and len(online) > 0
    extra = {**progress._asdict(), "replay_buffer": _stored_transitions(online) if keep_buffer else None}
    return training.save_checkpoint(run_dir, progress.updates, model=agent, optimizer=optimizer, config=config,
                                    extra=extra, keep=int(cfg.checkpoint.keep))


class EvalHistory:
    """``eval_history.json``: one record per evaluation; on resume, records past the checkpoint are dropped."""

    def __init__(self, path: Path, progress: Progress) -> None:
        self.path = path
        old = json.loads(path.read_text()) if path.exists() and progress.env_steps + progress.updates else []
        self.records = [r for r in old if (r["env_steps"], r["updates"]) <= (progress.env_steps, progress.updates)]
        self._write()

    def append(self, record: dict) -> None:
        self.records.append(record)
        self._write()

    def _write(self) -> None:
        tmp = self.path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.records, indent=2))
        tmp.replace(self.path)


def evaluate(cfg: DictConfig, actor, progress: Progress) -> dict:
    """One ``eval_history.json`` record: success rates of the greedy actor on ``eval.episodes`` fixed evaluation seeds,
    and each episode's (:meth:`~mmada_rl.evaluation.EvalResult.history_record`)."""
    from mmada_rl.evaluation import evaluate as run_eval

    mode = obs_mode(cfg)
    policy = OneStepChunkActor(actor, mode, int(cfg.env.image_size), cfg.env.camera_fov)
    result = run_eval(policy, cfg.env.task, episodes=int(cfg.eval.episodes),
                      image_size=int(cfg.env.image_size), control_mode=cfg.env.control_mode,
                      max_episode_steps=cfg.eval.max_episode_steps, execute_steps=1, progress=False)
    return {"env_steps": progress.env_steps, "updates": progress.updates, **result.history_record(),
            "wall_s": round(progress.wall_s, 2)}
