"""Convolutional image features for the denoiser's cross-attention.

The image tokens of the sequence summarise each 8x8-pixel patch by one VQ code,
fitted to reconstruct pixels; a few-pixel cube can vanish from them (see the
PushCube and PickCube analyses in docs/results/pretraining.md). :class:`ConvPatchEncoder` gives the
denoiser a second, continuous view of the same observation: a small strided
CNN, trained end to end with the denoiser, whose last feature map becomes
``N = (H / 2**n) * (W / 2**n)`` feature vectors, each with a fixed 2-D sin-cos
code of its cell, for the cross-attention sublayers to read; or, with
``keypoints=K``, ``K`` tokens, each the embedded expected image position of one
learned keypoint map (:class:`SpatialSoftmax`, the pooling of the BC baseline's
encoder): a narrow view of the image, positions only, where the cells let the
denoiser read (and memorise) every texture of the scene.

:func:`conv_stack` and :class:`SpatialSoftmax` are shared with the baselines' observation encoder.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["ConvPatchEncoder", "SpatialSoftmax", "conv_stack", "sincos_2d"]


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


class SpatialSoftmax(nn.Module):
    """``[B, C, H, W]`` -> ``[B, 2 * num_keypoints]``: per keypoint map, the softmax-weighted mean (x, y) in ``[-1, 1]``.

    Args:
        in_channels: ``C``.
        num_keypoints: keypoint maps (a 1x1 convolution of the input).

    Examples:
        >>> pool = SpatialSoftmax(8, num_keypoints=4)
        >>> pool(torch.zeros(2, 8, 6, 6)).shape
        torch.Size([2, 8])
    """

    def __init__(self, in_channels: int, num_keypoints: int) -> None:
        super().__init__()
        self.keypoints = nn.Conv2d(in_channels, num_keypoints, 1)

    @staticmethod
    def grid(height: int, width: int, device=None) -> torch.Tensor:
        """The (x, y) of every cell, row-major, in ``[-1, 1]``: ``[H * W, 2]``."""
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height, device=device),
                                torch.linspace(-1, 1, width, device=device), indexing="ij")
        return torch.stack([xs.flatten(), ys.flatten()], -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        attention = self.keypoints(x).flatten(2).softmax(-1)  # (B, N, H*W)
        return (attention @ self.grid(*x.shape[-2:], device=x.device)).flatten(1)  # (B, 2N)


class ConvPatchEncoder(nn.Module):
    """uint8 images ``[B, 3, H, W]`` -> cell features ``[B, (H / 2**n) * (W / 2**n), channels[-1]]``.

    Args:
        channels: output widths of the stride-2 convolutions (``n = len(channels)``).
        norm_groups: GroupNorm groups (the largest divisor of each width up to this).
        keypoints: ``K > 0``: return ``K`` keypoint tokens ``[B, K, channels[-1]]`` (each keypoint's
            expected (x, y) through a linear map, plus the keypoint's own learned embedding) instead
            of the cells.

    Examples:
        >>> enc = ConvPatchEncoder((16, 32, 64))
        >>> enc(torch.zeros(2, 3, 64, 64, dtype=torch.uint8)).shape
        torch.Size([2, 64, 64])
        >>> ConvPatchEncoder((16, 32, 64), keypoints=8)(torch.zeros(2, 3, 64, 64, dtype=torch.uint8)).shape
        torch.Size([2, 8, 64])
    """

    def __init__(self, channels: Sequence[int] = (32, 64, 128), norm_groups: int = 8, keypoints: int = 0) -> None:
        super().__init__()
        self.channels = tuple(int(c) for c in channels)
        if not self.channels or min(self.channels) < 1:
            raise ValueError(f"channels must be a non-empty list of positive widths, got {list(self.channels)!r}.")
        if self.channels[-1] % 4:
            raise ValueError(f"the last width must be a multiple of 4 (2-D position codes), got {self.channels[-1]}.")
        if not isinstance(keypoints, int) or keypoints < 0:
            raise ValueError(f"keypoints must be an int >= 0, got {keypoints!r}.")
        self.cnn = conv_stack(self.channels, norm_groups)
        self.num_keypoints = keypoints
        if keypoints:
            width = self.channels[-1]
            self.pool = SpatialSoftmax(width, keypoints)
            self.keypoint_position = nn.Linear(2, width)
            self.keypoint_embedding = nn.Parameter(torch.randn(keypoints, width) * 0.02)

    @property
    def out_features(self) -> int:
        return self.channels[-1]

    def load_conv_stack(self, source: nn.Module, *, freeze: bool = False) -> None:
        """Copy the weights of another :func:`conv_stack` of the same widths into this encoder's CNN.

        ``source`` may be longer than the stack (the baselines' image encoder continues
        it with its pooling and projection): its first ``3 * len(channels)`` modules are
        read. This starts the denoiser from a CNN trained by another policy on the same
        demonstrations, e.g. the BC baseline's (recipe option ``model.visual_encoder_init``).
        With ``freeze`` the copied CNN stays fixed (``requires_grad`` off); the keypoint
        read-out, when present, is not copied and keeps training.

        Examples:
            >>> bc_cnn = nn.Sequential(*conv_stack((16, 32, 64)), nn.Flatten())
            >>> enc = ConvPatchEncoder((16, 32, 64))
            >>> enc.load_conv_stack(bc_cnn, freeze=True)
            >>> torch.equal(enc.cnn[0].weight, bc_cnn[0].weight), enc.cnn[0].weight.requires_grad
            (True, False)
        """
        layers = list(source.children())[:len(self.cnn)]
        if [repr(m) for m in layers] != [repr(m) for m in self.cnn]:  # kinds, widths, strides, norm groups
            def describe(modules) -> str:
                modules = list(modules)
                widths = [m.out_channels for m in modules if isinstance(m, nn.Conv2d)]
                groups = [m.num_groups for m in modules if isinstance(m, nn.GroupNorm)]
                return f"convolution widths {widths}, GroupNorm groups {groups}"
            raise ValueError(f"the source CNN ({describe(source.children())}) does not begin with this encoder's "
                             f"conv_stack ({describe(self.cnn)}); set the denoiser's visual_encoder_channels to the "
                             "source's widths, or train the source with these.")
        self.cnn.load_state_dict(nn.Sequential(*layers).state_dict())
        self.cnn.requires_grad_(not freeze)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"images: expected [B, 3, H, W], got {list(image.shape)}.")
        stride = 2 ** len(self.channels)
        if image.shape[-1] % stride or image.shape[-2] % stride:
            raise ValueError(f"image side {tuple(image.shape[-2:])} is not a multiple of 2**len(channels)={stride}.")
        pixels = image.float() / 127.5 - 1.0  # (B, 3, H, W) in [-1, 1]
        features = self.cnn(pixels)  # (B, C, h, w)
        if self.num_keypoints:
            xy = self.pool(features).reshape(features.shape[0], self.num_keypoints, 2)  # (B, K, 2) in [-1, 1]
            return self.keypoint_position(xy) + self.keypoint_embedding  # (B, K, C)
        _, channels, h, w = features.shape
        cells = features.flatten(2).transpose(1, 2)  # (B, h*w, C)
        return cells + sincos_2d(h, w, channels, device=cells.device)
