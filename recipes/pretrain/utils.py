"""Factories of the pretraining recipe: each ``make_*`` turns one config section into objects."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mmada_rl.data import DemoBuffer, MultiTaskWindows, RandomShift, check_shift, make_window_buffer, window_skips
from mmada_rl.data.windows import check_state_differences
from mmada_rl.diffusion import FullMaskMixture, UniformNoiseSchedule, make_noise_schedule
from mmada_rl.diffusion.schedules import check_probability
from mmada_rl.envs.maniskill import EnvConfig, task_camera_fov
from mmada_rl.envs.tasks import task_option
from mmada_rl.keys import GOAL_IMAGE_KEY, IMAGE_KEY
from mmada_rl.objectives import MaskedDiffusionLoss
from mmada_rl.policy import MMaDAConfig, MMaDAModel, Tokenizers
from mmada_rl.tokenizers.from_buffer import TokenizerFitConfig, fit_tokenizers
from mmada_rl import training
from mmada_rl.training import make_optimizer, make_scheduler
from mmada_rl.training.demos import open_demos
from mmada_rl.training.validation import fixed_windows


def make_env_config(cfg: DictConfig, task: str | None = None) -> EnvConfig:
    """``env`` for ``task`` (default ``env.task``); a multi-task run's ``env.camera_fov`` may map each task to its camera."""
    env = OmegaConf.to_container(cfg.env)
    task = task or env["task"]
    return EnvConfig(**{**env, "task": task, "camera_fov": task_camera_fov(env.get("camera_fov"), task)})


def task_list(cfg: DictConfig) -> list[str]:
    """The tasks the model is trained on: ``tasks`` (a multi-task model) or ``env.task``."""
    tasks = cfg.get("tasks")
    if tasks is None:
        return [str(cfg.env.task)]
    tasks = [str(t) for t in tasks]
    if not tasks or len(set(tasks)) != len(tasks):
        raise ValueError(f"tasks must list distinct task ids (or be null for env.task alone), got {tasks}.")
    return tasks


def task_dir(directory, task: str, option: str = "data.dir") -> str:
    """``task``'s buffer: ``directory`` with ``{task}`` filled in, or its entry when it maps each task to a buffer."""
    path = str(task_option(directory, task, option, "buffers", "<dir>"))
    return path if isinstance(directory, Mapping) else path.format(task=task)


def make_demo_buffers(cfg: DictConfig) -> list[DemoBuffer]:
    """The demonstration buffer of each task (``data.dir`` with ``{task}`` replaced, or a mapping task -> dir);
    collected first when missing or short."""
    tasks = task_list(cfg)
    directory = cfg.data.dir
    if len(tasks) > 1 and not isinstance(directory, Mapping) and "{task}" not in str(directory):
        raise ValueError(f"a multi-task run needs one buffer per task: put {{task}} in data.dir (got {directory!r}), "
                         "e.g. data.dir='data/{task}', or map each task to its buffer.")
    return [open_demos(task_dir(directory, task), make_env_config(cfg, task),
                       collect_episodes=int(cfg.data.collect_episodes),
                       action_noise=float(cfg.data.action_noise), workers=int(cfg.data.collect_workers),
                       prefix="[pretrain] ") for task in tasks]


def make_tokenizers(cfg: DictConfig, buffers: list[DemoBuffer], run_dir: Path) -> Tokenizers:
    """Load fitted tokenizers (``tokenizers.dir``) or fit them on the buffers into ``run_dir/tokenizers``."""
    tcfg = OmegaConf.to_container(cfg.tokenizers)
    directory = tcfg.pop("dir")
    options = tcfg["action"]
    if tcfg["action_type"] not in options:
        raise ValueError(f"tokenizers.action_type={tcfg['action_type']!r} has no options under tokenizers.action "
                         f"(has {sorted(options)}); add tokenizers.action.{tcfg['action_type']}={{...}}.")
    tcfg["action"] = options[tcfg["action_type"]]
    if directory is None:
        directory = run_dir / "tokenizers"
        if not (directory / "action").exists():
            fit = TokenizerFitConfig(**{**tcfg, "seed": int(cfg.seed), "state_differences": state_differences(cfg)})
            if "hidden_sizes" in fit.action:  # learned tokenizers only (bins have no network)
                fit.action["hidden_sizes"] = tuple(fit.action["hidden_sizes"])
            fitted = fit_tokenizers(buffers, fit)
            fitted.save(directory)
    tokenizers = Tokenizers.load(directory)
    buffer = buffers[0]
    if tokenizers.image.config.image_size != buffer.metadata.image_size:
        raise ValueError(f"the image tokenizer in {directory} was fitted on {tokenizers.image.config.image_size}px images "
                         f"but the buffer holds {buffer.metadata.image_size}px ones; refit or use matching env.image_size.")
    state_dim = max(b.metadata.state_dim for b in buffers)
    differences = state_differences(cfg)
    if tokenizers.proprio is not None and differences and tokenizers.proprio.config.action_dim != state_dim + len(differences):
        raise ValueError(f"the proprio tokenizer in {directory} covers {tokenizers.proprio.config.action_dim} dimensions, "
                         f"not the demonstrations' {state_dim} plus the {len(differences)} of model.state_differences="
                         f"{differences}; fit it with them (tokenizers.dir=null, or `mmada-rl fit-tokenizers "
                         "--state-differences`).")
    if tokenizers.proprio is not None and tokenizers.proprio.config.action_dim < state_dim:
        raise ValueError(f"the proprio tokenizer in {directory} covers {tokenizers.proprio.config.action_dim} state "
                         f"dimensions but the demonstrations have {state_dim}; fit tokenizers on these tasks.")
    return tokenizers


