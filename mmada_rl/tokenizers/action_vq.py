"""The paper's action tokenizer: a learned projection and a residual EMA codebook.

``a (d_a) -> normalise -> W_a: MLP -> z (d_e) -> ResidualVQ (d_tok quantizers)``
gives one token per quantizer; the decoder maps the summed codes back to a
normalised action, whose gripper dimensions are snapped to -1 / +1. The
codebooks learn by exponential moving average (vector-quantize-pytorch's
``decay``), start from k-means on the first batch (``kmeans_init``) and restart
codes whose EMA usage falls below ``dead_code_threshold``; the encoder and
decoder learn by gradient on reconstruction + commitment.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from tensordict.utils import NestedKey
from vector_quantize_pytorch import ResidualVQ

from mmada_rl.tokenizers.action import (
    ActionTokenizer,
    ActionTokenizerConfig,
    TokenizerLoss,
    check_positive,
    make_mlp,
)

__all__ = ["VQActionTokenizerConfig", "VQActionTokenizer"]


@dataclass
class VQActionTokenizerConfig(ActionTokenizerConfig):
    """Config of :class:`VQActionTokenizer` (normalisation fields: :class:`ActionTokenizerConfig`).

    Attributes:
        codebook_size: codes per quantizer; the token vocabulary per position.
        embed_dim: latent size ``d_e`` of ``W_a a``.
        tokens_per_action: ``d_tok``, number of residual quantizers (one token each).
        ema_decay: EMA decay of the codebooks (closer to 1 = slower).
        kmeans_init: initialise each codebook by k-means on the first training batch.
        kmeans_iters: k-means iterations of that initialisation.
        dead_code_threshold: a code whose EMA usage (expected assignments per
            batch) falls below this is restarted on a vector of the batch; 0 disables.
        hidden_sizes: hidden widths of the encoder and decoder MLPs.
        commitment_weight: weight of ``||z - sg(q)||^2`` in the loss.
    """

    codebook_size: int = 256
    embed_dim: int = 32
    tokens_per_action: int = 4
    ema_decay: float = 0.95
    kmeans_init: bool = True
    kmeans_iters: int = 10
    dead_code_threshold: float = 0.1
    hidden_sizes: tuple[int, ...] = (256, 256)
    commitment_weight: float = 0.25

    def __post_init__(self) -> None:
        super().__post_init__()
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        if self.codebook_size < 2:
            raise ValueError(f"codebook_size must be >= 2, got {self.codebook_size}.")
        check_positive("embed_dim", self.embed_dim)
        check_positive("tokens_per_action", self.tokens_per_action)
        check_positive("kmeans_iters", self.kmeans_iters)
        check_positive("dead_code_threshold", self.dead_code_threshold, allow_zero=True)
        check_positive("commitment_weight", self.commitment_weight, allow_zero=True)
        if not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in (0, 1), got {self.ema_decay}.")
        if any(h < 1 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}.")


class VQActionTokenizer(ActionTokenizer):
    """Residual-VQ action tokenizer with EMA codebooks and dead-code restarts.

    Args:
        config: a :class:`VQActionTokenizerConfig`.
        in_keys / out_keys: keys of ``forward`` (default ``("vla_action", "chunk")``
            -> ``("vla_action", "tokens")``).

    Examples:
        >>> import torch
        >>> from mmada_rl.tokenizers import VQActionTokenizer, VQActionTokenizerConfig, fit_action_tokenizer
        >>> tok = VQActionTokenizer(VQActionTokenizerConfig(codebook_size=16, embed_dim=8,
        ...                                                 tokens_per_action=2, hidden_sizes=(32,)))
        >>> actions = torch.cat([torch.rand(512, 6) * 2 - 1, torch.randint(0, 2, (512, 1)) * 2.0 - 1], -1)
        >>> result = fit_action_tokenizer(tok, actions, steps=20, batch_size=128, progress=False)
        >>> tokens = tok.encode(actions[:4])
        >>> tokens.shape, tokens.dtype, tok.vocab_size
        (torch.Size([4, 2]), torch.int64, 16)
        >>> tok.decode(tokens).shape
        torch.Size([4, 7])
    """

    config: VQActionTokenizerConfig

    def __init__(
        self,
        config: VQActionTokenizerConfig | None = None,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        config = config if config is not None else VQActionTokenizerConfig()
        super().__init__(config, in_keys=in_keys, out_keys=out_keys)
        self.encoder = make_mlp(config.action_dim, config.hidden_sizes, config.embed_dim)  # W_a
        self.quantizer = ResidualVQ(
            dim=config.embed_dim,
            num_quantizers=config.tokens_per_action,
            codebook_size=config.codebook_size,
            decay=config.ema_decay,
            kmeans_init=config.kmeans_init,
            kmeans_iters=config.kmeans_iters,
            threshold_ema_dead_code=config.dead_code_threshold,
            commitment_weight=config.commitment_weight,
        )
        self.decoder = make_mlp(config.embed_dim, tuple(reversed(config.hidden_sizes)), config.action_dim)

    @property
    def tokens_per_action(self) -> int:
        return self.config.tokens_per_action

    @property
    def vocab_size(self) -> int:
        return self.config.codebook_size

    @property
    def codebooks(self) -> torch.Tensor:
        """The codebooks, ``(d_tok, codebook_size, d_e)``."""
        return self.quantizer.codebooks

    def _check_initialised(self) -> None:
        if not all(bool(layer._codebook.initted) for layer in self.quantizer.layers):
            raise RuntimeError(
                "the codebooks are not initialised yet (kmeans_init waits for training data); "
                "fit the tokenizer with fit_action_tokenizer first."
            )

    def _encode_normalized(self, normed: torch.Tensor) -> torch.Tensor:
        self._check_initialised()
        z = self.encoder(normed)[:, None]  # (N, 1, d_e)
        # freeze_codebook: encoding never moves the codebook, even in train mode
        _, indices, _ = self.quantizer(z, freeze_codebook=True)  # (N, 1, d_tok)
        return indices[:, 0]

    def _decode_normalized(self, tokens: torch.Tensor) -> torch.Tensor:
        z_q = self.quantizer.get_output_from_indices(tokens[:, None])  # (N, 1, d_e)
        return self.decoder(z_q[:, 0])  # (N, d_a)

    def loss(self, normed: torch.Tensor) -> TokenizerLoss:
        """Reconstruction MSE (normalised units) + commitment; in train mode this also
        runs the EMA codebook update and the dead-code restarts."""
        z = self.encoder(normed)[:, None]  # (B, 1, d_e)
        z_q, _, commit = self.quantizer(z)  # commit: (d_tok,), already weighted
        recon = F.mse_loss(self.decoder(z_q[:, 0]), normed)
        commitment = commit.sum()
        return TokenizerLoss(total=recon + commitment, reconstruction=recon, commitment=commitment)
