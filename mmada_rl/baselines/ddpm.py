"""Gaussian DDPM over flat vectors: the noise schedule, the noise-prediction network, DDIM sampling.

:class:`ChunkDDPM` exposes what TorchRL's :class:`~torchrl.objectives.DiffusionBCLoss`
reads from a diffusion actor's ``.module``: ``num_steps``, ``add_noise(clean, t)``
and a ``score_network`` called on ``cat([noisy, condition, t], -1)`` (``t`` the
raw integer timestep as a float). We do not use TorchRL's own module behind
``DiffusionActor`` (``_DDPMModule``, private): its linear beta schedule
(1e-4 .. 0.02) is made for ~1000 steps and at Diffusion Policy's 100 training
steps leaves ``alpha_bar_T ~ 0.37``, i.e. the last step is far from pure noise;
it runs every training step at inference and never clips. Here, after Chi et al.:

* the squared-cosine schedule (Nichol & Dhariwal) over ``num_steps`` (100);
* DDIM sampling (eta = 0) with ``num_inference_steps`` evenly spaced steps that
  start at the last training step, clipping the clean-sample estimate to the
  normalised action box ``[-1, 1]`` at every step;
* a noise-prediction MLP whose residual blocks are FiLM-conditioned on the
  observation features and a sinusoidal embedding of ``t``.
"""
from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["ChunkDDPM", "NoisePredictionMLP", "squared_cosine_alphas_cumprod"]


