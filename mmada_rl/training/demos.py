"""Opening the demonstration buffer a training recipe reads (collecting it first when needed)."""
from __future__ import annotations

from pathlib import Path

from mmada_rl.data import DemoBuffer
from mmada_rl.data.buffer import UNCHECKED
from mmada_rl.envs.maniskill import EnvConfig

__all__ = ["open_demos"]


def open_demos(path: str | Path, env: EnvConfig, *, collect_episodes: int = 0, action_noise: float = 0.0,
               workers: int = 1, prefix: str = "") -> DemoBuffer:
    """The buffer in ``path``, checked against ``env``; planner demonstrations are collected first
    while it holds fewer than ``collect_episodes`` episodes (0: never collect), executed with
    ``action_noise`` (DART, as ``mmada-rl collect --action-noise``; a buffer recorded with another
    noise is not topped up), by ``workers`` processes side by side (``mmada-rl collect --workers``).

    Raises:
        BufferMismatchError: the buffer's task, control mode, observation mode or
            image size or camera differs from ``env``'s (one sentence naming both values).
        FileNotFoundError: no buffer at ``path`` and ``collect_episodes == 0``.
    """
    path = Path(path)
    have = DemoBuffer.open(path).metadata.num_episodes if (path / "metadata.json").exists() else 0
    if collect_episodes and have < collect_episodes:
        from mmada_rl.data.collect import collect

        noise = f" (DART action noise {action_noise:g})" if action_noise else ""
        side = f" ({workers} processes side by side)" if workers > 1 else ""
        print(f"{prefix}collecting {collect_episodes - have} planner demonstrations{noise} into {path}{side}")
        collect(path, env, episodes=collect_episodes, action_noise=action_noise, workers=workers)
    rgb = env.obs_mode == "rgb"
    return DemoBuffer.open(path, task=env.task, control_mode=env.control_mode, obs_mode=env.obs_mode,
                           image_size=env.image_size if rgb else None, camera_fov=env.camera_fov if rgb else UNCHECKED)
