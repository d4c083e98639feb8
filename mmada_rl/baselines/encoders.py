"""The observation encoder shared by the baselines.

:class:`ObservationEncoder` turns a uint8 RGB image ``[B, 3, H, W]`` and the
proprioceptive state ``[B, S]`` into one feature vector ``[B, F]``: a small
strided CNN (GroupNorm instead of BatchNorm, as Diffusion Policy does, so the
policy behaves the same in train and eval mode and with any batch size) pooled
by a spatial softmax (Diffusion Policy's and robomimic's choice: the expected
image coordinates of learned keypoints, which is what locating a cube needs) or
flattened, and a state MLP, concatenated. Both baselines use it, trained end to end with their head.

:class:`~mmada_rl.data.augment.RandomShift` (DrQ's random-shift augmentation of
the training windows, shared with the pretraining recipe) is re-exported here.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from mmada_rl.baselines.normalization import StateStandardizer
from mmada_rl.data.augment import RandomShift, random_shift
from mmada_rl.data.windows import kept_state_dims
from mmada_rl.diffusion.visual import SpatialSoftmax, conv_stack

__all__ = ["EncoderConfig", "ObservationEncoder", "POOLS", "RandomShift", "SpatialSoftmax", "random_shift"]

#: Accepted values of ``EncoderConfig.pool``.
POOLS = ("spatial_softmax", "flatten")


@dataclass
class EncoderConfig:
    """Sizes of :class:`ObservationEncoder`.

    Attributes:
        channels: output channels of each stride-2 3x3 convolution (an image side
            of ``H`` leaves ``H / 2**len(channels)`` pixels).
        image_features: size of the image embedding.
        state_features: size of the state embedding.
        norm_groups: GroupNorm groups (the largest divisor of each width up to this).
        pool: ``"spatial_softmax"`` (``num_keypoints`` expected x-y positions) or
            ``"flatten"`` (every cell of the last feature map) before the image embedding.
        num_keypoints: keypoints of the spatial softmax.
        drop_state_dims: state dimensions the policy does not read (e.g. ``9..17``,
            the Panda's joint velocities in ManiSkill's state: a policy that sees
            them can learn to copy its own motion, "stand still when still", from
            the planner's pauses instead of reacting to the scene).
    """

    channels: tuple[int, ...] = (32, 64, 128)
    image_features: int = 128
    state_features: int = 64
    norm_groups: int = 8
    pool: str = "spatial_softmax"
    num_keypoints: int = 32
    drop_state_dims: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        self.channels = tuple(int(c) for c in self.channels)
        self.drop_state_dims = tuple(sorted({int(d) for d in self.drop_state_dims}))
        if not self.channels or min(self.channels) < 1:
            raise ValueError(f"channels must be a non-empty list of positive widths, got {list(self.channels)!r}.")
        if self.pool not in POOLS:
            raise ValueError(f"pool must be one of {POOLS}, got {self.pool!r}.")
        for name in ("image_features", "state_features", "norm_groups", "num_keypoints"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")

    @property
    def out_features(self) -> int:
        return self.image_features + self.state_features


class ObservationEncoder(nn.Module):
    """Image CNN + state MLP -> features ``[B, image_features + state_features]``.

    Args:
        config: sizes.
        image_size: side of the square input image (a multiple of ``2**len(channels)``);
            ``None``: no image, the state MLP alone (``[B, state_features]``; a
            policy on ManiSkill's privileged state vector, a reference).
        state_dim: ``S``.
        state_mean, state_std: state moments of the training data (default: identity).

    Examples:
        >>> enc = ObservationEncoder(EncoderConfig(channels=(8, 16)), image_size=64, state_dim=29)
        >>> enc(torch.zeros(2, 3, 64, 64, dtype=torch.uint8), torch.zeros(2, 29)).shape
        torch.Size([2, 192])
    """

    def __init__(self, config: EncoderConfig, *, image_size: int | None, state_dim: int,
                 state_mean: torch.Tensor | None = None, state_std: torch.Tensor | None = None) -> None:
        super().__init__()
        self.config, self.image_size = config, image_size
        self.cnn = None if image_size is None else self._build_cnn(config, image_size)
        self.standardize = StateStandardizer(state_dim, state_mean, state_std)
        kept = kept_state_dims(config.drop_state_dims, state_dim, "drop_state_dims")
        self.register_buffer("state_index", torch.tensor(kept), persistent=False)
        self.state_mlp = nn.Sequential(nn.Linear(len(kept), config.state_features), nn.Mish(),
                                       nn.Linear(config.state_features, config.state_features), nn.Mish())

    @staticmethod
    def _build_cnn(config: EncoderConfig, image_size: int) -> nn.Sequential:
        stride = 2 ** len(config.channels)
        if image_size % stride:
            raise ValueError(f"image_size={image_size} is not a multiple of 2**len(channels)={stride}; "
                             f"use fewer encoder channels or another image size.")
        width = config.channels[-1]
        side = image_size // stride
        if config.pool == "spatial_softmax":
            pool, pooled = SpatialSoftmax(width, config.num_keypoints), 2 * config.num_keypoints
        else:
            pool, pooled = nn.Flatten(), width * side * side
        return nn.Sequential(*conv_stack(config.channels, config.norm_groups), pool, nn.Linear(pooled, config.image_features),
                             nn.LayerNorm(config.image_features), nn.Mish())

    @property
    def out_features(self) -> int:
        return self.config.out_features if self.cnn is not None else self.config.state_features

    def forward(self, image: torch.Tensor | None, state: torch.Tensor) -> torch.Tensor:
        """``image`` uint8 ``(B, 3, H, W)`` (``None`` without a CNN), ``state`` ``(B, S)`` -> ``(B, F)``."""
        features = self.state_mlp(self.standardize(state.float())[..., self.state_index])  # (B, state_features)
        if self.cnn is None:
            return features
        if image is None or image.shape[-2:] != (self.image_size, self.image_size):
            got = None if image is None else tuple(image.shape[-2:])
            raise ValueError(f"observation images are {got} but the encoder was built for "
                             f"{self.image_size}x{self.image_size}; use env image_size={self.image_size}.")
        pixels = image.float() / 127.5 - 1.0  # (B, 3, H, W) in [-1, 1]
        return torch.cat([self.cnn(pixels), features], -1)  # (B, F)
