"""Import ManiSkill's own trajectory format (``.h5`` + ``.json`` from ``RecordEpisode``).

ManiSkill records actions, env states and flags, and observations only in the
observation mode it ran with (often none). We re-simulate each trajectory from
its recorded reset seed in an env built from the target :class:`EnvConfig` —
as ManiSkill's own ``replay_trajectory`` tool does — so the imported
observations have exactly the layout, camera and image size of every other
buffer. Actions recorded in ``pd_joint_pos`` are converted to the target
control mode on the way; actions already in the target mode replay as they are.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from tqdm.auto import tqdm

from mmada_rl.data.buffer import DemoBuffer
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.data.sources import ActionReplayer
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.envs.tasks import task_spec


@dataclass
class ImportResult:
    buffer: DemoBuffer
    imported: int
    skipped: dict[str, int]


def read_trajectory_json(h5_path: Path) -> dict:
    """The ``.json`` that ``RecordEpisode`` writes beside ``h5_path``."""
    json_path = Path(h5_path).with_suffix(".json")
    if not json_path.exists():
        raise FileNotFoundError(f"{json_path} not found: ManiSkill writes it beside {h5_path}; both are needed.")
    return json.loads(json_path.read_text())


def import_h5(h5_path: str | Path, out: str | Path, cfg: EnvConfig | None = None, *, only_success: bool = True, progress: bool = True) -> ImportResult:
    """Import every trajectory of ``h5_path`` into the buffer ``out``.

    Args:
        h5_path: a ManiSkill ``.h5`` trajectory file (its ``.json`` must sit beside it).
        out: buffer directory (created, or appended to if it matches).
        cfg: target env; defaults to the recorded task with our default observation
            and control settings (``pd_ee_delta_pose``, 64×64 RGB).
        only_success: skip trajectories that do not reach success after replay.
    """
    h5_path = Path(h5_path)
    info = read_trajectory_json(h5_path)
    task = info["env_info"]["env_id"]
    cfg = cfg or EnvConfig(task=task)
    if cfg.task != task:
        raise ValueError(f"{h5_path} holds {task!r} trajectories but the target env is {cfg.task!r}.")
    replayer = ActionReplayer(cfg)
    meta = BufferMetadata(
        task=task,
        control_mode=cfg.control_mode,
        obs_mode=cfg.obs_mode,
        image_size=cfg.image_size if cfg.obs_mode == "rgb" else 0,
        action_dim=int(replayer.recorder.action_space.shape[0]),
        state_dim=int(replayer.recorder.observation_space["proprio"].shape[0]),
        reward=cfg.reward,
        max_episode_steps=cfg.episode_steps,
        source="h5",
    )
    episodes = info["episodes"]
    buffer = DemoBuffer.open_or_create(out, meta, capacity=len(episodes) * (cfg.episode_steps or 200))
    skipped: dict[str, int] = {}
    imported = 0
    instruction = task_spec(task).instruction
    try:
        with h5py.File(h5_path, "r") as f:
            for ep in tqdm(episodes, desc=f"import {h5_path.name}", unit="traj", disable=not progress):
                actions = np.asarray(f[f"traj_{ep['episode_id']}"]["actions"], dtype=np.float32)
                seed = ep.get("reset_kwargs", {}).get("seed", ep.get("episode_seed"))
                if isinstance(seed, list):
                    seed = seed[0]
                control_mode = ep.get("control_mode") or info["env_info"]["env_kwargs"].get("control_mode")
                attempt = replayer.replay(list(actions), int(seed), control_mode)
                buffer.metadata.attempts += 1
                buffer.metadata.successes += int(attempt.success)
                if attempt.episode is None or (only_success and not attempt.success):
                    reason = attempt.reason or "no success"
                    skipped[reason] = skipped.get(reason, 0) + 1
                    continue
                buffer.add_episode(attempt.episode, seed=int(seed), instruction=instruction)
                imported += 1
    finally:
        buffer.save_metadata()
        replayer.close()
    return ImportResult(buffer, imported, skipped)
