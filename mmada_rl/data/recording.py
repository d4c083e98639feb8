"""Record what a gym env sees into a TorchRL-layout episode tensordict.

ManiSkill's motion planners and its control-mode converter drive a gym env
directly (not a TorchRL env), so their episodes are captured by a gym wrapper
and laid out exactly as ``make_env(...).rollout(...)`` would lay them out.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from mmada_rl.keys import ACTION_KEY, IMAGE_KEY, STATE_KEY, STEP_KEY


class StepRecorder(gym.Wrapper):
    """Keeps every observation, action, reward, flag and success since the last reset.

    Wraps the env returned by :func:`mmada_rl.envs.maniskill.make_gym_env`.
    """

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.observations = [obs]
        self.actions, self.rewards, self.terminated, self.truncated, self.success = [], [], [], [], []
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.observations.append(obs)
        self.actions.append(np.asarray(action.cpu() if torch.is_tensor(action) else action, dtype=np.float32).reshape(-1))
        self.rewards.append(float(reward))
        self.terminated.append(bool(terminated))
        self.truncated.append(bool(truncated))
        self.success.append(bool(np.asarray(info["success"]).any()))
        return obs, reward, terminated, truncated, info

    def __len__(self) -> int:
        return len(self.actions)

    def first_success(self) -> int | None:
        """Index of the first step whose resulting state is a success, if any."""
        return next((t for t, s in enumerate(self.success) if s), None)

    def episode(self, stop: int | None = None) -> TensorDict:
        """The recorded steps ``[0, stop)`` as a ``[T]`` tensordict in TorchRL's rollout layout.

        The last kept step is marked done (terminated where the env said so or
        where it is a success, truncated otherwise), so the stored episode ends there.
        """
        T = len(self) if stop is None else stop
        if T == 0:
            raise ValueError("no step recorded since the last reset.")

        def obs_td(frames):
            out = {STATE_KEY[-1]: torch.from_numpy(np.stack([f["proprio"] for f in frames]))}
            if "camera" in frames[0]:
                out[IMAGE_KEY[-1]] = torch.from_numpy(np.stack([f["camera"] for f in frames]))
            return out

        terminated = torch.tensor(self.terminated[:T]).unsqueeze(-1)
        truncated = torch.tensor(self.truncated[:T]).unsqueeze(-1)
        success = torch.tensor(self.success[:T]).unsqueeze(-1)
        terminated[-1] |= success[-1]
        truncated[-1] |= ~terminated[-1]
        return TensorDict(
            {
                "observation": obs_td(self.observations[:T]),
                ACTION_KEY: torch.from_numpy(np.stack(self.actions[:T])),
                STEP_KEY: torch.arange(T).unsqueeze(-1),
                "next": {
                    "observation": obs_td(self.observations[1 : T + 1]),
                    "reward": torch.tensor(self.rewards[:T], dtype=torch.float32).unsqueeze(-1),
                    "terminated": terminated,
                    "truncated": truncated,
                    "done": terminated | truncated,
                    "success": success,
                },
            },
            batch_size=[T],
        )
