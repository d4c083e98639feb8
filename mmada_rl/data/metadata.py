"""The self-description written beside every buffer (``metadata.json``)."""
from __future__ import annotations

import json
import os
import platform
import tempfile
from dataclasses import asdict, dataclass, field, fields
from importlib import metadata as importlib_metadata
from pathlib import Path

METADATA_FILE = "metadata.json"
_FORMAT_VERSION = 1


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape the stored data."""
    out = {"python": platform.python_version()}
    for name in ("mmada_rl", "torch", "torchrl", "tensordict", "mani_skill", "sapien", "numpy", "mplib"):
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def write_json_atomic(path: Path, payload: dict) -> None:
    """Write JSON through a temporary file and a rename, so readers never see half a file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(payload, f, indent=2, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


@dataclass
class BufferMetadata:
    """What a buffer holds and how it was made.

    Counts (episodes, transitions) and action statistics describe the episodes
    committed to storage; they are refreshed after every episode.

    Attributes:
        task: ManiSkill task id.
        control_mode: controller the actions are expressed in.
        obs_mode: ``"rgb"`` or ``"state"``.
        image_size: camera side in pixels (0 for state-only buffers).
        camera_fov: the camera's field of view in degrees (``None``: the task's own; see
            :class:`~mmada_rl.envs.EnvConfig`).
        action_dim, state_dim: sizes of one action / state vector.
        reward: ``"dense"`` or ``"sparse"``.
        max_episode_steps: episode length limit used while recording.
        source: ``"planner"``, ``"random"``, ``"scripted"``, ``"policy"``, ``"checkpoint"``, ``"h5"``,
            or the parts' sources joined by ``"+"`` for a merged buffer.
        checkpoint: the policy directories a ``"checkpoint"`` source recorded (several: their ensemble).
        parts: for a merged buffer (:func:`~mmada_rl.data.merge_buffers`), what each part was: its
            path, source, checkpoint, episodes, ``keep_after_success`` and ``action_noise``.
        keep_after_success: planner episodes run past their first success to the
            end of the planner's path (else they end at the first success).
        action_noise: std of the noise planner episodes were executed with (DART; 0: none).
        teacher: for a buffer relabelled by :func:`~mmada_rl.data.relabel_buffer`, the policy whose chunks it
            stores under :data:`~mmada_rl.keys.TEACHER_CHUNK_KEY` (its ``checkpoints``, ``chunk_size``, how it
            decoded, the buffer it relabelled and the chunks' error against the demonstrated ones); empty otherwise.
        capacity: number of transitions the storage was allocated for.
        instructions: instruction strings; transitions store an index into this list.
        num_episodes, num_transitions: committed content.
        attempts, successes: episodes tried / kept by the source (planner success rate).
        next_seed: the seed the next collected episode starts from (resume point).
        seeds: env seed of every committed episode, in episode order.
        action_stats: per-dimension ``mean``, ``std``, ``min``, ``max``, ``p01``, ``p99``.
        versions: package versions at creation.
    """

    task: str
    control_mode: str
    obs_mode: str
    image_size: int
    action_dim: int
    state_dim: int
    reward: str = "dense"
    camera_fov: float | None = None
    max_episode_steps: int | None = None
    source: str = "planner"
    keep_after_success: bool = False
    action_noise: float = 0.0
    checkpoint: list[str] = field(default_factory=list)
    parts: list[dict] = field(default_factory=list)
    teacher: dict = field(default_factory=dict)
    capacity: int = 0
    instructions: list[str] = field(default_factory=list)
    num_episodes: int = 0
    num_transitions: int = 0
    attempts: int = 0
    successes: int = 0
    next_seed: int = 0
    seeds: list[int] = field(default_factory=list)
    action_stats: dict[str, list[float]] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=package_versions)
    format_version: int = _FORMAT_VERSION

    @property
    def source_success_rate(self) -> float:
        return self.successes / self.attempts if self.attempts else float("nan")

    def save(self, directory: str | Path) -> None:
        write_json_atomic(Path(directory) / METADATA_FILE, asdict(self))

    @classmethod
    def load(cls, directory: str | Path) -> BufferMetadata:
        path = Path(directory) / METADATA_FILE
        if not path.exists():
            raise FileNotFoundError(
                f"{directory} is not an mmada_rl buffer: {METADATA_FILE} is missing "
                "(create one with `mmada-rl collect --out DIR`)."
            )
        payload = json.loads(path.read_text())
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in payload.items() if k in known})
