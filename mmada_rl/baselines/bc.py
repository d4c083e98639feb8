"""Chunked behaviour cloning: encoder features -> MLP -> the whole ``K x A`` chunk in one pass.

Trained with TorchRL's :class:`~torchrl.objectives.BCLoss` as it is: the policy
writes its prediction at ``("vla_action", "chunk")``, the key of the demonstrated
chunk, and ``pad_mask="action_is_pad"`` drops the padded steps of windows that
run past an episode's end (a ``[B, K]`` mask broadcast over ``A``; the mean is
over the unpadded elements). BCLoss compares in whatever space its
``loss_function`` chooses; :class:`NormalizedChunkError` measures the error in
the policy's normalised action space, so that the 7 action dimensions (ranges
from ~0.1 to 2) weigh alike.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn
from torchrl.objectives import BCLoss

from mmada_rl.baselines.base import ChunkPolicy, ChunkPolicyConfig
from mmada_rl.baselines.normalization import ChunkNormalizer, NormalizationStats
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_IS_PAD_KEY

__all__ = ["BCConfig", "BCPolicy", "NormalizedChunkError", "make_bc_loss"]

_ERRORS = {"l1": F.l1_loss, "mse": F.mse_loss, "smooth_l1": F.smooth_l1_loss}


@dataclass
class BCConfig(ChunkPolicyConfig):
    """:class:`ChunkPolicyConfig` plus the MLP head.

    Attributes:
        hidden_sizes: widths of the head's hidden layers.
    """

    hidden_sizes: tuple[int, ...] = (256, 256)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        if any(h < 1 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive widths, got {list(self.hidden_sizes)!r}.")


class BCPolicy(ChunkPolicy):
    """Deterministic chunk regressor: features ``[B, F]`` -> MLP -> ``[B, K, A]``.

    Args / keyword args: as :class:`~mmada_rl.baselines.base.ChunkPolicy`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = BCPolicy(BCConfig(chunk_size=5, action_dim=7, state_dim=29), execute_steps=2)
        >>> observation = TensorDict({("observation", "image"): torch.zeros(3, 64, 64, dtype=torch.uint8),
        ...                           ("observation", "state"): torch.zeros(29)})   # as one env's reset, batch []
        >>> td = policy(observation)
        >>> td["vla_action", "chunk"].shape, td["action"].shape
        (torch.Size([5, 7]), torch.Size([2, 7]))
    """

    kind = "bc"
    config_class = BCConfig

    def __init__(self, config: BCConfig, stats: NormalizationStats | None = None, **kwargs) -> None:
        super().__init__(config, stats, **kwargs)
        layers, width = [], self.encoder.out_features
        for hidden in config.hidden_sizes:
            layers += [nn.Linear(width, hidden), nn.Mish()]
            width = hidden
        self.head = nn.Sequential(*layers, nn.Linear(width, config.chunk_size * config.action_dim))

    def _predict_normalized(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        return self.head(features).unflatten(-1, (self.chunk_size, self.action_dim))  # (B, K, A)

    def get_new_version(self, **kwargs) -> BCPolicy:
        if kwargs.get("num_denoise_steps", 1) != 1:
            raise ValueError(f"a BC policy predicts its chunk in one forward pass; num_denoise_steps="
                             f"{kwargs['num_denoise_steps']!r} does not apply to it (leave it unset).")
        return super().get_new_version(**kwargs)


class NormalizedChunkError:
    """``BCLoss`` ``loss_function``: elementwise error of two chunks in normalised action units.

    Args:
        normalizer: the policy's :class:`~mmada_rl.baselines.normalization.ChunkNormalizer`.
        kind: ``"l1"`` | ``"mse"`` | ``"smooth_l1"``.
    """

    def __init__(self, normalizer: ChunkNormalizer, kind: Literal["l1", "mse", "smooth_l1"] = "l1") -> None:
        if kind not in _ERRORS:
            raise ValueError(f"loss_function must be one of {sorted(_ERRORS)}, got {kind!r}.")
        self.normalizer, self.kind = normalizer, kind

    def __call__(self, prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        norm = self.normalizer.normalize
        return _ERRORS[self.kind](norm(prediction), norm(target), reduction="none")  # (B, K, A)


def make_bc_loss(policy: BCPolicy, loss_function: Literal["l1", "mse", "smooth_l1"] = "l1") -> BCLoss:
    """TorchRL's ``BCLoss`` scoring chunks at ``("vla_action", "chunk")`` with the ``action_is_pad`` mask.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> loss = make_bc_loss(BCPolicy(BCConfig(chunk_size=5, action_dim=7, state_dim=29)))
        >>> batch = TensorDict({("observation", "image"): torch.zeros(4, 3, 64, 64, dtype=torch.uint8),
        ...                     ("observation", "state"): torch.zeros(4, 29),
        ...                     ("vla_action", "chunk"): torch.zeros(4, 5, 7)}, batch_size=[4])  # as a window batch
        >>> loss(batch)["loss_bc"].backward()
    """
    with warnings.catch_warnings():
        # TorchRL 0.14.1's BCLoss lacks a target-params annotation and warns about it on every construction
        warnings.filterwarnings("ignore", message="The name target_actor_network_params", category=UserWarning)
        loss = BCLoss(policy, loss_function=NormalizedChunkError(policy.normalizer, loss_function))
    loss.set_keys(action=ACTION_CHUNK_KEY, pad_mask=ACTION_IS_PAD_KEY)
    return loss
