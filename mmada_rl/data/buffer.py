"""A directory-backed buffer of episodes: TorchRL replay buffer on memmap + metadata.

Layout of a buffer directory::

    DIR/metadata.json      BufferMetadata (task, control mode, sizes, stats, seeds, versions)
    DIR/storage/           LazyMemmapStorage files (written in place, never copied)
    DIR/sampler, DIR/writer, DIR/buffer_metadata.json   TorchRL's own ``dumps`` state

Each stored item is one transition in TorchRL's layout (``observation``, ``action``,
``next/{observation, reward, done, terminated, truncated, success}``, ``step_count``)
plus ``episode`` (trajectory id), ``instruction_id`` and ``seed``. The
instruction is kept as an index into ``metadata.instructions`` because memmap
storages do not keep per-item strings; :class:`InstructionLookup` puts the text
back under ``language_instruction`` when sampling.

Commit order per episode: ``extend`` → ``dumps`` → ``metadata.json`` (atomic).
The storage length TorchRL records is only advanced by ``dumps``, so a process
killed mid-episode leaves the directory at its last finished episode.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer
from torchrl.envs.transforms import Transform

from mmada_rl.data.metadata import METADATA_FILE, BufferMetadata
from mmada_rl.instructions import instruction_entry
from mmada_rl.keys import (
    ACTION_KEY,
    EPISODE_KEY,
    IMAGE_KEY,
    INSTRUCTION_ID_KEY,
    INSTRUCTION_KEY,
    SEED_KEY,
    STATE_KEY,
    STEP_KEY,
    TEACHER_CHUNK_KEY,
)

#: Keys every stored transition carries (beside ``episode``, ``instruction_id``, ``seed``).
TRANSITION_KEYS = (
    STATE_KEY,
    ACTION_KEY,
    ("next", *STATE_KEY),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "success"),
    STEP_KEY,
)
IMAGE_KEYS = (IMAGE_KEY, ("next", *IMAGE_KEY))

#: ``DemoBuffer.open(camera_fov=UNCHECKED)``: accept any camera (``None`` there means the task's own camera).
UNCHECKED = object()


class BufferMismatchError(ValueError):
    """A buffer's task, control mode, observation mode, image size or camera differs from what is asked."""


class InstructionLookup(Transform):
    """Replay-buffer transform: ``instruction_id`` → ``language_instruction`` text."""

    def __init__(self, instructions: list[str]):
        super().__init__(in_keys=[INSTRUCTION_ID_KEY], out_keys=[INSTRUCTION_KEY])
        self.instructions = list(instructions)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        ids = tensordict.get(INSTRUCTION_ID_KEY)
        texts = instruction_entry(self.instructions, ids.reshape(-1).tolist(), ids.shape, tensordict.device)
        tensordict.set(INSTRUCTION_KEY, texts)
        return tensordict


