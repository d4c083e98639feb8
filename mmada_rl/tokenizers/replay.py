"""Closed-loop proof of an action tokenizer: replay demonstrations through it.

Each stored demonstration is replayed open loop from its own reset seed, once
with its raw actions and once with the actions after an ``encode → decode``
round trip. Success is the task's own flag at any step (the demonstrations
stop at their first success). If tokenization loses what matters for the
task, the round-tripped replays fail where the raw ones succeed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from mmada_rl.envs.maniskill import EnvConfig, make_gym_env
from mmada_rl.keys import ACTION_KEY


@dataclass
class ReplayResult:
    """Success of open-loop replays, per episode and overall."""

    name: str
    successes: list[bool] = field(default_factory=list)

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else float("nan")

    def to_dict(self) -> dict:
        return {"name": self.name, "episodes": len(self.successes), "success_rate": self.success_rate}


def round_trip(tokenizer, actions: torch.Tensor) -> torch.Tensor:
    """``decode(encode(actions))`` in env units, without gradients."""
    with torch.no_grad():
        return tokenizer.decode(tokenizer.encode(actions))


def replay_demonstrations(buffer, tokenizers: dict[str, object | None], *, max_episodes: int | None = None,
                          progress: bool = True) -> dict[str, ReplayResult]:
    """Replay every demonstration of ``buffer`` with raw and round-tripped actions.

    Args:
        buffer: a :class:`~mmada_rl.data.buffer.DemoBuffer`.
        tokenizers: ``{name: tokenizer}``; ``None`` as the tokenizer replays the raw actions.
        max_episodes: replay only the first episodes.

    Returns:
        ``{name: ReplayResult}``.
    """
    meta = buffer.metadata
    # physics does not depend on rendering, so replays run state-only (several times faster)
    env = make_gym_env(EnvConfig(task=meta.task, obs_mode="state", control_mode=meta.control_mode,
                                 max_episode_steps=10 * (meta.max_episode_steps or 200)))
    results = {name: ReplayResult(name) for name in tokenizers}
    episodes = list(buffer.episodes())[:max_episodes]
    try:
        for ep in tqdm(episodes, desc="replay demonstrations", unit="ep", disable=not progress):
            seed = int(ep["seed"][0])
            actions = ep.get(ACTION_KEY)
            for name, tok in tokenizers.items():
                replayed = actions if tok is None else round_trip(tok, actions)
                env.reset(seed=seed)
                success = False
                for action in replayed.numpy():
                    *_, info = env.step(action.astype(np.float32))
                    if bool(np.asarray(info["success"]).any()):
                        success = True
                        break
                results[name].successes.append(success)
    finally:
        env.close()
    return results
