"""Fill a buffer directory with episodes from a source, resumably."""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Sequence

from tqdm.auto import tqdm

from mmada_rl.data.buffer import BufferMismatchError, DemoBuffer
from mmada_rl.data.collect_workers import parallel_attempts
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.data.sources import CheckpointSource, PlannerSource, PolicySource
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.envs.tasks import task_spec

SOURCES = ("planner", "scripted", "random", "checkpoint")


@dataclass
class CollectResult:
    """What a collection run did."""

    buffer: DemoBuffer
    new_episodes: int
    attempts: int
    successes: int
    steps: int
    seconds: float
    failures: dict[str, int]

    @property
    def success_rate(self) -> float:
        return self.successes / self.attempts if self.attempts else float("nan")


def make_source(cfg: EnvConfig, policy: str = "planner", torchrl_policy=None, keep_after_success: bool = False,
                action_noise: float = 0.0, checkpoint: Sequence[str | Path] = ()):
    """The episode source named ``policy`` (``"planner"``, ``"scripted"``, ``"random"``, ``"checkpoint"``: the
    policy saved in ``checkpoint``, several as one ensemble), or a TorchRL policy object."""
    if (keep_after_success or action_noise) and (policy != "planner" or torchrl_policy is not None):
        raise ValueError("keep_after_success and action_noise apply to the motion planner's demonstrations "
                         "(--policy planner) only.")
    if bool(checkpoint) != (policy == "checkpoint" and torchrl_policy is None):
        raise ValueError("--policy checkpoint records the policy given by --checkpoint PATH [PATH ...]; "
                         "--checkpoint goes with it alone.")
    if torchrl_policy is not None:
        return PolicySource(cfg, torchrl_policy)
    if policy == "planner":
        return PlannerSource(cfg, keep_after_success, action_noise)
    if policy == "scripted":
        from mmada_rl.data.scripted import ScriptedSource

        return ScriptedSource(cfg)
    if policy == "random":
        return PolicySource(cfg, None)
    if policy == "checkpoint":
        return CheckpointSource(cfg, checkpoint)
    raise ValueError(f"unknown --policy {policy!r}; choose one of {SOURCES}.")


