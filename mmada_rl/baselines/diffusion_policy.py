"""Diffusion Policy (Chi et al., RSS 2023) at CPU size: Gaussian DDPM over the flattened chunk.

The policy diffuses the normalised chunk flattened to ``[B, K * A]``,
conditioned on the shared encoder's features ``[B, F]``; inference runs DDIM
with ``num_denoise_steps`` steps (see :mod:`mmada_rl.baselines.ddpm`).

Training uses TorchRL's :class:`~torchrl.objectives.DiffusionBCLoss` (epsilon
prediction, MSE) unchanged, through :class:`ChunkDiffusionBCLoss`, a small
subclass that only prepares its two inputs: DiffusionBCLoss reads a flat
``observation`` vector and a flat clean ``action`` from the tensordict, while a
window batch holds an image, a state and a ``[B, K, A]`` chunk in env units. The
subclass encodes the observation (so the encoder trains end to end, as in
Diffusion Policy) and normalises and flattens the chunk, then calls the parent.

DiffusionBCLoss has no pad mask and none is applied: past an episode's end
the window's chunk repeats the last demonstrated action (TorchRL's
``ActionChunkTransform``), which is a valid target — the robot holding its last
command — and the same padding Diffusion Policy itself trains on.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import DiffusionBCLoss

from mmada_rl.baselines.base import ChunkPolicy, ChunkPolicyConfig
from mmada_rl.baselines.ddpm import ChunkDDPM, NoisePredictionMLP
from mmada_rl.baselines.normalization import NormalizationStats
from mmada_rl.keys import ACTION_CHUNK_KEY

__all__ = ["ChunkDiffusionBCLoss", "DiffusionPolicy", "DiffusionPolicyConfig"]

#: Inputs ChunkDiffusionBCLoss hands to DiffusionBCLoss (an internal tensordict, never stored).
FEATURES_KEY = ("diffusion", "features")  # encoder features, float [B, F]
FLAT_CHUNK_KEY = ("diffusion", "clean_chunk")  # normalised chunk, flattened, float [B, K * A]


@dataclass
class DiffusionPolicyConfig(ChunkPolicyConfig):
    """:class:`ChunkPolicyConfig` plus the DDPM.

    Attributes:
        num_train_steps: diffusion timesteps ``T`` of training (Diffusion Policy: 100).
        num_inference_steps: DDIM steps per chunk at inference, ``1 .. T``.
        hidden_size: width of the noise network's residual blocks.
        num_blocks: number of FiLM residual blocks.
        time_embed_dim: size of the timestep embedding.
    """

    num_train_steps: int = 100
    num_inference_steps: int = 10
    hidden_size: int = 256
    num_blocks: int = 3
    time_embed_dim: int = 64

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("num_train_steps", "num_inference_steps", "hidden_size", "num_blocks", "time_embed_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if self.num_train_steps < 2 or self.num_inference_steps > self.num_train_steps:
            raise ValueError(f"need 2 <= num_train_steps and num_inference_steps <= num_train_steps, got "
                             f"num_train_steps={self.num_train_steps}, num_inference_steps={self.num_inference_steps}.")


class DiffusionPolicy(ChunkPolicy):
    """Denoises a flattened chunk conditioned on encoder features.

    Inference is deterministic under ``ExplorationType.DETERMINISTIC`` (the
    default; ``x_T = 0``) and samples ``x_T ~ N(0, I)`` under ``RANDOM``.
    ``get_new_version(num_denoise_steps=n)`` runs ``n`` DDIM steps instead of
    ``config.num_inference_steps``.

    The DDPM sits at ``self.module``, the attribute DiffusionBCLoss reads (as on
    TorchRL's ``DiffusionActor``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = DiffusionPolicy(DiffusionPolicyConfig(chunk_size=5, state_dim=29))  # stats: identity maps
        >>> observation = TensorDict({("observation", "image"): torch.zeros(3, 64, 64, dtype=torch.uint8),
        ...                           ("observation", "state"): torch.zeros(29)})   # as one env's reset, batch []
        >>> policy(observation)["vla_action", "chunk"].shape
        torch.Size([5, 7])
        >>> policy.get_new_version(num_denoise_steps=4).num_denoise_steps
        4
    """

    kind = "diffusion_policy"
    config_class = DiffusionPolicyConfig

    def __init__(self, config: DiffusionPolicyConfig, stats: NormalizationStats | None = None, **kwargs) -> None:
        super().__init__(config, stats, **kwargs)
        flat = config.chunk_size * config.action_dim
        network = NoisePredictionMLP(flat, self.encoder.out_features, hidden_size=config.hidden_size,
                                     num_blocks=config.num_blocks, time_embed_dim=config.time_embed_dim)
        self.module = ChunkDDPM(network, action_dim=flat, num_steps=config.num_train_steps)
        self.num_denoise_steps = config.num_inference_steps

    def get_new_version(self, **kwargs) -> DiffusionPolicy:
        if "num_denoise_steps" in kwargs:
            self.module.inference_timesteps(kwargs["num_denoise_steps"])  # validates the range
        return super().get_new_version(**kwargs)

    def _predict_normalized(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        flat = self.module.sample(features, self.num_denoise_steps, greedy=self.is_greedy(), generator=generator)
        return flat.unflatten(-1, (self.chunk_size, self.action_dim))  # (B, K, A)


class ChunkDiffusionBCLoss(DiffusionBCLoss):
    """TorchRL's ``DiffusionBCLoss`` on window batches of a :class:`DiffusionPolicy`.

    Reads the policy's observation keys and ``("vla_action", "chunk")``, writes
    ``loss_diffusion_bc`` (the parent's epsilon-prediction MSE over all ``K * A``
    entries, padded steps included: see the module docstring).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = DiffusionPolicy(DiffusionPolicyConfig(chunk_size=5, state_dim=29))
        >>> loss = ChunkDiffusionBCLoss(policy)
        >>> batch = TensorDict({("observation", "image"): torch.zeros(4, 3, 64, 64, dtype=torch.uint8),
        ...                     ("observation", "state"): torch.zeros(4, 29),
        ...                     ("vla_action", "chunk"): torch.zeros(4, 5, 7)}, batch_size=[4])  # as a window batch
        >>> loss(batch)["loss_diffusion_bc"].backward()
    """

    @dataclass
    class _AcceptedKeys(DiffusionBCLoss._AcceptedKeys):
        """The parent's keys (here: the prepared inputs) plus the demonstrated chunk."""

        action: NestedKey = FLAT_CHUNK_KEY
        observation: NestedKey = FEATURES_KEY
        action_chunk: NestedKey = ACTION_CHUNK_KEY

    actor_network: DiffusionPolicy

    def __init__(self, actor_network: DiffusionPolicy, *, reduction: str = "mean") -> None:
        if not isinstance(actor_network, DiffusionPolicy):
            raise TypeError(f"ChunkDiffusionBCLoss trains a DiffusionPolicy, got {type(actor_network).__name__}.")
        super().__init__(actor_network, reduction=reduction)

    @property
    def in_keys(self):
        return [*self.actor_network.in_keys, self.tensor_keys.action_chunk]  # image, state, chunk

    @in_keys.setter
    def in_keys(self, value):
        pass  # derived from the policy's keys

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        policy = self.actor_network
        with self.actor_network_params.to_module(policy, preserve_module_state=False):
            features = policy.features(tensordict)  # (B, F), with gradients to the encoder
            clean = policy.normalizer.normalize(tensordict.get(self.tensor_keys.action_chunk)).flatten(-2)  # (B, K*A)
        inputs = TensorDict({self.tensor_keys.observation: features, self.tensor_keys.action: clean},
                            batch_size=[features.shape[0]], device=features.device)
        return super().forward(inputs)
