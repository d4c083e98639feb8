"""What every action tokenizer of mmada_rl shares.

An action tokenizer is both a :class:`torchrl.data.vla.tokenizers.ActionTokenizerBase`
(``encode`` / ``decode`` / ``vocab_size``, so TorchRL's VLA code can use it) and a
:class:`tensordict.nn.TensorDictModuleBase` (``forward(td)`` reads the action
chunk and writes its tokens). All three kinds normalise actions with the same
:class:`~mmada_rl.tokenizers.normalize.ActionNormalizer`, emit
``tokens_per_action`` tokens in ``[0, vocab_size)`` per action, and save / load
themselves through :mod:`mmada_rl.tokenizers.io`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data.vla.tokenizers import ActionTokenizerBase

from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_TOKENS_KEY
from mmada_rl.tokenizers.io import TokenizerIOMixin
from mmada_rl.tokenizers.normalize import CLIP_MODES, ActionNormalizer

__all__ = ["ActionTokenizerConfig", "ActionTokenizer", "TokenizerLoss", "make_mlp"]


@dataclass
class ActionTokenizerConfig:
    """Fields shared by every action tokenizer config.

    Attributes:
        action_dim: action size ``d_a`` (7 for ManiSkill's ``pd_ee_delta_pose``).
        gripper_dims: dimensions that are binary grippers (kept as -1 / +1).
        low_quantile: data quantile mapped to -1 when normalising.
        high_quantile: data quantile mapped to +1 when normalising.
        clip_to: range kept when encoding, ``"quantiles"`` or ``"data_range"``
            (see :mod:`mmada_rl.tokenizers.normalize`).
    """

    action_dim: int = 7
    gripper_dims: tuple[int, ...] = (6,)
    low_quantile: float = 0.01
    high_quantile: float = 0.99
    clip_to: str = "data_range"

    def __post_init__(self) -> None:
        self.gripper_dims = tuple(int(d) for d in self.gripper_dims)
        if self.action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {self.action_dim}.")
        bad = [d for d in self.gripper_dims if not 0 <= d < self.action_dim]
        if bad:
            raise ValueError(f"gripper_dims {bad} are outside [0, action_dim={self.action_dim}).")
        if not 0.0 <= self.low_quantile < self.high_quantile <= 1.0:
            raise ValueError(
                f"need 0 <= low_quantile < high_quantile <= 1, got {self.low_quantile}, {self.high_quantile}."
            )
        if self.clip_to not in CLIP_MODES:
            raise ValueError(f"clip_to must be one of {CLIP_MODES}, got {self.clip_to!r}.")


class TokenizerLoss(NamedTuple):
    """Training loss of a learned tokenizer (all scalars)."""

    total: torch.Tensor
    reconstruction: torch.Tensor
    commitment: torch.Tensor


def make_mlp(in_dim: int, hidden_sizes: Sequence[int], out_dim: int) -> nn.Sequential:
    """``Linear -> SiLU`` stack ending in a plain ``Linear``."""
    layers: list[nn.Module] = []
    for width in hidden_sizes:
        layers += [nn.Linear(in_dim, width), nn.SiLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


def check_positive(name: str, value, *, allow_zero: bool = False) -> None:
    """Raises ``ValueError`` naming ``name`` unless ``value`` is > 0 (or >= 0)."""
    if value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value}.")


class ActionTokenizer(TokenizerIOMixin, ActionTokenizerBase, TensorDictModuleBase):
    """Base of the action tokenizers: normalisation, token checks, TensorDict I/O, save / load.

    Subclasses set ``self.config`` and implement ``tokens_per_action``,
    ``vocab_size``, ``_encode_normalized`` and ``_decode_normalized`` on flat
    ``(N, d_a)`` / ``(N, d_tok)`` tensors; learned ones also implement ``loss``.

    Args:
        config: the tokenizer's config.
        in_keys: the continuous-action key read by ``forward`` (default ``("vla_action", "chunk")``).
        out_keys: the token key written by ``forward`` (default ``("vla_action", "tokens")``).
    """

    config: ActionTokenizerConfig

    def __init__(
        self,
        config: ActionTokenizerConfig,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.in_keys = list(in_keys) if in_keys is not None else [ACTION_CHUNK_KEY]
        self.out_keys = list(out_keys) if out_keys is not None else [ACTION_TOKENS_KEY]
        if len(self.in_keys) != 1 or len(self.out_keys) != 1:
            raise ValueError(f"an action tokenizer reads one key and writes one, got {self.in_keys} -> {self.out_keys}.")
        self.normalizer = ActionNormalizer(
            config.action_dim,
            config.gripper_dims,
            low_quantile=config.low_quantile,
            high_quantile=config.high_quantile,
            clip_to=config.clip_to,
        )

    # -- interface for subclasses -------------------------------------------
    @property
    def tokens_per_action(self) -> int:
        """Number of tokens ``d_tok`` each action becomes."""
        raise NotImplementedError

    @property
    def action_dim(self) -> int:
        return self.config.action_dim

    @property
    def is_trainable(self) -> bool:
        """Whether the tokenizer has weights to fit beyond the normaliser."""
        return any(p.requires_grad for p in self.parameters())

    def _encode_normalized(self, normed: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _decode_normalized(self, tokens: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def loss(self, normed: torch.Tensor) -> TokenizerLoss:
        """Training loss on a batch of normalised actions ``(B, d_a)``."""
        raise NotImplementedError(f"{type(self).__name__} has nothing to train.")

    # -- public API ----------------------------------------------------------
    @torch.no_grad()
    def encode(self, actions: torch.Tensor) -> torch.Tensor:
        """Env-unit actions ``[..., d_a]`` -> tokens ``long [..., d_tok]`` in ``[0, vocab_size)``."""
        normed = self.normalizer.normalize(actions)  # (..., d_a)
        lead = normed.shape[:-1]
        flat = normed.reshape(-1, self.action_dim)  # (N, d_a)
        if flat.shape[0] == 0:
            return torch.zeros(*lead, self.tokens_per_action, dtype=torch.long)
        tokens = self._encode_normalized(flat)  # (N, d_tok)
        return tokens.long().reshape(*lead, self.tokens_per_action)

    @torch.no_grad()
    def decode(self, tokens: torch.Tensor) -> torch.Tensor:
        """Tokens ``[..., d_tok]`` -> env-unit actions ``[..., d_a]`` (grippers exactly -1 / +1)."""
        tokens = self.check_tokens(tokens)
        lead = tokens.shape[:-1]
        flat = tokens.reshape(-1, self.tokens_per_action)  # (N, d_tok)
        if flat.shape[0] == 0:
            return torch.zeros(*lead, self.action_dim)
        normed = self._decode_normalized(flat)  # (N, d_a)
        return self.normalizer.denormalize(normed).reshape(*lead, self.action_dim)

    @property
    def has_ordered_bins(self) -> bool:
        """Whether each token is one action dimension's bin, so a distribution over a token's codes
        has a mean (:meth:`decode_mean`)."""
        return False

    def require_ordered_bins(self, what: str) -> None:
        """A ``ValueError`` saying that ``what`` (e.g. ``"loss.action_mean_weight=1 scores the expected bin of each
        action token"``) needs ordered bin tokens, unless this tokenizer has them (:attr:`has_ordered_bins`)."""
        if not self.has_ordered_bins:
            raise ValueError(f"{what}, so it needs ordered bin tokens (tokenizers.action_type=bins), "
                             f"not a {type(self).__name__}.")

    def _bin_centres(self) -> torch.Tensor:
        """Normalised value ``[vocab_size]`` of each code (tokenizers with ordered bins)."""
        raise NotImplementedError

    @torch.no_grad()
    def decode_mean(self, probs: torch.Tensor) -> torch.Tensor:
        """Expected action under per-token distributions ``probs [..., d_tok, vocab_size]`` -> env units ``[..., d_a]``.

        Each dimension's value is the probability-weighted mean of its bin centres (the
        regression read-out of a binned prediction); grippers are snapped to -1 / +1 by the
        sign of that mean. Only for tokenizers whose tokens are ordered bins of one
        dimension each (:attr:`has_ordered_bins`): a VQ or FSQ code has no mean.
        """
        self.require_ordered_bins("the mean read-out averages each token's bin centres")
        if probs.ndim < 2 or probs.shape[-2:] != (self.tokens_per_action, self.vocab_size):
            raise ValueError(f"probs must have shape [..., {self.tokens_per_action}, {self.vocab_size}], "
                             f"got {tuple(probs.shape)}.")
        normed = probs @ self._bin_centres().to(probs)  # (..., d_a)
        return self.normalizer.denormalize(normed)

    def check_tokens(self, tokens: torch.Tensor) -> torch.Tensor:
        """Returns ``tokens`` as long after checking dtype, trailing size and range."""
        tokens = torch.as_tensor(tokens)
        if tokens.is_floating_point() or tokens.dtype == torch.bool:
            raise ValueError(f"tokens must be an integer tensor, got {tokens.dtype}.")
        if tokens.ndim == 0 or tokens.shape[-1] != self.tokens_per_action:
            raise ValueError(
                f"tokens must have shape [..., {self.tokens_per_action}] (tokens_per_action), got {tuple(tokens.shape)}."
            )
        if tokens.numel() and (tokens.min() < 0 or tokens.max() >= self.vocab_size):
            raise ValueError(
                f"tokens must lie in [0, {self.vocab_size}), got values in [{int(tokens.min())}, {int(tokens.max())}]."
            )
        return tokens.long()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes ``encode(td[in_key])`` to ``td[out_key]``."""
        tensordict.set(self.out_keys[0], self.encode(tensordict.get(self.in_keys[0])))
        return tensordict

    def extra_state_json(self) -> dict:
        """JSON written beside the config: the normaliser statistics."""
        return {"normalizer": self.normalizer.statistics()}
