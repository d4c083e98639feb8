"""Chunk-level value function of the fine-tuning recipes: ``V(o_t)`` from the image and the proprio state.

A separate small network (the baselines' :class:`~mmada_rl.baselines.encoders.ObservationEncoder`
and an MLP head), so that fitting values never moves the policy's denoiser.
Wrapped as TorchRL's :class:`~torchrl.modules.ValueOperator`, it plugs into
:class:`~torchrl.objectives.value.GAE`.
"""
from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import ValueOperator

from mmada_rl.baselines.encoders import EncoderConfig, ObservationEncoder
from mmada_rl.keys import IMAGE_KEY, STATE_KEY

__all__ = ["ValueNetwork", "make_value_operator"]


class ValueNetwork(nn.Module):
    """``V(image, state) -> [B, 1]``.

    Args:
        encoder: sizes of the observation encoder.
        image_size: side of the square image.
        state_dim: size of the proprio state.
        hidden: width of the MLP head.
        state_mean, state_std: state moments (e.g. of the demonstrations).
    """

    def __init__(self, encoder: EncoderConfig, *, image_size: int, state_dim: int, hidden: int = 256,
                 state_mean: torch.Tensor | None = None, state_std: torch.Tensor | None = None) -> None:
        super().__init__()
        self.encoder = ObservationEncoder(encoder, image_size=image_size, state_dim=state_dim,
                                          state_mean=state_mean, state_std=state_std)
        self.head = nn.Sequential(nn.Linear(self.encoder.out_features, hidden), nn.Mish(), nn.Linear(hidden, 1))

    def forward(self, image: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        batch = image.shape[:-3]
        out = self.head(self.encoder(image.reshape(-1, *image.shape[-3:]), state.reshape(-1, state.shape[-1])))
        return out.reshape(*batch, 1)


def make_value_operator(network: ValueNetwork) -> ValueOperator:
    """The network as a TorchRL ``ValueOperator`` reading the canonical observation keys, writing ``"state_value"``."""
    return ValueOperator(network, in_keys=[IMAGE_KEY, STATE_KEY])
