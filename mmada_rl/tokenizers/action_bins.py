"""Baseline: uniform bins per action dimension (OpenVLA; the MMaDA-VLA code's current choice).

Actions are normalised (1st / 99th percentiles -> [-1, 1], grippers -> sign),
clipped to [-1, 1] (counted and warned about by the normaliser) and each
dimension is binned by TorchRL's :class:`~torchrl.data.vla.UniformActionTokenizer`
into ``num_bins`` equal bins, so one action is ``d_a`` tokens and the round trip
errs by at most half a bin, ``1 / num_bins`` in normalised units.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict.utils import NestedKey
from torchrl.data.vla.tokenizers import UniformActionTokenizer

from mmada_rl.tokenizers.action import ActionTokenizer, ActionTokenizerConfig

__all__ = ["UniformBinActionTokenizerConfig", "UniformBinActionTokenizer"]


@dataclass
class UniformBinActionTokenizerConfig(ActionTokenizerConfig):
    """Config of :class:`UniformBinActionTokenizer`.

    Attributes:
        num_bins: bins per dimension (256 in OpenVLA / MMaDA-VLA).
        clip_to: fixed to ``"quantiles"``: the bins span normalised [-1, 1].
    """

    num_bins: int = 256
    clip_to: str = "quantiles"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.num_bins < 2:
            raise ValueError(f"num_bins must be >= 2, got {self.num_bins}.")
        if self.clip_to != "quantiles":
            raise ValueError(
                f"uniform bins span the normalised [-1, 1] range, so clip_to must be 'quantiles', got {self.clip_to!r}; "
                "set low_quantile=0, high_quantile=1 to bin the full data range."
            )


class UniformBinActionTokenizer(ActionTokenizer):
    """Per-dimension uniform-bin action tokenizer on normalised actions.

    Examples:
        >>> import torch
        >>> from mmada_rl.tokenizers import UniformBinActionTokenizer, fit_action_tokenizer
        >>> tok = UniformBinActionTokenizer()
        >>> actions = torch.cat([torch.rand(1000, 6) * 2 - 1, torch.randint(0, 2, (1000, 1)) * 2.0 - 1], -1)
        >>> _ = fit_action_tokenizer(tok, actions, progress=False)  # fits the normaliser only
        >>> tok.encode(actions[:2]).shape, tok.vocab_size, tok.tokens_per_action
        (torch.Size([2, 7]), 256, 7)
    """

    config: UniformBinActionTokenizerConfig

    def __init__(
        self,
        config: UniformBinActionTokenizerConfig | None = None,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        config = config if config is not None else UniformBinActionTokenizerConfig()
        super().__init__(config, in_keys=in_keys, out_keys=out_keys)
        self.bins = UniformActionTokenizer(config.num_bins, low=-1.0, high=1.0, action_dim=config.action_dim)

    @property
    def tokens_per_action(self) -> int:
        return self.config.action_dim

    @property
    def vocab_size(self) -> int:
        return self.bins.vocab_size

    @property
    def half_bin_width(self) -> float:
        """Largest round-trip error in normalised units, for actions inside the fitted range."""
        return 1.0 / self.config.num_bins

    def _encode_normalized(self, normed: torch.Tensor) -> torch.Tensor:
        return self.bins.encode(normed)  # (N, d_a)

    def _decode_normalized(self, tokens: torch.Tensor) -> torch.Tensor:
        return self.bins.decode(tokens)  # (N, d_a), bin centres

    @property
    def has_ordered_bins(self) -> bool:
        return True

    def _bin_centres(self) -> torch.Tensor:
        codes = torch.arange(self.vocab_size, device=self.bins.low.device)  # on the bins' device
        codes = codes[:, None].expand(-1, self.config.action_dim)  # (V, d_a)
        return self.bins.decode(codes)[:, 0]  # (V,): the same bins in every dimension
