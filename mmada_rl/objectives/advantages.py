"""Chunk-level advantages for fine-tuning: group-relative or plain Monte-Carlo episode returns.

A decision is one executed chunk (a macro-action). Learned-value advantages use
TorchRL's :class:`~torchrl.objectives.value.GAE` directly on the chunk-level
transitions, with the discount ``gamma ** k`` of ``k`` executed steps (the
chunk's reward is already its discounted sum, :class:`~mmada_rl.policy.execution.ChunkReward`).
The critic-free alternative below compares rollouts that started from the same
initial state, as TorchRL's ``vla_grpo`` recipe (SimpleVLA-RL) does; or, with
no baseline at all, takes each episode's return as the advantage of its decisions
(with a sparse success reward and binary weights: imitate the successful rollouts).
"""
from __future__ import annotations

import torch

__all__ = ["group_relative_advantages"]


def group_relative_advantages(returns: torch.Tensor, groups: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Standardise episode returns within groups of rollouts from one initial state.

    Args:
        returns: float ``[E]``, one return per episode.
        groups: int ``[E]``, the group of each episode (e.g. its reset seed).
        eps: added to the standard deviation; a group whose returns are all equal
            gets advantage 0 everywhere (nothing to learn from it).

    Returns:
        float ``[E]``: ``(R - mean_g) / (std_g + eps)`` with the population std of the group.

    Examples:
        >>> group_relative_advantages(torch.tensor([1., 0., 1., 1.]), torch.tensor([7, 7, 8, 8]))
        tensor([ 1.0000, -1.0000,  0.0000,  0.0000])
    """
    if returns.shape != groups.shape or returns.ndim != 1:
        raise ValueError(f"returns and groups must be 1-d of one shape, got {tuple(returns.shape)} and {tuple(groups.shape)}.")
    _, index = torch.unique(groups, return_inverse=True)
    n = int(index.max()) + 1 if index.numel() else 0
    returns = returns.float()
    count = torch.zeros(n).index_add(0, index, torch.ones_like(returns))
    mean = torch.zeros(n).index_add(0, index, returns) / count
    var = torch.zeros(n).index_add(0, index, (returns - mean[index]) ** 2) / count
    std = var.sqrt()
    adv = (returns - mean[index]) / (std[index] + eps)
    return torch.where(std[index] > 0, adv, torch.zeros_like(adv))
