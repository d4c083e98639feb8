"""Factories of the imitation-baseline recipe: each ``make_*`` turns one config section into objects."""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mmada_rl import baselines
from mmada_rl.baselines import ChunkPolicy, NormalizationStats, RandomShift
from mmada_rl.data import DemoBuffer, make_window_buffer
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.training import latest_checkpoint, load_checkpoint, make_optimizer, make_scheduler
from mmada_rl.training.checkpoint import restore_rng_state
from mmada_rl.training.demos import open_demos

PREFIX = "[imitation]"


def make_env_config(cfg: DictConfig) -> EnvConfig:
    return EnvConfig(**OmegaConf.to_container(cfg.env))


def make_demo_buffer(cfg: DictConfig) -> DemoBuffer:
    """The demonstrations of ``cfg.data.dir`` (checked against ``cfg.env``; collected first when missing or short)."""
    return open_demos(cfg.data.dir, make_env_config(cfg), collect_episodes=int(cfg.data.collect_episodes), prefix=f"{PREFIX} ")


def make_policy(cfg: DictConfig, buffer: DemoBuffer) -> ChunkPolicy:
    """The ``cfg.algo`` policy, shaped by the buffer and normalised with its statistics."""
    if cfg.algo not in baselines.ALGOS:
        raise ValueError(f"algo={cfg.algo!r} is not a baseline; use algo=bc or algo=diffusion_policy.")
    meta = buffer.metadata
    config = {
        "chunk_size": int(cfg.model.chunk_size),
        "action_dim": int(meta.action_dim),
        "state_dim": int(meta.state_dim),
        "image_size": int(meta.image_size),
        "encoder": OmegaConf.to_container(cfg.model.encoder),
        **OmegaConf.to_container(cfg.model[cfg.algo]),
    }
    return baselines.make_policy(cfg.algo, config, NormalizationStats.from_buffer(buffer)).to(cfg.device)


def make_data(cfg: DictConfig, buffer: DemoBuffer):
    """Chunk-window sampler over the demonstrations (seeded), with random-shift augmentation of the images."""
    data = make_window_buffer(buffer, int(cfg.model.chunk_size), int(cfg.replay_buffer.batch_size), seed=int(cfg.seed))
    if int(cfg.replay_buffer.random_shift):
        data.append_transform(RandomShift(int(cfg.replay_buffer.random_shift)))
    return data


def make_loss(cfg: DictConfig, policy: ChunkPolicy):
    """TorchRL's ``BCLoss`` (bc) or ``DiffusionBCLoss`` (diffusion_policy) for the policy."""
    kwargs = {"loss_function": cfg.loss.bc_loss_function} if cfg.algo == "bc" else {}
    return baselines.make_loss(policy, **kwargs)


def make_optim(cfg: DictConfig, policy: ChunkPolicy):
    o = cfg.optim
    optimizer = make_optimizer(policy.parameters(), lr=float(o.lr), weight_decay=float(o.weight_decay))
    scheduler = make_scheduler(optimizer, warmup_steps=int(o.warmup_steps), total_steps=int(o.total_steps))
    return optimizer, scheduler


def make_logger(cfg: DictConfig, run_dir: Path):
    """A TorchRL logger writing under ``run_dir/logs``."""
    from torchrl.record.loggers import get_logger

    return get_logger(cfg.logger.backend, logger_name=str(run_dir), experiment_name="logs")


def resume(cfg: DictConfig, run_dir: Path, policy: ChunkPolicy, optimizer, scheduler, generators: dict) -> int:
    """Restore weights, optimizer, scheduler and RNG states from ``checkpoint.resume``; returns the step (0: fresh run)."""
    if not cfg.checkpoint.resume:
        return 0
    path = latest_checkpoint(run_dir) if cfg.checkpoint.resume is True else Path(cfg.checkpoint.resume)
    if path is None:
        raise FileNotFoundError(f"checkpoint.resume=true but {run_dir}/checkpoints holds no checkpoint.")
    ckpt = load_checkpoint(path)
    saved = baselines.load_policy(ckpt.model_dir)
    if saved.kind != policy.kind:
        raise ValueError(f"{ckpt.path} holds a {saved.kind} policy but algo={policy.kind}; resume with algo={saved.kind}.")
    policy.load_state_dict(saved.state_dict())
    optimizer.load_state_dict(ckpt.trainer_state["optimizer"])
    scheduler.load_state_dict(ckpt.trainer_state["scheduler"])
    restore_rng_state(ckpt.trainer_state["rng"], generators)
    print(f"{PREFIX} resumed from {ckpt.path} at step {ckpt.step}")
    return ckpt.step


def evaluate(cfg: DictConfig, policy: ChunkPolicy) -> dict:
    """``eval/...`` metrics of the policy on ``cfg.eval.episodes`` fixed evaluation seeds."""
    from mmada_rl.evaluation import evaluate as run_eval

    result = run_eval(policy, cfg.env.task, episodes=int(cfg.eval.episodes), image_size=int(cfg.env.image_size),
                      control_mode=cfg.env.control_mode, max_episode_steps=cfg.eval.max_episode_steps,
                      execute_steps=int(cfg.eval.execute_steps), num_denoise_steps=cfg.eval.num_denoise_steps,
                      progress=False)
    return result.to_dict()
