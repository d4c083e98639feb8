"""What the imitation baselines share: config, observation encoding, the actor contract, saving.

A :class:`ChunkPolicy` is a TorchRL :class:`~torchrl.modules.vla.VLAWrapperBase`
with the ``"continuous"`` action head, and it honours the contract of
:class:`~mmada_rl.policy.actor.MMaDAActor`, so :func:`~mmada_rl.policy.make_policy_env`
and :func:`~mmada_rl.evaluation.evaluate` run it unchanged. It reads::

    ("observation", "image")   uint8 [*B, 3, H, W]
    ("observation", "state")   float [*B, S]

and writes::

    ("vla_action", "chunk")    float [*B, K, A]   the predicted chunk, env units
    "action"                   float [*B, k, A]   its first ``execute_steps`` actions

(no instruction: the baselines are single-task policies). With ``obs_mode="state"``
the policy reads ManiSkill's privileged state vector at ``("observation", "state")``
and no image: a reference that shows what the demonstrations teach with perfect
perception, labelled as such wherever it is reported. Subclasses map encoder
features ``[B, F]`` to a chunk in the normalised action space ``[B, K, A]``
(:meth:`ChunkPolicy._predict_normalized`); this class encodes, denormalises,
reshapes to the input's batch and times the call.

A policy saves to one directory, ``policy.json`` (its kind and config) +
``policy.safetensors`` (weights and normalisation statistics), and
:func:`mmada_rl.baselines.load_policy` rebuilds it from there.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

import torch
from safetensors.torch import load_file, save_file
from tensordict import TensorDict, TensorDictBase
from torchrl.modules.vla import VLAWrapperBase

from mmada_rl.baselines.encoders import EncoderConfig, ObservationEncoder
from mmada_rl.baselines.normalization import ChunkNormalizer, NormalizationStats
from mmada_rl.envs.maniskill import OBS_MODES
from mmada_rl.policy.actor import ChunkExecutionMixin, check_execute_steps

__all__ = ["POLICY_CONFIG", "POLICY_WEIGHTS", "ChunkPolicy", "ChunkPolicyConfig"]

#: The file that marks a directory as a saved baseline policy (kind + config).
POLICY_CONFIG = "policy.json"
POLICY_WEIGHTS = "policy.safetensors"


@dataclass
class ChunkPolicyConfig:
    """Shapes and encoder of a chunk policy; subclasses add their head's fields.

    Attributes:
        chunk_size: actions per chunk ``K``.
        action_dim: ``A`` (7 for ``pd_ee_delta_pose``).
        state_dim: ``S``, the proprioceptive state size of the task.
        image_size: side of the square RGB observation (unused with ``obs_mode="state"``).
        encoder: :class:`~mmada_rl.baselines.encoders.EncoderConfig` (or its dict).
        obs_mode: ``"rgb"`` (image + proprio, default) or ``"state"`` (the privileged
            state vector alone: ``state_dim`` is its size).
        camera_fov: field of view (degrees) of the training images' camera; ``None``: the
            task's own. Evaluation builds its env with it.
    """

    chunk_size: int = 5
    action_dim: int = 7
    state_dim: int = 29
    image_size: int = 64
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    obs_mode: str = "rgb"
    camera_fov: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.encoder, dict):
            self.encoder = EncoderConfig(**self.encoder)
        if self.obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {self.obs_mode!r}.")
        for name in ("chunk_size", "action_dim", "state_dim", "image_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")

    def to_dict(self) -> dict:
        return asdict(self)


class ChunkPolicy(ChunkExecutionMixin, VLAWrapperBase):
    """Base actor of the baselines (see the module docstring for its keys).

    Args:
        config: the policy's config.
        stats: action range and state moments of the training data (``None``:
            identity; a loaded policy gets them from its weights).

    Keyword Args:
        execute_steps: ``k``, actions written to ``"action"``; ``None``: the whole chunk.
        generator: RNG of sampled (``ExplorationType.RANDOM``) inference.
        **kwargs: other :class:`~torchrl.modules.vla.VLAWrapperBase` keywords (key names, ``inplace``...).

    Attributes:
        last_decode_seconds: wall time of the last chunk prediction.
        num_denoise_steps: network evaluations per chunk (1 for a one-shot head).
    """

    #: the name saved in ``policy.json`` (and the recipe's ``algo``)
    kind: ClassVar[str] = ""
    config_class: ClassVar[type[ChunkPolicyConfig]] = ChunkPolicyConfig

    def __init__(self, config: ChunkPolicyConfig, stats: NormalizationStats | None = None, *,
                 execute_steps: int | None = None, generator: torch.Generator | None = None, **kwargs) -> None:
        for name in ("action_head", "output_mode", "action_dim", "chunk_size", "use_state", "vocab_size"):
            if name in kwargs:
                raise ValueError(f"{name} is fixed by the policy config; do not pass {name}={kwargs[name]!r}.")
        super().__init__(None, action_head="continuous", output_mode="chunk", action_dim=config.action_dim,
                         chunk_size=config.chunk_size, use_state=True,
                         return_vla_action_container=kwargs.pop("return_vla_action_container", False), **kwargs)
        self.config = config
        self._update_keys()  # again, now that the observation mode is known
        self._build_encoding(config, stats)
        self.execute_steps = check_execute_steps(execute_steps, self.chunk_size)
        self.generator = generator
        self.num_denoise_steps = 1
        self.last_decode_seconds = float("nan")

    @property
    def image_size(self) -> int | None:
        """Side of the images the policy reads (``None``: a state policy reads none)."""
        return self.config.image_size if self.config.obs_mode == "rgb" else None

    @property
    def camera_fov(self) -> float | None:
        """Field of view (degrees) of the camera it reads (``None``: the task's own, or a state policy)."""
        return self.config.camera_fov if self.config.obs_mode == "rgb" else None

    @property
    def obs_mode(self) -> str:
        """``"rgb"`` or ``"state"``: the observation mode of the env it runs in."""
        return self.config.obs_mode

    def _build_encoding(self, config: ChunkPolicyConfig, stats: NormalizationStats | None) -> None:
        """The observation encoder and the chunk normaliser (no stats: identity maps, to be
        overwritten by ``load_state_dict``, as for a loaded policy)."""
        low, high, mean, std = stats if stats is not None else (None, None, None, None)
        self.encoder = ObservationEncoder(config.encoder, image_size=self.image_size, state_dim=config.state_dim,
                                          state_mean=mean, state_std=std)
        self.normalizer = ChunkNormalizer(config.action_dim, low, high)

    # -- keys -------------------------------------------------------------------
    def _update_keys(self) -> None:
        super()._update_keys()
        keys = self._tensor_keys
        state_only = getattr(self, "config", None) is not None and self.config.obs_mode == "state"
        drop = {keys.instruction} | ({keys.image} if state_only else set())
        self.in_keys = [key for key in self.in_keys if key not in drop]  # single-task: no language
        self.out_keys = [*self.out_keys, keys.action]

    # -- inference --------------------------------------------------------------
    def features(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Encoder features ``[B, F]`` of the observations of ``tensordict`` (batch ``[*B]`` flattened)."""
        state, device = self._get_state(tensordict), self.normalizer.center.device
        image = None
        if self.config.obs_mode == "rgb":
            image = self._get_image(tensordict)
            image = image.reshape(-1, *image.shape[-3:]).to(device)
        return self.encoder(image, state.reshape(-1, state.shape[-1]).to(device))

    def _predict_normalized(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """Features ``[B, F]`` -> normalised chunk ``[B, K, A]``; what each baseline implements."""
        raise NotImplementedError

    def predict_chunk(self, tensordict: TensorDictBase, generator: torch.Generator | None = None) -> torch.Tensor:
        """The chunk ``[B, K, A]`` in env units for the observations of ``tensordict`` (batch flattened)."""
        return self.normalizer.denormalize(self._predict_normalized(self.features(tensordict), generator))

    def forward(self, tensordict: TensorDictBase, *, tensordict_out: TensorDictBase | None = None,
                generator: torch.Generator | None = None, **kwargs) -> TensorDictBase:
        """Predict one chunk per observation of ``tensordict`` (batch ``[*B]``)."""
        batch = tensordict.batch_size
        start = time.perf_counter()
        chunk = self.predict_chunk(tensordict, generator or self.generator)  # (B, K, A)
        self.last_decode_seconds = time.perf_counter() - start
        home = tensordict.device or self._get_state(tensordict).device  # where the env reads the action
        chunk = chunk.reshape(*batch, self.chunk_size, self.action_dim).to(home)  # (*B, K, A)
        out = TensorDict({}, batch_size=batch, device=tensordict.device)
        self._set_action(out, chunk=chunk)
        out.set(self._tensor_keys.action, chunk[..., : self.execute_steps, :])  # (*B, k, A)
        return self._output_tensordict(tensordict, out, tensordict_out)

    # -- persistence ------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write ``policy.json`` and ``policy.safetensors`` into ``directory`` (each atomically)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        payload = {"kind": self.kind, "config": self.config.to_dict(),
                   "num_parameters": sum(p.numel() for p in self.parameters())}
        tmp = directory / f".{POLICY_WEIGHTS}.tmp"
        save_file({k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}, str(tmp))
        tmp.replace(directory / POLICY_WEIGHTS)
        tmp = directory / f".{POLICY_CONFIG}.tmp"
        tmp.write_text(json.dumps(payload, indent=2))
        tmp.replace(directory / POLICY_CONFIG)
        return directory

    @classmethod
    def from_payload(cls, payload: dict, directory: Path, *, device: str | torch.device = "cpu") -> ChunkPolicy:
        """Rebuild the policy from ``policy.json``'s content and the weights beside it."""
        policy = cls(cls.config_class(**payload["config"]))
        policy.load_state_dict(load_file(str(directory / POLICY_WEIGHTS)))
        return policy.to(device)
