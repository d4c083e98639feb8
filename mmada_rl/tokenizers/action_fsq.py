"""Baseline: residual finite scalar quantization on an MLP autoencoder.

An earlier choice of the MMaDA-VLA code. ``a -> normalise -> MLP -> z (d_e) ->
ResidualFSQ`` (vector-quantize-pytorch): each of ``num_quantizers`` stages
rounds a projection of the residual to a fixed grid of ``prod(levels)`` points,
so there is no codebook to learn and no dead code, only the autoencoder.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from tensordict.utils import NestedKey
from vector_quantize_pytorch import ResidualFSQ

from mmada_rl.tokenizers.action import (
    ActionTokenizer,
    ActionTokenizerConfig,
    TokenizerLoss,
    check_positive,
    make_mlp,
)

__all__ = ["FSQActionTokenizerConfig", "FSQActionTokenizer"]


@dataclass
class FSQActionTokenizerConfig(ActionTokenizerConfig):
    """Config of :class:`FSQActionTokenizer`.

    Attributes:
        levels: FSQ levels per latent channel; the vocabulary is ``prod(levels)``.
            ``len(levels)`` is the width of the quantized latent, so it should be at
            least the number of independent action dimensions: the default
            ``(2,) * 8`` (256 codes, 8 channels) reconstructs 7-DoF actions about 5x
            better than ``(4, 4, 4, 4)`` (also 256 codes, but a 4-channel bottleneck).
        num_quantizers: residual stages = tokens per action.
        embed_dim: autoencoder latent size ``d_e`` (projected to ``len(levels)`` by the FSQ).
        hidden_sizes: hidden widths of the encoder and decoder MLPs.
    """

    levels: tuple[int, ...] = (2,) * 8
    num_quantizers: int = 4
    embed_dim: int = 32
    hidden_sizes: tuple[int, ...] = (256, 256)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.levels = tuple(int(level) for level in self.levels)
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        if not self.levels or any(level < 2 for level in self.levels):
            raise ValueError(f"levels must be a non-empty tuple of integers >= 2, got {self.levels}.")
        check_positive("num_quantizers", self.num_quantizers)
        check_positive("embed_dim", self.embed_dim)
        if any(h < 1 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}.")


class FSQActionTokenizer(ActionTokenizer):
    """Residual-FSQ action tokenizer (MLP autoencoder, fixed scalar grids).

    Examples:
        >>> import torch
        >>> from mmada_rl.tokenizers import FSQActionTokenizer, FSQActionTokenizerConfig
        >>> tok = FSQActionTokenizer(FSQActionTokenizerConfig(levels=(8, 8, 4), num_quantizers=7))
        >>> tok.vocab_size, tok.tokens_per_action
        (256, 7)
    """

    config: FSQActionTokenizerConfig

    def __init__(
        self,
        config: FSQActionTokenizerConfig | None = None,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        config = config if config is not None else FSQActionTokenizerConfig()
        super().__init__(config, in_keys=in_keys, out_keys=out_keys)
        self.encoder = make_mlp(config.action_dim, config.hidden_sizes, config.embed_dim)
        self.quantizer = ResidualFSQ(
            levels=list(config.levels), num_quantizers=config.num_quantizers, dim=config.embed_dim
        )
        self.decoder = make_mlp(config.embed_dim, tuple(reversed(config.hidden_sizes)), config.action_dim)

    @property
    def tokens_per_action(self) -> int:
        return self.config.num_quantizers

    @property
    def vocab_size(self) -> int:
        return math.prod(self.config.levels)

    def _encode_normalized(self, normed: torch.Tensor) -> torch.Tensor:
        z = self.encoder(normed)[:, None]  # (N, 1, d_e)
        _, indices = self.quantizer(z)  # (N, 1, n_q) int32
        return indices[:, 0].long()

    def _decode_normalized(self, tokens: torch.Tensor) -> torch.Tensor:
        z_q = self.quantizer.get_output_from_indices(tokens[:, None])  # (N, 1, d_e)
        return self.decoder(z_q[:, 0])  # (N, d_a)

    def loss(self, normed: torch.Tensor) -> TokenizerLoss:
        """Reconstruction MSE in normalised units (FSQ has no commitment term)."""
        z_q, _ = self.quantizer(self.encoder(normed)[:, None])  # (B, 1, d_e)
        recon = F.mse_loss(self.decoder(z_q[:, 0]), normed)
        zero = recon.new_zeros(())
        return TokenizerLoss(total=recon, reconstruction=recon, commitment=zero)