def collect(
    out: str | Path,
    cfg: EnvConfig,
    *,
    episodes: int,
    policy: str = "planner",
    torchrl_policy=None,
    checkpoint: Sequence[str | Path] = (),
    only_success: bool | None = None,
    keep_after_success: bool = False,
    action_noise: float = 0.0,
    seed: int = 0,
    max_attempts: int | None = None,
    workers: int = 1,
    progress: bool = True,
) -> CollectResult:
    """Collect until ``out`` holds ``episodes`` episodes; resume what is there.

    Args:
        out: buffer directory; created, or resumed when it already holds a
            buffer of the same task, control mode, observation mode and image size.
        cfg: the environment the episodes are recorded in.
        episodes: total number of episodes the buffer should hold.
        policy: ``"planner"`` (ManiSkill's motion planner, converted to
            ``cfg.control_mode``), ``"scripted"`` (a state-based expert, see
            :mod:`mmada_rl.data.scripted`), ``"random"`` or ``"checkpoint"``
            (a trained policy, :class:`~mmada_rl.data.sources.CheckpointSource`).
        torchrl_policy: any TorchRL policy module; overrides ``policy``.
        checkpoint: with ``policy="checkpoint"``, the policy's run, checkpoint or
            model directories (two or more: their ensemble). The buffer takes the
            policy's camera, image size and observation mode.
        only_success: keep only episodes that reach success (default: True for
            the planner and scripted experts, False otherwise).
        keep_after_success: planner episodes run to the end of the planner's
            path instead of ending at the first success (see :class:`PlannerSource`).
        action_noise: planner episodes execute their actions with Gaussian noise of
            this std on the arm (DART) and store the exact ones (see :class:`NoisyExecution`).
        seed: first env seed of a new buffer (a resumed one continues from its ``next_seed``).
        max_attempts: stop after this many tries in this run (default: 3 × missing episodes + 10).
        workers: processes trying the next seeds side by side, each with its own simulator
            (:func:`~mmada_rl.data.collect_workers.parallel_attempts`); their attempts are taken in
            seed order, as one process takes them (the episodes can differ from one process's in the last
            digits: see that module). Not with ``torchrl_policy``.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be positive, got {episodes}.")
    if workers < 1 or (workers > 1 and torchrl_policy is not None):
        raise ValueError(f"workers must be a positive number of processes (1 with a TorchRL policy object, which "
                         f"the worker processes cannot rebuild), got {workers}.")
    only_success = (policy in ("planner", "scripted") and torchrl_policy is None) if only_success is None else only_success
    cfg_in = cfg
    source = make_source(cfg, policy, torchrl_policy, keep_after_success, action_noise, checkpoint)
    cfg = source.cfg  # the env the source records in (a checkpoint's: its camera and image size)
    meta = BufferMetadata(
        task=cfg.task,
        control_mode=cfg.control_mode,
        obs_mode=cfg.obs_mode,
        image_size=cfg.image_size if cfg.obs_mode == "rgb" else 0,
        action_dim=source.action_dim,
        state_dim=source.state_dim,
        reward=cfg.reward,
        camera_fov=cfg.camera_fov if cfg.obs_mode == "rgb" else None,
        max_episode_steps=cfg.episode_steps,
        source=source.name,
        keep_after_success=bool(keep_after_success),
        action_noise=float(action_noise),
        checkpoint=[str(c) for c in checkpoint],
        next_seed=seed,
    )
    longest = cfg.episode_steps or 200  # steps an episode may take: what the storage is allocated by
    buffer = DemoBuffer.open_or_create(out, meta, capacity=episodes * longest)
    recorded = {k: getattr(buffer.metadata, k) for k in ("keep_after_success", "action_noise", "checkpoint")}
    if recorded != {k: getattr(meta, k) for k in recorded}:
        source.close()
        settings = ", ".join(f"{k}={v}" for k, v in recorded.items())
        raise BufferMismatchError(f"{out} holds episodes recorded with {settings}; resume it with the same "
                                  "settings or collect into another directory.")
    missing = episodes - buffer.metadata.num_episodes
    if missing > 0 and len(buffer) + missing * longest > buffer.metadata.capacity:
        # a resumed buffer keeps the storage it was created with: say so now, not after minutes of collection
        source.close()
        raise ValueError(
            f"{out} was allocated for {buffer.metadata.capacity} transitions and holds {len(buffer)} "
            f"({buffer.metadata.num_episodes} episodes); {missing} more episodes of up to {longest} steps may not fit. "
            f"Collect into a new directory with --episodes {episodes} (the same --seed records the same first episodes)."
        )
    max_attempts = max_attempts if max_attempts is not None else 3 * max(missing, 0) + 10
    instruction = task_spec(cfg.task).instruction
    result = CollectResult(buffer, 0, 0, 0, 0, 0.0, {})
    start = time.perf_counter()
    bar = tqdm(total=episodes, initial=buffer.metadata.num_episodes, unit="ep", desc=f"collect {cfg.task}", disable=not progress)
    first = buffer.metadata.next_seed
    if workers > 1:  # each worker builds its own source from the same arguments; this one served the metadata
        source.close()
        attempts = parallel_attempts(partial(make_source, cfg_in, policy, None, keep_after_success, action_noise,
                                             checkpoint), workers, first, max_attempts)
    else:
        attempts = ((seed, source(seed)) for seed in itertools.count(first))
    try:
        while buffer.metadata.num_episodes < episodes and result.attempts < max_attempts:
            env_seed, attempt = next(attempts)
            result.attempts += 1
            result.successes += int(attempt.success)
            buffer.metadata.attempts += 1
            buffer.metadata.successes += int(attempt.success)
            buffer.metadata.next_seed = env_seed + 1
            keep = attempt.episode is not None and (attempt.success or not only_success)
            if keep:
                buffer.add_episode(attempt.episode, seed=env_seed, instruction=instruction)
                result.new_episodes += 1
                result.steps += attempt.episode.shape[0]
                bar.update(1)
            else:
                reason = attempt.reason or "no success"
                result.failures[reason] = result.failures.get(reason, 0) + 1
                buffer.save_metadata()
            elapsed = time.perf_counter() - start
            bar.set_postfix(
                success=f"{result.success_rate:.0%}",
                steps_per_s=f"{result.steps / max(elapsed, 1e-9):.1f}",
                ep_per_min=f"{60 * result.new_episodes / max(elapsed, 1e-9):.1f}",
            )
    finally:
        attempts.close()  # stops the workers
        bar.close()
        result.seconds = time.perf_counter() - start
        if workers == 1:
            source.close()
    return result