def squared_cosine_alphas_cumprod(num_steps: int, s: float = 0.008, max_beta: float = 0.999) -> torch.Tensor:
    """``alpha_bar_t`` of the squared-cosine schedule, ``t = 0 .. num_steps - 1`` (float64 -> float32)."""
    def f(t):
        return math.cos((t / num_steps + s) / (1 + s) * math.pi / 2) ** 2

    betas = torch.tensor([min(1 - f(t + 1) / f(t), max_beta) for t in range(num_steps)], dtype=torch.float64)
    return torch.cumprod(1 - betas, 0).float()


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding ``[B, dim]`` of float timesteps ``[B]``."""
    half = dim // 2
    freqs = torch.exp(-math.log(10_000) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = t.float()[:, None] * freqs[None]  # (B, half)
    emb = torch.cat([angles.sin(), angles.cos()], -1)
    return nn.functional.pad(emb, (0, dim - 2 * half))


class _FiLMBlock(nn.Module):
    """``h + Linear(Mish(FiLM(LayerNorm(h), c)))``."""

    def __init__(self, width: int, cond_width: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(width)
        self.film = nn.Linear(cond_width, 2 * width)
        self.out = nn.Sequential(nn.Mish(), nn.Linear(width, width))

    def forward(self, h: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(cond).chunk(2, -1)
        return h + self.out(self.norm(h) * (1 + scale) + shift)


class NoisePredictionMLP(nn.Module):
    """``eps_theta(x_t, c, t)`` on one input ``cat([x_t, c, t], -1)``, the layout DiffusionBCLoss builds.

    Args:
        action_dim: size ``D`` of the diffused vector (``K * A`` for a flattened chunk).
        cond_dim: size ``F`` of the conditioning features.
        hidden_size: width of the residual blocks.
        num_blocks: number of FiLM residual blocks.
        time_embed_dim: size of the timestep embedding.
    """

    def __init__(self, action_dim: int, cond_dim: int, *, hidden_size: int = 256, num_blocks: int = 3,
                 time_embed_dim: int = 64) -> None:
        super().__init__()
        self.action_dim, self.cond_dim, self.time_embed_dim = action_dim, cond_dim, time_embed_dim
        self.time_mlp = nn.Sequential(nn.Linear(time_embed_dim, 4 * time_embed_dim), nn.Mish(),
                                      nn.Linear(4 * time_embed_dim, time_embed_dim))
        cond_width = cond_dim + time_embed_dim
        self.inp = nn.Linear(action_dim, hidden_size)
        self.blocks = nn.ModuleList(_FiLMBlock(hidden_size, cond_width) for _ in range(num_blocks))
        self.out = nn.Sequential(nn.LayerNorm(hidden_size), nn.Mish(), nn.Linear(hidden_size, action_dim))

    def forward(self, model_input: torch.Tensor) -> torch.Tensor:
        """``[B, D + F + 1]`` -> predicted noise ``[B, D]``."""
        expected = self.action_dim + self.cond_dim + 1
        if model_input.shape[-1] != expected:
            raise ValueError(f"the noise network takes [noisy ({self.action_dim}) | condition ({self.cond_dim}) | t (1)] "
                             f"= {expected} values, got {model_input.shape[-1]}.")
        x, cond, t = model_input.split([self.action_dim, self.cond_dim, 1], -1)
        cond = torch.cat([cond, self.time_mlp(timestep_embedding(t.squeeze(-1), self.time_embed_dim))], -1)
        h = self.inp(x)
        for block in self.blocks:
            h = block(h, cond)
        return self.out(h)


class ChunkDDPM(nn.Module):
    """Forward process and DDIM sampler of a flat Gaussian DDPM in the box ``[-1, 1]^D``.

    Args:
        score_network: the noise predictor (see :class:`NoisePredictionMLP`).
        action_dim: ``D``.
        num_steps: training timesteps ``T``.

    Examples:
        >>> ddpm = ChunkDDPM(NoisePredictionMLP(35, 192), action_dim=35, num_steps=100)
        >>> noisy, noise = ddpm.add_noise(torch.zeros(8, 35), torch.randint(0, 100, (8,)))
        >>> ddpm.sample(torch.randn(8, 192), num_inference_steps=10).shape
        torch.Size([8, 35])
    """

    def __init__(self, score_network: nn.Module, action_dim: int, num_steps: int = 100) -> None:
        super().__init__()
        if num_steps < 2:
            raise ValueError(f"num_steps (training timesteps) must be >= 2, got {num_steps!r}.")
        self.score_network = score_network
        self.action_dim, self.num_steps = int(action_dim), int(num_steps)
        self.register_buffer("alphas_cumprod", squared_cosine_alphas_cumprod(num_steps), persistent=False)

    def add_noise(self, clean: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x_t = sqrt(ab_t) x_0 + sqrt(1 - ab_t) eps``; returns ``(x_t, eps)``, both ``[..., D]``."""
        alpha_bar = self.alphas_cumprod[t].unsqueeze(-1).to(clean.dtype)  # (..., 1)
        noise = torch.randn_like(clean)
        return alpha_bar.sqrt() * clean + (1 - alpha_bar).sqrt() * noise, noise

    def inference_timesteps(self, num_inference_steps: int) -> list[int]:
        """``num_inference_steps`` distinct timesteps from ``T - 1`` down to 0."""
        if not 1 <= num_inference_steps <= self.num_steps:
            raise ValueError(f"num_inference_steps must lie in [1, num_steps={self.num_steps}], got {num_inference_steps!r}.")
        return torch.linspace(self.num_steps - 1, 0, num_inference_steps).round().long().tolist()

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, num_inference_steps: int, *, greedy: bool = False,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """DDIM (eta = 0) from ``x_T`` to ``x_0`` in ``[-1, 1]^D`` conditioned on ``cond`` ``[B, F]``.

        ``greedy``: start from ``x_T = 0`` (the prior's mode, TorchRL's
        ``DiffusionActor`` convention for ``ExplorationType.DETERMINISTIC``),
        which makes the chunk a deterministic function of the observation;
        otherwise ``x_T ~ N(0, I)`` from ``generator``.
        """
        B = cond.shape[0]
        x = torch.zeros(B, self.action_dim, device=cond.device, dtype=cond.dtype)
        if not greedy:
            x = torch.randn(B, self.action_dim, generator=generator, dtype=cond.dtype).to(cond.device)
        steps = self.inference_timesteps(num_inference_steps)
        ab = self.alphas_cumprod.to(cond.dtype)
        for i, t in enumerate(steps):
            ab_t = ab[t]
            ab_prev = ab[steps[i + 1]] if i + 1 < len(steps) else torch.ones_like(ab_t)
            t_in = torch.full((B, 1), float(t), device=cond.device, dtype=cond.dtype)
            eps = self.score_network(torch.cat([x, cond, t_in], -1))  # (B, D)
            x0 = ((x - (1 - ab_t).sqrt() * eps) / ab_t.sqrt()).clamp(-1.0, 1.0)
            x = ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps
        return x  # the last step has ab_prev = 1: x = x0, inside [-1, 1]