class DemoBuffer:
    """Episodes of one task in one control mode, persisted in a directory.

    Use :meth:`create` for a new directory, :meth:`open` for an existing one
    (with the values the caller expects, which are checked), and
    :meth:`open_or_create` to resume a collection.

    Examples (a buffer written by ``mmada-rl collect``; a sample is flat transitions, instruction text included):
        >>> buf = DemoBuffer.open("data/pickcube", task="PickCube-v1", control_mode="pd_ee_delta_pose")  # doctest: +SKIP
        >>> len(buf), buf.metadata.num_episodes  # doctest: +SKIP
        (7921, 100)
        >>> batch = buf.replay_buffer.sample(32)  # doctest: +SKIP
    """

    def __init__(self, path: Path, replay_buffer: TensorDictReplayBuffer, metadata: BufferMetadata):
        self.path = Path(path)
        self.replay_buffer = replay_buffer
        self.metadata = metadata
        self.instruction_lookup = InstructionLookup(metadata.instructions)
        replay_buffer.append_transform(self.instruction_lookup)

    # -- construction ---------------------------------------------------------
    @staticmethod
    def _make_rb(path: Path, capacity: int, metadata: BufferMetadata) -> TensorDictReplayBuffer:
        storage = LazyMemmapStorage(capacity, scratch_dir=path / "storage", existsok=True)
        return TensorDictReplayBuffer(storage=storage)

    @classmethod
    def create(cls, path: str | Path, metadata: BufferMetadata, capacity: int) -> DemoBuffer:
        """A new, empty buffer in ``path`` (which must not hold one already)."""
        path = Path(path)
        if (path / METADATA_FILE).exists():
            raise FileExistsError(f"{path} already holds a buffer; open it with DemoBuffer.open (or collect resumes it).")
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}.")
        path.mkdir(parents=True, exist_ok=True)
        metadata.capacity = int(capacity)
        metadata.save(path)
        return cls(path, cls._make_rb(path, capacity, metadata), metadata)

    @classmethod
    def open(
        cls,
        path: str | Path,
        *,
        task: str | None = None,
        control_mode: str | None = None,
        obs_mode: str | None = None,
        image_size: int | None = None,
        camera_fov: float | None | object = UNCHECKED,
    ) -> DemoBuffer:
        """Load the buffer in ``path``; each given expectation must match its metadata
        (``camera_fov``, whose ``None`` is the task's own camera, is checked unless left out).

        Raises:
            FileNotFoundError: ``path`` holds no buffer.
            BufferMismatchError: a given value differs from the buffer's, naming both.
        """
        path = Path(path)
        metadata = BufferMetadata.load(path)
        expected = {"task": task, "control_mode": control_mode, "obs_mode": obs_mode, "image_size": image_size}
        expected = {k: v for k, v in expected.items() if v is not None}
        if camera_fov is not UNCHECKED:
            expected["camera_fov"] = camera_fov
        for name, want in expected.items():
            have = getattr(metadata, name)
            if want != have:
                raise BufferMismatchError(
                    f"Buffer {path} was recorded with {name}={have!r} but {want!r} was asked for; "
                    f"collect a new buffer with that {name} or use {name}={have!r}."
                )
        rb = cls._make_rb(path, metadata.capacity, metadata)
        if metadata.num_transitions:
            rb.loads(path)
            if len(rb) != metadata.num_transitions:
                # killed between TorchRL's dumps and our metadata write: the storage is the truth
                metadata = cls._refresh(rb, metadata)
        return cls(path, rb, metadata)

    @classmethod
    def open_or_create(cls, path: str | Path, metadata: BufferMetadata, capacity: int) -> DemoBuffer:
        """Resume the buffer in ``path`` if there is one (checking it matches ``metadata``), else create it."""
        if (Path(path) / METADATA_FILE).exists():
            return cls.open(
                path,
                task=metadata.task,
                control_mode=metadata.control_mode,
                obs_mode=metadata.obs_mode,
                image_size=metadata.image_size,
                camera_fov=metadata.camera_fov,
            )
        return cls.create(path, metadata, capacity)

    # -- content --------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.replay_buffer)

    @property
    def storage(self):
        return self.replay_buffer.storage

    def transition_keys(self) -> tuple:
        image = IMAGE_KEYS if self.metadata.obs_mode == "rgb" else ()
        teacher = (TEACHER_CHUNK_KEY,) if self.metadata.teacher else ()
        return TRANSITION_KEYS + image + teacher

    def add_episode(self, episode: TensorDictBase, *, seed: int, instruction: str) -> int:
        """Append one finished episode (batch ``[T]``, TorchRL rollout layout) and commit it to disk.

        Returns:
            the episode id it was stored under.
        """
        if episode.ndim != 1 or episode.shape[0] == 0:
            raise ValueError(f"an episode is a non-empty 1-D tensordict, got batch size {tuple(episode.shape)}.")
        missing = [k for k in self.transition_keys() if k not in episode.keys(True, True)]
        if missing:
            raise KeyError(f"episode lacks {missing}; it must follow the TorchRL rollout layout of make_env.")
        if not isinstance(instruction, str):
            raise TypeError(f"instruction must be a string, got {type(instruction).__name__}.")
        if not torch.isfinite(episode.get(ACTION_KEY)).all():
            raise ValueError("episode has non-finite actions; refusing to store it.")
        T = episode.shape[0]
        if len(self) + T > self.metadata.capacity:
            raise RuntimeError(
                f"Buffer {self.path} is full ({len(self)}/{self.metadata.capacity} transitions, episode of {T}); "
                "collect into a new directory with more --episodes."
            )
        if instruction not in self.metadata.instructions:
            self.metadata.instructions.append(instruction)
            self.instruction_lookup.instructions = list(self.metadata.instructions)
        episode_id = self.metadata.num_episodes
        data = episode.select(*self.transition_keys()).clone()
        data.set(EPISODE_KEY, torch.full((T,), episode_id, dtype=torch.int64))
        data.set(INSTRUCTION_ID_KEY, torch.full((T,), self.metadata.instructions.index(instruction), dtype=torch.int64))
        data.set(SEED_KEY, torch.full((T,), int(seed), dtype=torch.int64))
        self.replay_buffer.extend(data)
        self.replay_buffer.dumps(self.path)
        self.metadata.seeds.append(int(seed))
        self.metadata = self._refresh(self.replay_buffer, self.metadata)
        self.metadata.save(self.path)
        return episode_id

    def save_metadata(self) -> None:
        self.metadata.save(self.path)

    @staticmethod
    def _refresh(rb: TensorDictReplayBuffer, metadata: BufferMetadata) -> BufferMetadata:
        """Recompute counts and action statistics from the committed storage."""
        n = len(rb)
        metadata.num_transitions = n
        if n == 0:
            metadata.num_episodes = 0
            return metadata
        stored = rb.storage[:n]
        metadata.num_episodes = int(stored.get(EPISODE_KEY).max()) + 1
        metadata.seeds = metadata.seeds[: metadata.num_episodes]
        actions = stored.get(ACTION_KEY).float().numpy()
        metadata.action_stats = {
            "mean": actions.mean(0).tolist(),
            "std": actions.std(0).tolist(),
            "min": actions.min(0).tolist(),
            "max": actions.max(0).tolist(),
            "p01": np.percentile(actions, 1, axis=0).tolist(),
            "p99": np.percentile(actions, 99, axis=0).tolist(),
        }
        return metadata

    def episode_bounds(self) -> list[tuple[int, int]]:
        """``(start, stop)`` storage indices of every episode, in order."""
        if len(self) == 0:
            return []
        ids = self.storage[: len(self)].get(EPISODE_KEY)
        change = torch.nonzero(ids[1:] != ids[:-1]).flatten() + 1
        starts = [0, *change.tolist()]
        stops = [*change.tolist(), len(self)]
        return list(zip(starts, stops))

    def episodes(self) -> Iterator[TensorDictBase]:
        """Every stored episode as a ``[T]`` tensordict (instruction text included)."""
        for start, stop in self.episode_bounds():
            ep = self.storage[start:stop]
            yield self.instruction_lookup(ep.clone() if isinstance(ep, TensorDict) else ep.to_tensordict())

    def summary(self) -> str:
        """A few human-readable lines about the buffer."""
        m = self.metadata
        bounds = self.episode_bounds()
        lengths = [b - a for a, b in bounds]
        lines = [
            f"buffer        {self.path}",
            f"task          {m.task}  ({m.instructions[0] if m.instructions else '-'!s})",
            f"control mode  {m.control_mode}   obs mode {m.obs_mode}   image {m.image_size}x{m.image_size}"
            + (f" (camera fov {m.camera_fov:g} deg)" if m.camera_fov is not None else ""),
            f"episodes      {m.num_episodes}   transitions {m.num_transitions} / capacity {m.capacity}",
        ]
        if lengths:
            lines.append(f"episode len   mean {np.mean(lengths):.1f}  min {min(lengths)}  max {max(lengths)}")
        if m.attempts:
            lines.append(f"source        {m.source}: {m.successes}/{m.attempts} attempts reached success "
                         f"({100 * m.source_success_rate:.1f}%)")
        if m.checkpoint:
            lines.append(f"policy        {' + '.join(m.checkpoint)}")
        if m.teacher:
            lines.append(f"teacher       {' + '.join(m.teacher['checkpoints'])}: its {m.teacher['chunk_size']}-action chunk "
                         f"for every step of {m.teacher['buffer']} (mean |error| {m.teacher['chunk_mae']:.4f} against "
                         "the demonstrated chunks)")
        for part in m.parts:
            lines.append(f"part          {part['episodes']} episodes of {part['path']} ({part['source']})")
        if m.action_stats:
            lo = ", ".join(f"{v:+.2f}" for v in m.action_stats["p01"])
            hi = ", ".join(f"{v:+.2f}" for v in m.action_stats["p99"])
            lines.append(f"action p01    [{lo}]")
            lines.append(f"action p99    [{hi}]")
        return "\n".join(lines)


