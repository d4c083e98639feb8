"""Factories of the imitation-baseline recipe: each ``make_*`` turns one config section into objects."""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mmada_rl import baselines
from mmada_rl.baselines import ChunkPolicy, NormalizationStats, RandomShift
from mmada_rl.data import DemoBuffer, StateDropout, make_window_buffer, window_skips
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl import training
from mmada_rl.training import WeightEMA, ema_checkpointed, make_optimizer, make_scheduler, make_weight_ema, save_checkpoint
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
        "image_size": int(meta.image_size or cfg.env.image_size),
        "obs_mode": meta.obs_mode,
        "camera_fov": meta.camera_fov,
        "encoder": OmegaConf.to_container(cfg.model.encoder),
        **OmegaConf.to_container(cfg.model[cfg.algo]),
    }
    return baselines.make_policy(cfg.algo, config, NormalizationStats.from_buffer(buffer)).to(cfg.device)


def make_data(cfg: DictConfig, buffer: DemoBuffer):
    """Chunk-window sampler over the demonstrations (seeded), with random-shift augmentation of the images and,
    with ``replay_buffer.state_drop_prob`` > 0, state dropout (:class:`~mmada_rl.data.StateDropout`)."""
    skips = window_skips(cfg.data)
    if skips["grasp_hold_gripper_only"]:
        raise ValueError("data.grasp_hold_gripper_only scores only the gripper tokens of some windows, which the "
                         "MMaDA-VLA losses do; the baselines' regression losses score every action entry. Leave it off.")
    data = make_window_buffer(buffer, int(cfg.model.chunk_size), int(cfg.replay_buffer.batch_size), seed=int(cfg.seed),
                              **skips)
    if int(cfg.replay_buffer.random_shift) and buffer.metadata.obs_mode == "rgb":
        data.append_transform(RandomShift(int(cfg.replay_buffer.random_shift)))
    p = float(cfg.replay_buffer.get("state_drop_prob", 0.0))
    if p > 0:
        if buffer.metadata.obs_mode != "rgb":
            raise ValueError(f"replay_buffer.state_drop_prob={p} drops the state, the only input of an "
                             f"obs_mode={buffer.metadata.obs_mode!r} policy; it applies to image policies only.")
        mean = NormalizationStats.from_buffer(buffer).state_mean
        keep = list(cfg.replay_buffer.get("state_drop_keep_dims", []) or [])
        try:
            data.append_transform(StateDropout(p, mean, keep_dims=keep))
        except ValueError as err:
            raise ValueError(f"replay_buffer.state_drop_prob / state_drop_keep_dims: {err}") from None
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
    return training.make_logger(cfg.logger.backend, run_dir)


def make_ema(cfg: DictConfig, policy: ChunkPolicy) -> WeightEMA | None:
    """The moving average of the policy's weights that is evaluated and saved (``ema.enabled``; null: diffusion_policy only)."""
    enabled = cfg.ema.enabled if cfg.ema.enabled is not None else cfg.algo == "diffusion_policy"
    return make_weight_ema(policy, cfg.ema, enabled=enabled)


def resume(cfg: DictConfig, run_dir: Path, policy: ChunkPolicy, optimizer, scheduler, generators: dict) -> tuple[int, dict]:
    """Restore weights, optimizer, scheduler and RNG states from ``checkpoint.resume``.

    Returns:
        the step to continue from (0: fresh run) and the checkpoint's ``extra`` dict. The policy holds the
        checkpoint's saved weights: the moving average when the run kept one (see :func:`save`).
    """
    def load_weights(model_dir: Path) -> None:
        saved = baselines.load_policy(model_dir)
        if saved.kind != policy.kind:
            raise ValueError(f"{model_dir} holds a {saved.kind} policy but algo={policy.kind}; resume with algo={saved.kind}.")
        policy.load_state_dict(saved.state_dict())

    ckpt = training.resume_training(cfg.checkpoint.resume, run_dir, load_weights=load_weights, optimizer=optimizer,
                                    scheduler=scheduler, generators=generators)
    if ckpt is None:
        return 0, {}
    print(f"{PREFIX} resumed from {ckpt.path} at step {ckpt.step}")
    return ckpt.step, ckpt.trainer_state["extra"]


def save(cfg: DictConfig, run_dir: Path, step: int, *, policy: ChunkPolicy, ema: WeightEMA | None, optimizer, scheduler,
         config: dict, generators: dict, history: list) -> None:
    """Checkpoint ``step``; with a moving average, ``model/`` holds the average (what is evaluated and loaded) and
    ``trainer.pt`` the optimizer's own weights to resume from. ``history``, the rows logged so far, travels in
    ``trainer.pt`` so that a resumed run's ``history.json`` starts at step 1."""
    with ema_checkpointed(ema) as extra:
        save_checkpoint(run_dir, step, model=policy, optimizer=optimizer, scheduler=scheduler, config=config,
                        generators=generators, extra={**extra, "history": history}, keep=int(cfg.checkpoint.keep))


def evaluate(cfg: DictConfig, policy: ChunkPolicy, record: Path | None = None, checkpoint: Path | None = None) -> dict:
    """``eval/...`` metrics of the policy on ``cfg.eval.episodes`` fixed evaluation seeds; with ``record``, the
    evaluation is also written there (``eval.json`` with every episode, ``eval.md``), naming ``checkpoint`` as the
    policy evaluated."""
    from mmada_rl.evaluation import evaluate as run_eval

    result = run_eval(policy, cfg.env.task, episodes=int(cfg.eval.episodes), image_size=policy.image_size,
                      control_mode=cfg.env.control_mode, max_episode_steps=cfg.eval.max_episode_steps,
                      execute_steps=int(cfg.eval.execute_steps), num_denoise_steps=cfg.eval.num_denoise_steps,
                      progress=False)
    if record is not None:
        result.checkpoint = str(checkpoint) if checkpoint else None
        result.save(record)
    return result.to_dict()
