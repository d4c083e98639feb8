"""Scripted experts: closed-loop end-effector controllers that read the simulator's true state.

They are the demonstration source for tasks (or control modes) that ManiSkill's
motion planners do not cover, and a cheap, planner-free check that a task is
solvable in ``pd_ee_delta_pose``. Each expert maps the unwrapped ManiSkill env
to one normalised ``pd_ee_delta_pose`` action ``[dx, dy, dz, 0, 0, 0, gripper]``
(a proportional step toward the phase's target position, saturating at
ManiSkill's 0.1 m per step; the orientation is held; gripper +1 open, -1 closed).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from mmada_rl.data.recording import StepRecorder
from mmada_rl.data.sources import Attempt
from mmada_rl.envs.maniskill import EnvConfig, make_gym_env

OPEN, CLOSED = 1.0, -1.0
_MAX_DELTA = 0.1  # metres per step at action 1 (ManiSkill's pd_ee_delta_pose)


def _p(pose) -> np.ndarray:
    return pose.p.reshape(-1, 3)[0].cpu().numpy().astype(np.float64)


def _move(tcp: np.ndarray, target: np.ndarray, gripper: float, gain: float = 1.0) -> np.ndarray:
    delta = np.clip(gain * (target - tcp) / _MAX_DELTA, -1.0, 1.0)
    return np.concatenate([delta, np.zeros(3), [gripper]]).astype(np.float32)


class PickPlaceExpert:
    """PickCube: above the cube, down, close, carry to the goal."""

    def __init__(self):
        self.phase, self.hold = "above", 0

    def __call__(self, env) -> np.ndarray:
        tcp, cube, goal = _p(env.agent.tcp.pose), _p(env.cube.pose), _p(env.goal_site.pose)
        if self.phase == "above":
            target = cube + [0, 0, 0.06]
            if np.linalg.norm(tcp - target) < 0.01:
                self.phase = "down"
            return _move(tcp, target, OPEN)
        if self.phase == "down":
            if np.linalg.norm(tcp - cube) < 0.006:
                self.phase = "grasp"
            return _move(tcp, cube, OPEN)
        if self.phase == "grasp":
            self.hold += 1
            if self.hold >= 6:
                self.phase = "carry"
            return _move(tcp, cube, CLOSED)
        return _move(tcp, goal, CLOSED, gain=0.6)


class PushExpert:
    """PushCube / PullCube: get behind the cube on the side away from the goal, then push it to the goal."""

    def __init__(self):
        self.phase = "above"

    def __call__(self, env) -> np.ndarray:
        tcp, cube, goal = _p(env.agent.tcp.pose), _p(env.obj.pose), _p(env.goal_region.pose)
        direction = goal[:2] - cube[:2]
        direction /= max(np.linalg.norm(direction), 1e-6)
        behind = cube.copy()
        behind[:2] -= direction * 0.05
        behind[2] = 0.02
        if self.phase == "above":
            target = behind + [0, 0, 0.08]
            if np.linalg.norm(tcp[:2] - target[:2]) < 0.01:
                self.phase = "down"
            return _move(tcp, target, CLOSED)
        if self.phase == "down":
            if abs(tcp[2] - behind[2]) < 0.01:
                self.phase = "push"
            return _move(tcp, behind, CLOSED)
        target = np.array([goal[0], goal[1], 0.02]) - np.r_[direction * 0.02, 0]
        return _move(tcp, target, CLOSED, gain=0.5)


EXPERTS: dict[str, Callable[[], Callable]] = {
    "PickCube-v1": PickPlaceExpert,
    "PushCube-v1": PushExpert,
    "PullCube-v1": PushExpert,
}
_CONTROL_MODES = ("pd_ee_delta_pose",)


class ScriptedSource:
    """Episodes of the scripted expert of ``cfg.task``, recorded in ``cfg.control_mode``."""

    name = "scripted"

    def __init__(self, cfg: EnvConfig):
        if cfg.task not in EXPERTS:
            raise ValueError(f"no scripted expert for {cfg.task!r}; scripted experts exist for {sorted(EXPERTS)}.")
        if cfg.control_mode not in _CONTROL_MODES:
            raise ValueError(f"the scripted experts command {_CONTROL_MODES[0]!r}, not {cfg.control_mode!r}; "
                             "collect with --control-mode pd_ee_delta_pose (or use the planner for other modes).")
        self.cfg = cfg
        self.recorder = StepRecorder(make_gym_env(cfg))
        self.action_dim = int(self.recorder.action_space.shape[0])
        self.state_dim = int(self.recorder.observation_space["proprio"].shape[0])

    def __call__(self, seed: int) -> Attempt:
        rec = self.recorder
        rec.reset(seed=seed)
        expert = EXPERTS[self.cfg.task]()
        for _ in range(self.cfg.episode_steps or 200):
            _, _, terminated, truncated, info = rec.step(expert(rec.unwrapped))
            if rec.success[-1]:
                return Attempt(rec.episode(len(rec)), True)
            if truncated:
                break
        return Attempt(rec.episode(len(rec)), False, "scripted expert did not succeed within the episode")

    def close(self) -> None:
        self.recorder.close()