def state_differences(cfg: DictConfig) -> list[list[int]]:
    """``model.state_differences`` as checked pairs of ints (absent from older configs: none)."""
    return check_state_differences(cfg.model.get("state_differences", None))


def make_model(cfg: DictConfig, tokenizers: Tokenizers) -> MMaDAModel:
    m = cfg.model
    config = MMaDAConfig(
        chunk_size=int(m.chunk_size),
        predict_goal=bool(m.predict_goal),
        use_proprio=bool(m.use_proprio),
        observation_tokens=bool(m.observation_tokens),
        proprio_drop_dims=[int(d) for d in m.proprio_drop_dims],
        state_differences=state_differences(cfg),
        interleave=bool(m.interleave),
        denoiser=m.denoiser if isinstance(m.denoiser, str) else OmegaConf.to_container(m.denoiser),
        denoiser_overrides=OmegaConf.to_container(m.denoiser_overrides),
        sampler={"num_steps": int(m.num_denoise_steps), "schedule": m.sampler_schedule, "kernel": cfg.loss.kernel},
        camera_fov=cfg.env.camera_fov,  # a per-task mapping becomes a plain dict in MMaDAConfig
        action_readout=str(m.action_readout),
    )
    model = MMaDAModel(config, tokenizers)
    init_visual_encoder(cfg, model)
    return model.to(cfg.device)


def init_visual_encoder(cfg: DictConfig, model: MMaDAModel) -> None:
    """``model.visual_encoder_init``: copy a baseline policy's image CNN (e.g. BC trained on the same
    demonstrations) into the denoiser's own CNN; ``model.visual_encoder_freeze`` keeps it fixed."""
    m = cfg.model
    source, freeze = m.get("visual_encoder_init", None), bool(m.get("visual_encoder_freeze", False))
    if source is None:
        if freeze:
            raise ValueError("model.visual_encoder_freeze=true fixes a CNN copied from model.visual_encoder_init; "
                             "set that to a baseline run (e.g. runs/bc_PickCube-v1_s0) or leave the freeze off.")
        return
    encoder = model.denoiser.visual_encoder
    if encoder is None:
        raise ValueError("model.visual_encoder_init copies a CNN into the denoiser's own, which it does not have: "
                         "set model.denoiser_overrides.visual_encoder_channels (e.g. [32, 64, 128]) and "
                         "cross_attention_to_visual=true.")
    from mmada_rl.baselines import is_policy_dir, load_policy
    from mmada_rl.evaluation import resolve_model_dir

    directory = resolve_model_dir(source)
    if not is_policy_dir(directory):
        raise ValueError(f"model.visual_encoder_init={source!r} is not a baseline policy (BC or Diffusion Policy); "
                         f"{directory} holds another kind of model.")
    policy = load_policy(directory)
    if policy.encoder.cnn is None:
        raise ValueError(f"model.visual_encoder_init={source!r} is a state-based policy: it has no image CNN.")
    for task in task_list(cfg):
        env = make_env_config(cfg, task)
        if (policy.image_size, policy.camera_fov) != (env.image_size, env.camera_fov):
            raise ValueError(f"model.visual_encoder_init={source!r} read {policy.image_size}px images through a "
                             f"camera_fov={policy.camera_fov} camera; this run's {task} images are {env.image_size}px "
                             f"with camera_fov={env.camera_fov}.")
    encoder.load_conv_stack(policy.encoder.cnn, freeze=freeze)
    print(f"[pretrain] the denoiser's CNN starts from {directory}'s" + (" (frozen)" if freeze else ""))