#: What every part of a merged buffer must share (checked by :func:`merge_buffers`).
MERGE_CHECKED = ("task", "control_mode", "obs_mode", "image_size", "camera_fov", "action_dim", "state_dim", "reward")


def merge_buffers(out: str | Path, parts: list[str | Path]) -> DemoBuffer:
    """A new buffer in ``out`` holding every episode of ``parts``, in order, with their seeds and instructions.

    The parts must agree on :data:`MERGE_CHECKED` (one task, controller, observation and camera); what
    each part was (source, checkpoint, DART noise, episodes) is kept in the new buffer's ``metadata.parts``.
    E.g. the planner's demonstrations and a trained policy's rollouts (``mmada-rl collect --policy
    checkpoint``), for one pretraining run to read.

    Raises:
        ValueError: fewer than two parts, one given twice, or a part relabelled by a teacher (its labels would be lost).
        BufferMismatchError: a part differs from the first in a checked field (both values named).
        FileExistsError: ``out`` already holds a buffer.
    """
    paths = [Path(p) for p in parts]
    if len(paths) < 2:
        raise ValueError(f"merging needs two or more buffers, got {len(paths)}.")
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError(f"a buffer is given twice among {[str(p) for p in paths]}.")
    buffers = [DemoBuffer.open(p) for p in paths]
    first = buffers[0].metadata
    for buf in buffers[1:]:
        for name in MERGE_CHECKED:
            if getattr(buf.metadata, name) != getattr(first, name):
                raise BufferMismatchError(f"{buf.path} has {name}={getattr(buf.metadata, name)!r} but {paths[0]} has "
                                          f"{getattr(first, name)!r}; a merged buffer holds episodes of one setting.")
    relabelled = [str(b.path) for b in buffers if b.metadata.teacher]
    if relabelled:
        raise ValueError(f"{', '.join(relabelled)} hold a teacher's labels, which a merged buffer would drop; merge the "
                         "buffers they were relabelled from, then relabel the merged one.")
    sources = list(dict.fromkeys(b.metadata.source for b in buffers))
    meta = BufferMetadata(
        **{name: getattr(first, name) for name in MERGE_CHECKED},
        max_episode_steps=max((b.metadata.max_episode_steps or 0) for b in buffers) or None,
        source="+".join(sources),
        parts=[{"path": str(b.path), "source": b.metadata.source, "checkpoint": list(b.metadata.checkpoint),
                "episodes": b.metadata.num_episodes, "keep_after_success": b.metadata.keep_after_success,
                "action_noise": b.metadata.action_noise} for b in buffers],
        attempts=sum(b.metadata.attempts for b in buffers),
        successes=sum(b.metadata.successes for b in buffers),
        next_seed=max(b.metadata.next_seed for b in buffers),
    )
    merged = DemoBuffer.create(out, meta, capacity=sum(len(b) for b in buffers))
    for buf in buffers:
        for episode, seed in zip(buf.episodes(), buf.metadata.seeds):
            instruction = buf.metadata.instructions[int(episode.get(INSTRUCTION_ID_KEY)[0])]
            merged.add_episode(episode, seed=seed, instruction=instruction)
    return merged
