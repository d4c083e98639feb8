"""Pre-norm transformer blocks of the denoiser.

Self-attention (optionally masked, optionally after cached keys and values)
and an optional cross-attention sublayer to visual features, both through
``torch.nn.functional.scaled_dot_product_attention``.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["Attention", "ScalarEmbedding", "TransformerBlock"]


class Attention(nn.Module):
    """Multi-head attention; self-attention when ``context`` is None.

    ``prefix``: keys and values ``([B, H, C, Dh], [B, H, C, Dh])`` computed
    earlier (a conditioning cache) that the queries attend to before their own
    keys; ``return_kv``: also return this call's own keys and values.
    """

    def __init__(self, dim: int, num_heads: int, dropout: float = 0.0, context_dim: int | None = None) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"d_model={dim} must be divisible by num_heads={num_heads}.")
        self.num_heads = num_heads
        self.dropout = dropout
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(context_dim or dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(
        self,
        x: torch.Tensor,
        context: torch.Tensor | None = None,
        attn_mask: torch.Tensor | None = None,
        prefix: tuple[torch.Tensor, torch.Tensor] | None = None,
        return_kv: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        batch, length, dim = x.shape  # (B, L, D)
        context = x if context is None else context  # (B, N, D_ctx)
        q = self.q(x).view(batch, length, self.num_heads, -1).transpose(1, 2)  # (B, H, L, Dh)
        k, v = self.kv(context).view(batch, context.shape[1], 2, self.num_heads, -1).permute(2, 0, 3, 1, 4)
        own = (k, v)
        if prefix is not None:
            k, v = torch.cat([prefix[0], k], dim=2), torch.cat([prefix[1], v], dim=2)  # (B, H, C + N, Dh)
        y = F.scaled_dot_product_attention(
            q, k, v, attn_mask=attn_mask, dropout_p=self.dropout if self.training else 0.0
        )  # (B, H, L, Dh)
        out = self.out(y.transpose(1, 2).reshape(batch, length, dim))
        return (out, own) if return_kv else out


class TransformerBlock(nn.Module):
    """``x + SelfAttn(LN x)``, then ``x + CrossAttn(LN x, visual)`` (optional), then ``x + MLP(LN x)``.

    ``prefix`` and ``return_kv`` go to the self-attention (see :class:`Attention`).
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        dropout: float = 0.0,
        cross_attention: bool = False,
    ) -> None:
        super().__init__()
        self.norm_attn = nn.LayerNorm(dim)
        self.attn = Attention(dim, num_heads, dropout)
        self.norm_cross = nn.LayerNorm(dim) if cross_attention else None
        self.cross = Attention(dim, num_heads, dropout) if cross_attention else None
        self.norm_mlp = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        self.drop = nn.Dropout(dropout)

    def forward(
        self,
        x: torch.Tensor,
        attn_mask: torch.Tensor | None = None,
        visual: torch.Tensor | None = None,
        prefix: tuple[torch.Tensor, torch.Tensor] | None = None,
        return_kv: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        attended = self.attn(self.norm_attn(x), attn_mask=attn_mask, prefix=prefix, return_kv=return_kv)
        if return_kv:
            attended, kv = attended
        x = x + self.drop(attended)  # (B, L, D)
        if self.cross is not None:
            x = x + self.drop(self.cross(self.norm_cross(x), context=visual))
        x = x + self.drop(self.mlp(self.norm_mlp(x)))
        return (x, kv) if return_kv else x


class ScalarEmbedding(nn.Module):
    """Sinusoidal embedding of a value in ``[0, 1]`` through an MLP: ``[*B] -> [*B, D]``.

    The denoiser embeds the masking ratio ``ρ`` with it (``scale=1000``, as
    diffusion models embed timesteps), and, as an option, the value of each
    proprioception bin (``scale=10``: the highest frequency turns 10 radians over
    ``[0, 1]``, so the features' distance grows with the values' distance across
    the whole range instead of aliasing between neighbouring bins).
    """

    def __init__(self, dim: int, frequencies: int = 64, max_period: float = 10_000.0, scale: float = 1000.0) -> None:
        super().__init__()
        self.scale = float(scale)
        half = frequencies // 2
        freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32) / half)
        self.register_buffer("freqs", freqs, persistent=False)
        self.mlp = nn.Sequential(nn.Linear(2 * half, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, value: torch.Tensor) -> torch.Tensor:
        angles = self.scale * value.float()[..., None] * self.freqs  # (*B, F/2)
        return self.mlp(torch.cat([angles.sin(), angles.cos()], dim=-1))  # (*B, D)