def make_data(cfg: DictConfig, buffers: list[DemoBuffer]):
    """Chunk-window sampler over the demonstrations (seeded, so resumption replays the same batches);
    with several tasks, every batch mixes their windows (``data.task_weights``). With
    ``replay_buffer.random_shift`` > 0 the observation image and its goal frame are shifted together."""
    K, batch, seed = int(cfg.model.chunk_size), int(cfg.replay_buffer.batch_size), int(cfg.seed)
    skips = window_skips(cfg.data)
    if len(buffers) == 1:
        data = make_window_buffer(buffers[0], K, batch, seed=seed, **skips)
    else:
        weights = cfg.data.get("task_weights", "uniform")
        weights = weights if isinstance(weights, str) else list(weights)
        data = MultiTaskWindows(buffers, K, batch, weights=weights, seed=seed, **skips)
    pad = check_shift(cfg.replay_buffer.get("random_shift", 0), "replay_buffer.random_shift")
    if pad:
        data.append_transform(RandomShift(pad, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY]))
    return data


def make_loss(cfg: DictConfig, model: MMaDAModel) -> MaskedDiffusionLoss:
    l = cfg.loss
    schedule = UniformNoiseSchedule(float(l.schedule_low), float(l.schedule_high)) if l.schedule == "uniform" else l.schedule
    full = float(l.get("full_mask_prob", 0.0))  # the share of windows with every target masked
    check_probability("loss.full_mask_prob", full)
    if full > 0:
        schedule = FullMaskMixture(make_noise_schedule(schedule), full)
    sigma = float(l.action_label_sigma)
    mean_weight = float(l.get("action_mean_weight", 0.0))
    for name, value, what in (("action_label_sigma", sigma, "smooths the targets over neighbouring bins"),
                              ("action_mean_weight", mean_weight, "scores the expected bin of each action token")):
        if value > 0:
            model.action_tokenizer.require_ordered_bins(f"loss.{name}={value} {what}")
    if window_skips(cfg.data)["grasp_hold_gripper_only"]:
        model.action_tokenizer.require_ordered_bins("data.grasp_hold_gripper_only scores the gripper's token of each action")
    return MaskedDiffusionLoss(
        model.denoiser, schedule=schedule, kernel=l.kernel, action_weight=float(l.action_weight),
        goal_weight=float(l.goal_weight), condition_mask_prob=float(l.condition_mask_prob),
        proprio_drop_prob=float(l.proprio_drop_prob), proprio_drop_index=proprio_drop_index(cfg, model),
        corruptions_per_sample=int(l.corruptions_per_sample), action_label_sigma=sigma,
        action_mean_weight=mean_weight,
    )


def proprio_drop_index(cfg: DictConfig, model: MMaDAModel) -> list[int] | None:
    """The proprio tokens state dropout masks: all but those of ``loss.proprio_drop_keep_dims`` (None: all)."""
    keep = [int(d) for d in cfg.loss.get("proprio_drop_keep_dims", None) or []]
    if not keep:
        return None
    if not float(cfg.loss.proprio_drop_prob) > 0:
        raise ValueError(f"loss.proprio_drop_keep_dims={keep} names the state dropout keeps, but it is off "
                         "(loss.proprio_drop_prob=0).")
    return model.proprio_drop_index(keep, name="loss.proprio_drop_keep_dims")


def make_optim(cfg: DictConfig, model: MMaDAModel):
    o = cfg.optim
    optimizer = make_optimizer(model.denoiser.parameters(), lr=float(o.lr), weight_decay=float(o.weight_decay))
    scheduler = make_scheduler(optimizer, warmup_steps=int(o.warmup_steps), total_steps=int(o.total_steps))
    return optimizer, scheduler


def make_logger(cfg: DictConfig, run_dir: Path):
    return training.make_logger(cfg.logger.backend, run_dir)


def make_validation(cfg: DictConfig, model: MMaDAModel) -> list | None:
    """Fixed window batches of the held-out buffer(s) ``validation.dir`` (as ``data.dir``: one per task), checked
    against the env config like the training demonstrations; ``None`` without ``validation.dir``."""
    if cfg.validation.dir is None:
        return None
    batches = []
    for task in task_list(cfg):
        buffer = open_demos(task_dir(cfg.validation.dir, task, "validation.dir"), make_env_config(cfg, task))
        batches += fixed_windows(buffer, model.config.chunk_size, int(cfg.validation.minibatches),
                                 int(cfg.validation.batch_size), seed=int(cfg.seed))
    return batches
