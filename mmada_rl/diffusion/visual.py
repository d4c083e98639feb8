"""Convolutional image features for the denoiser's cross-attention.

The image tokens of the sequence summarise each 8x8-pixel patch by one VQ code,
fitted to reconstruct pixels; a few-pixel cube can vanish from them (see the
README's PushCube and PickCube analyses). :class:`ConvPatchEncoder` gives the
denoiser a second, continuous view of the same observation: a small strided
CNN, trained end to end with the denoiser, whose last feature map becomes
``N = (H / 2**n) * (W / 2**n)`` feature vectors, each with a fixed 2-D sin-cos
code of its cell, for the cross-attention sublayers to read.

:func:`conv_stack` is the CNN body it shares with the baselines' observation encoder.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["ConvPatchEncoder", "conv_stack", "sincos_2d"]


def conv_stack(channels: Sequence[int], norm_groups: int = 8) -> nn.Sequential:
    """Stride-2 3x3 convolutions with GroupNorm and Mish: ``[B, 3, H, W] -> [B, C_n, H / 2**n, W / 2**n]``.

    GroupNorm instead of BatchNorm (as Diffusion Policy does), so the module
    behaves the same in train and eval mode and with any batch size.
    """
    layers, width = [], 3
    for out in channels:
        layers += [nn.Conv2d(width, out, 3, stride=2, padding=1), nn.GroupNorm(math.gcd(out, norm_groups), out), nn.Mish()]
        width = out
    return nn.Sequential(*layers)


def sincos_2d(height: int, width: int, dim: int, device=None) -> torch.Tensor:
    """Fixed 2-D sin-cos position codes ``[height * width, dim]`` (``dim`` a multiple of 4), row-major cells."""
    if dim % 4:
        raise ValueError(f"dim must be a multiple of 4 for 2-D sin-cos codes, got {dim}.")
    quarter = dim // 4
    freqs = 1.0 / (10000 ** (torch.arange(quarter, device=device, dtype=torch.float32) / quarter))  # (D/4,)
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                            torch.arange(width, device=device, dtype=torch.float32), indexing="ij")
    angles_y = ys.flatten()[:, None] * freqs  # (H*W, D/4)
    angles_x = xs.flatten()[:, None] * freqs
    return torch.cat([angles_y.sin(), angles_y.cos(), angles_x.sin(), angles_x.cos()], -1)  # (H*W, D)


class ConvPatchEncoder(nn.Module):
    """uint8 images ``[B, 3, H, W]`` -> cell features ``[B, (H / 2**n) * (W / 2**n), channels[-1]]``.

    Args:
        channels: output widths of the stride-2 convolutions (``n = len(channels)``).
        norm_groups: GroupNorm groups (the largest divisor of each width up to this).

    Examples:
        >>> enc = ConvPatchEncoder((16, 32, 64))
        >>> enc(torch.zeros(2, 3, 64, 64, dtype=torch.uint8)).shape
        torch.Size([2, 64, 64])
    """

    def __init__(self, channels: Sequence[int] = (32, 64, 128), norm_groups: int = 8) -> None:
        super().__init__()
        self.channels = tuple(int(c) for c in channels)
        if not self.channels or min(self.channels) < 1:
            raise ValueError(f"channels must be a non-empty list of positive widths, got {list(self.channels)!r}.")
        if self.channels[-1] % 4:
            raise ValueError(f"the last width must be a multiple of 4 (2-D position codes), got {self.channels[-1]}.")
        self.cnn = conv_stack(self.channels, norm_groups)

    @property
    def out_features(self) -> int:
        return self.channels[-1]

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"images: expected [B, 3, H, W], got {list(image.shape)}.")
        stride = 2 ** len(self.channels)
        if image.shape[-1] % stride or image.shape[-2] % stride:
            raise ValueError(f"image side {tuple(image.shape[-2:])} is not a multiple of 2**len(channels)={stride}.")
        pixels = image.float() / 127.5 - 1.0  # (B, 3, H, W) in [-1, 1]
        features = self.cnn(pixels)  # (B, C, h, w)
        _, channels, h, w = features.shape
        cells = features.flatten(2).transpose(1, 2)  # (B, h*w, C)
        return cells + sincos_2d(h, w, channels, device=cells.device)
