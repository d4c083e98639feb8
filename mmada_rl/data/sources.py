"""Where episodes come from: ManiSkill's motion planners, replayed action files, TorchRL policies,
trained policies' checkpoints.

Every source returns an :class:`Attempt`: the episode in TorchRL's rollout
layout (or ``None`` when it failed) and why it failed.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from mmada_rl.data.recording import StepRecorder
from mmada_rl.envs.maniskill import EnvConfig, make_gym_env
from mmada_rl.envs.tasks import task_spec
from mmada_rl.keys import ACTION_KEY

#: The control mode ManiSkill's motion-planning solutions command.
PLANNER_CONTROL_MODE = "pd_joint_pos"


@dataclass
class Attempt:
    """One try at an episode.

    Attributes:
        episode: the ``[T]`` tensordict, or ``None`` if nothing usable was produced.
        success: the task's own success was reached (the episode stops at the first success).
        reason: why the attempt is not kept, empty when it is.
    """

    episode: TensorDictBase | None
    success: bool
    reason: str = ""


class _ActionLog(gym.Wrapper):
    """Keeps the actions a planner sends, so they can be replayed in another control mode."""

    def reset(self, **kwargs):
        self.actions: list[np.ndarray] = []
        return self.env.reset(**kwargs)

    def step(self, action):
        self.actions.append(np.asarray(action, dtype=np.float32).copy())
        return self.env.step(action)


class NoisyExecution(gym.Wrapper):
    """Executes each action plus Gaussian noise on its first ``dims`` entries (DART's noise injection).

    Placed under the :class:`StepRecorder`, which keeps the action as given: the
    demonstration stores the expert's label while the env moves by the noisy
    action. With the planners' closed-loop conversion the next label steers back
    toward the planned path, so the demonstrations show recoveries from states
    slightly off it (Laskey et al., 2017, "DART: Noise Injection for Robust
    Imitation Learning"). The noise is reseeded from each reset's seed, so an
    episode is reproducible.

    Args:
        env: the recording env (normalised actions in ``[-1, 1]``).
        std: noise standard deviation, in normalised action units.
        dims: leading action entries that get noise (the arm; the gripper is left exact).
    """

    def __init__(self, env: gym.Env, std: float, dims: int):
        super().__init__(env)
        self.std, self.dims = float(std), int(dims)
        self.rng = np.random.default_rng(0)

    def reset(self, *, seed=None, **kwargs):
        if seed is not None:
            self.rng = np.random.default_rng([int(seed), 0xDA27])
        return self.env.reset(seed=seed, **kwargs)

    def step(self, action):
        noisy = np.array(action.cpu() if hasattr(action, "cpu") else action, dtype=np.float32).reshape(-1)
        noisy[: self.dims] += self.rng.normal(0.0, self.std, self.dims).astype(np.float32)
        return self.env.step(np.clip(noisy, -1.0, 1.0))


def planner_function(task: str) -> Callable:
    """ManiSkill's motion-planning solution for ``task``; a clear error where there is none."""
    name = task_spec(task).planner
    if name is None:
        from mmada_rl.envs.tasks import TASKS

        have = ", ".join(t for t, s in TASKS.items() if s.planner)
        raise ValueError(f"ManiSkill ships no motion-planning solution for {task!r}; tasks with one: {have}. "
                         "Use --policy random, or a scripted/TorchRL policy, for this task.")
    from mani_skill.examples.motionplanning.panda import solutions

    return getattr(solutions, name)


class ActionReplayer:
    """Replays actions from one control mode in a recording env of the configured control mode.

    Actions given in the recording env's own control mode are stepped as they
    are; ``pd_joint_pos`` actions (the planners' mode) are converted on the fly
    with ManiSkill's own closed-loop converter
    (``mani_skill.trajectory.utils.actions.conversion.from_pd_joint_pos``), which
    tracks the source env's joint targets in the target controller.

    Args:
        cfg: the recording env.
        keep_after_success: keep the steps after the first success (the rest of
            the replayed actions, up to ``cfg``'s episode length) instead of
            ending the episode at it.
        action_noise: execute every action with Gaussian noise of this standard
            deviation on its arm entries (:class:`NoisyExecution`; 0: exact).
    """

    def __init__(self, cfg: EnvConfig, keep_after_success: bool = False, action_noise: float = 0.0):
        if action_noise < 0:
            raise ValueError(f"action_noise must be >= 0, got {action_noise!r}.")
        self.cfg, self.keep_after_success = cfg, bool(keep_after_success)
        # the recorder runs past cfg's limit so over-long conversions are seen, then dropped
        limit = 4 * (cfg.episode_steps or 200)
        env = make_gym_env(EnvConfig(**{**cfg.to_dict(), "max_episode_steps": limit}))
        if action_noise > 0:
            env = NoisyExecution(env, action_noise, dims=env.action_space.shape[0] - 1)  # all but the gripper
        self.recorder = StepRecorder(env)
        self._source_envs: dict[str, gym.Env] = {}

    def source_env(self, control_mode: str) -> gym.Env:
        """A state-only env in ``control_mode`` that the converter steps alongside."""
        if control_mode not in self._source_envs:
            import mani_skill.envs  # noqa: F401

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self._source_envs[control_mode] = _ActionLog(
                    gym.make(
                        self.cfg.task,
                        obs_mode="state",
                        control_mode=control_mode,
                        sim_backend="physx_cpu",
                        render_backend="cpu",
                        max_episode_steps=100_000,
                    )
                )
        return self._source_envs[control_mode]

    def replay(self, actions: Sequence[np.ndarray], seed: int, source_control_mode: str) -> Attempt:
        """Reset to ``seed`` and replay ``actions``; record in the configured control mode."""
        rec = self.recorder
        rec.reset(seed=seed)
        if source_control_mode == self.cfg.control_mode:
            for action in actions:
                rec.step(np.asarray(action, dtype=np.float32))
                if rec.success[-1]:
                    break
        elif source_control_mode == PLANNER_CONTROL_MODE:
            from mani_skill.trajectory.utils.actions.conversion import from_pd_joint_pos

            src = self.source_env(source_control_mode)
            src.reset(seed=seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                from_pd_joint_pos(self.cfg.control_mode, list(actions), src.unwrapped, rec)
        else:
            raise ValueError(
                f"cannot convert actions from {source_control_mode!r} to {self.cfg.control_mode!r}; "
                f"only {PLANNER_CONTROL_MODE!r} sources convert to other control modes."
            )
        return self._finish()

    def _finish(self) -> Attempt:
        rec = self.recorder
        first = rec.first_success()
        if first is None:
            return Attempt(None, False, "no success after replay in the target control mode")
        stop = first + 1
        limit = self.cfg.episode_steps
        if limit is not None and stop > limit:
            return Attempt(None, True, f"success only after {stop} steps, beyond max_episode_steps={limit}")
        if self.keep_after_success:
            stop = len(rec) if limit is None else min(len(rec), limit)
        return Attempt(rec.episode(stop), True)

    def close(self) -> None:
        self.recorder.close()
        for env in self._source_envs.values():
            env.close()


class PlannerSource:
    """Demonstrations from ManiSkill's motion-planning solutions, recorded in ``cfg.control_mode``.

    Episodes end at the first success, or with ``keep_after_success`` at the end
    of the planner's path: a pick-and-place planner reaches the success region
    while still moving and only then slows down to a stop at the goal, so
    episodes cut at the first success never show the arm stopping there.
    ``action_noise`` executes the converted actions with noise (DART, see
    :class:`NoisyExecution`) and records the exact ones.
    """

    name = "planner"

    def __init__(self, cfg: EnvConfig, keep_after_success: bool = False, action_noise: float = 0.0):
        self.cfg = cfg
        self.solve = planner_function(cfg.task)
        self.replayer = ActionReplayer(cfg, keep_after_success, action_noise)

    @property
    def action_dim(self) -> int:
        return int(self.replayer.recorder.action_space.shape[0])

    @property
    def state_dim(self) -> int:
        return int(self.replayer.recorder.observation_space["proprio"].shape[0])

    def __call__(self, seed: int) -> Attempt:
        planner_env = self.replayer.source_env(PLANNER_CONTROL_MODE)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = self.solve(planner_env, seed=seed)
        except Exception as err:  # noqa: BLE001 - the planners raise on unreachable poses
            return Attempt(None, False, f"planner error: {err}")
        if result == -1:
            return Attempt(None, False, "planner found no plan")
        actions = list(planner_env.actions)
        return self.replayer.replay(actions, seed, PLANNER_CONTROL_MODE)

    def close(self) -> None:
        self.replayer.close()


class PolicySource:
    """Episodes of any TorchRL policy (``None``: uniform random actions) in ``make_env(cfg)``."""

    def __init__(self, cfg: EnvConfig, policy=None, name: str = "policy"):
        from torchrl.envs.utils import RandomPolicy

        from mmada_rl.envs.maniskill import make_env

        self.cfg = cfg
        self.env = make_env(cfg)
        self.policy = policy if policy is not None else RandomPolicy(self.env.action_spec)
        self.name = "random" if policy is None else name
        self.max_steps = cfg.episode_steps or 200
        self.action_dim = int(self.env.action_spec.shape[-1])
        self.state_dim = int(self.env.observation_spec["observation", "state"].shape[-1])

    def __call__(self, seed: int) -> Attempt:
        self.env.set_seed(seed)
        td = self.env.rollout(self.max_steps, self.policy, break_when_any_done=True)
        success = bool(td.get(("next", "success")).any())
        return Attempt(td, success)

    def close(self) -> None:
        self.env.close()


class CheckpointSource:
    """Episodes of a trained policy: one checkpoint, or several as one ensemble (what ``mmada-rl eval`` runs).

    The policy decodes greedily and executes its whole chunks, as in evaluation;
    every executed action is recorded (the :class:`~mmada_rl.policy.StepLog` of
    :func:`~mmada_rl.policy.make_policy_env`, which sees each step of a chunk,
    as :meth:`~mmada_rl.policy.StepLog.transitions`), so the buffer holds the policy's own
    behaviour in the demonstrations' format (e.g. a teacher's rollouts for a
    student to imitate). An episode ends at the task's first success, as a
    planner demonstration does, or at the time limit.

    The env takes the policy's camera, image size and observation mode; ``cfg``
    must agree where it names them (its ``camera_fov`` ``None``: the policy's).

    Args:
        cfg: the recording env (task, control mode, reward, episode length).
        checkpoints: run, checkpoint or model directories (two or more: their ensemble).
        device: where the policy runs.
    """

    name = "checkpoint"

    def __init__(self, cfg: EnvConfig, checkpoints: Sequence[str | Path], device: str = "cpu"):
        from mmada_rl.data.buffer import IMAGE_KEYS, TRANSITION_KEYS
        from mmada_rl.evaluation import eval_env_config, load_actor
        from mmada_rl.policy.execution import make_policy_env

        if not checkpoints:
            raise ValueError("a checkpoint source needs at least one policy directory (--checkpoint PATH).")
        actor = load_actor(list(checkpoints), device)
        policy_cfg = eval_env_config(actor, cfg.task, control_mode=cfg.control_mode, reward=cfg.reward,
                                     max_episode_steps=cfg.max_episode_steps)
        for name, flag in (("obs_mode", "--obs-mode"), ("image_size", "--image-size"), ("camera_fov", "--camera-fov")):
            given, policy = getattr(cfg, name), getattr(policy_cfg, name)
            if given != policy and not (name == "camera_fov" and given is None):
                fix = f"collect with {flag} {policy} (or leave it out)" if policy is not None else f"leave {flag} out"
                raise ValueError(f"the policy in {', '.join(map(str, checkpoints))} was trained with {name}={policy!r} "
                                 f"but {given!r} was asked for; {fix}.")
        self.cfg = dataclasses.replace(policy_cfg, ignore_terminations=False, stage_flags=False)
        self.keys = TRANSITION_KEYS + (IMAGE_KEYS if self.cfg.obs_mode == "rgb" else ())
        logged = {k[1:] if isinstance(k, tuple) and k[0] == "next" else k for k in self.keys} - {ACTION_KEY}
        self.penv = make_policy_env(self.cfg, actor, log_keys=sorted(logged, key=str))
        self.action_dim = int(self.penv.env.action_spec.shape[-1])
        if self.action_dim != self.penv.actor.action_dim:
            self.close()
            raise ValueError(f"{cfg.task} with control_mode={cfg.control_mode!r} takes {self.action_dim}-d actions but "
                             f"the policy outputs {self.penv.actor.action_dim}-d ones; collect in the control mode it "
                             "was trained in.")
        self.state_dim = int(self.penv.env.observation_spec["observation", "state"].shape[-1])

    def __call__(self, seed: int) -> Attempt:
        penv, limit = self.penv, self.cfg.episode_steps or 200
        torch.manual_seed(seed)  # a policy that draws noise (Diffusion Policy) repeats with the episode
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            td = penv.env.reset(seed=seed)
            for _ in range(limit + 1):  # decisions; the env ends the episode at success or its limit
                td = penv.env.step(penv.policy(td))
                if td.get(("next", "done")).any():
                    break
                td = step_mdp(td)
        episode = self.penv.step_log.transitions().select(*self.keys)
        return Attempt(episode, bool(episode.get(("next", "success")).any()))

    def close(self) -> None:
        self.penv.env.close()
