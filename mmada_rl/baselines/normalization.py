"""Normalisation of the baselines' inputs and targets, fitted on a demonstration buffer.

Actions are mapped per dimension from the ``[min, max]`` seen in the
demonstrations to ``[-1, 1]`` (Diffusion Policy's convention: the sampler clips
its clean-chunk estimate to that box, so every sampled action lies in the range
the demonstrations cover). States are standardised with their mean and standard
deviation. Both live in buffers, so they are saved with the weights.

We do not reuse :class:`mmada_rl.tokenizers.ActionNormalizer`: it clips to
quantiles and warns about every clipped value (a tokenizer's concern), whereas
these policies need an exact, differentiable affine map over the whole range.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from mmada_rl.keys import STATE_KEY

__all__ = ["ChunkNormalizer", "NormalizationStats", "StateStandardizer"]

#: Smallest action half-range: a constant dimension (e.g. PushCube's closed gripper) maps to 0 and back.
_EPS = 1e-6
#: Smallest state standard deviation: a state entry constant in the demonstrations must not blow up
#: when it moves a little at evaluation.
_STATE_STD_MIN = 1e-2


class NormalizationStats(NamedTuple):
    """Per-dimension statistics of a demonstration buffer."""

    action_min: torch.Tensor  # (A,)
    action_max: torch.Tensor  # (A,)
    state_mean: torch.Tensor  # (S,)
    state_std: torch.Tensor  # (S,)

    @classmethod
    def from_buffer(cls, buffer) -> NormalizationStats:
        """Action range from the buffer's metadata, state moments from its stored transitions."""
        stats = buffer.metadata.action_stats
        if not stats:
            raise ValueError(f"buffer {buffer.path} holds no action statistics (is it empty?).")
        states = buffer.storage[: len(buffer)].get(STATE_KEY).float()  # (N, S)
        return cls(
            torch.tensor(stats["min"], dtype=torch.float32),
            torch.tensor(stats["max"], dtype=torch.float32),
            states.mean(0),
            states.std(0),
        )


class ChunkNormalizer(nn.Module):
    """Affine map of actions ``[min, max] -> [-1, 1]`` per dimension (and back).

    Args:
        action_dim: ``A``.
        low, high: per-dimension range (defaults: ``-1`` and ``1``, the identity).

    Examples:
        >>> norm = ChunkNormalizer(2, low=torch.tensor([0.0, -2.0]), high=torch.tensor([1.0, 2.0]))
        >>> norm.normalize(torch.tensor([[1.0, -2.0]]))
        tensor([[ 1., -1.]])
        >>> norm.denormalize(torch.zeros(1, 2))
        tensor([[0.5000, 0.0000]])
    """

    def __init__(self, action_dim: int, low: torch.Tensor | None = None, high: torch.Tensor | None = None) -> None:
        super().__init__()
        low = -torch.ones(action_dim) if low is None else torch.as_tensor(low, dtype=torch.float32)
        high = torch.ones(action_dim) if high is None else torch.as_tensor(high, dtype=torch.float32)
        if low.shape != (action_dim,) or high.shape != (action_dim,):
            raise ValueError(f"low and high must have shape ({action_dim},), got {tuple(low.shape)} and {tuple(high.shape)}.")
        if (high < low).any():
            raise ValueError(f"need low <= high in every dimension, got low={low.tolist()}, high={high.tolist()}.")
        self.register_buffer("center", (high + low) / 2)
        self.register_buffer("half_range", ((high - low) / 2).clamp_min(_EPS))

    def normalize(self, actions: torch.Tensor) -> torch.Tensor:
        """``[..., A]`` env units -> normalised."""
        return (actions - self.center) / self.half_range

    def denormalize(self, actions: torch.Tensor) -> torch.Tensor:
        """``[..., A]`` normalised -> env units."""
        return actions * self.half_range + self.center


class StateStandardizer(nn.Module):
    """``(state - mean) / std`` per dimension.

    Args:
        state_dim: ``S``.
        mean, std: per-dimension moments (defaults: 0 and 1, the identity).
    """

    def __init__(self, state_dim: int, mean: torch.Tensor | None = None, std: torch.Tensor | None = None) -> None:
        super().__init__()
        mean = torch.zeros(state_dim) if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        std = torch.ones(state_dim) if std is None else torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (state_dim,) or std.shape != (state_dim,):
            raise ValueError(f"mean and std must have shape ({state_dim},), got {tuple(mean.shape)} and {tuple(std.shape)}.")
        self.register_buffer("mean", mean.clone())
        self.register_buffer("std", std.clamp_min(_STATE_STD_MIN).clone())

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return (state - self.mean) / self.std
