"""Decoding paths of the parallel sampler and their exact log-probability.

A :class:`DecodingPath` records, for each decoding step, the target tokens the
denoiser saw, the noise level it was given, which positions were committed at
that step, the token chosen there and its log-probability under that step's
(restricted, temperature-scaled) distribution. :func:`path_log_prob` replays the
path with teacher forcing (the same inputs at every step) under the current
parameters, which is what policy-gradient fine-tuning needs: with unchanged
parameters it returns the recorded log-probability.

The log-probability of a path is the sum, over every commit event, of the
log-probability of the committed token. Which positions get committed (the
confidence ranking) is treated as part of the sampling procedure, not scored.
"""
from __future__ import annotations

import torch
from tensordict import tensorclass
from tensordict.nn import TensorDictModuleBase
from torch import nn

__all__ = ["DecodingPath", "path_log_prob", "target_log_probs", "unwrap_denoiser"]


@tensorclass
class DecodingPath:
    """Per-step record of one parallel decoding run (batch ``[B]``, ``N`` steps, ``T`` targets)."""

    #: Long ``[B, L]``: the sequence at the start (conditioning + initial target noise).
    start_ids: torch.Tensor
    #: Long ``[B, N, T]``: target ids the denoiser saw at each step (as ``layout.target_positions``).
    inputs: torch.Tensor
    #: Float ``[B, N]``: noise level (fraction of uncommitted targets) given at each step.
    noise_levels: torch.Tensor
    #: Bool ``[B, N, T]``: positions committed at each step.
    committed: torch.Tensor
    #: Long ``[B, N, T]``: the token committed at each step (the input token elsewhere).
    tokens: torch.Tensor
    #: Float ``[B, N, T]``: log-probability of each committed token (0 elsewhere).
    log_probs: torch.Tensor
    #: Float ``[B]``: token-sampling temperature of the step distributions.
    temperature: torch.Tensor

    @property
    def num_steps(self) -> int:
        return self.inputs.shape[-2]

    @property
    def log_prob(self) -> torch.Tensor:
        """Recorded log-probability of the whole path, float ``[B]``."""
        return self.log_probs.sum(dim=(-2, -1))


def unwrap_denoiser(denoiser: nn.Module) -> nn.Module:
    """The ``nn.Module`` inside a ``TensorDictModule`` (or the module itself).

    A denoiser must have a ``layout`` attribute and be callable as
    ``denoiser(ids, noise_level, visual=None, positions=None) -> logits``.
    """
    module = denoiser.module if isinstance(denoiser, TensorDictModuleBase) and hasattr(denoiser, "module") else denoiser
    if not hasattr(module, "layout"):
        raise ValueError(f"{type(module).__name__} has no `layout`; a denoiser must expose the SequenceLayout it uses.")
    return module


def target_log_probs(
    denoiser: nn.Module,
    ids: torch.Tensor,
    noise_level: torch.Tensor,
    temperature: torch.Tensor | float = 1.0,
    visual: torch.Tensor | None = None,
) -> torch.Tensor:
    """Log-probabilities ``[B, T, V]`` of every target position, restricted to its modality.

    The one function both the sampler and :func:`path_log_prob` call, so that
    recording and replay compute exactly the same distribution.
    """
    layout = denoiser.layout
    positions = layout.target_positions.to(ids.device)  # (T,)
    logits = denoiser(ids, noise_level, visual=visual, positions=positions)  # (B, T, V)
    low, high = layout.logit_bounds()
    low, high = low[positions.cpu()].to(ids.device), high[positions.cpu()].to(ids.device)
    vocab_ids = torch.arange(logits.shape[-1], device=ids.device)
    allowed = (vocab_ids >= low[:, None]) & (vocab_ids < high[:, None])  # (T, V)
    logits = logits.masked_fill(~allowed, float("-inf"))
    temperature = torch.as_tensor(temperature, dtype=logits.dtype, device=ids.device)
    if temperature.ndim:
        temperature = temperature.reshape(-1, 1, 1)
    return torch.log_softmax(logits / temperature, dim=-1)


def path_log_prob(
    denoiser: nn.Module,
    path: DecodingPath,
    visual: torch.Tensor | None = None,
    per_token: bool = False,
) -> torch.Tensor:
    """Log-probability of a recorded path under the denoiser's current parameters.

    All ``N`` steps are replayed in one batched forward pass (batch ``B * N``)
    with the recorded inputs and noise levels. Put the denoiser in ``eval()``
    mode (no dropout) to reproduce the sampler's distribution.

    Args:
        denoiser: the denoiser (or its ``TensorDictModule``) that sampled, or a
            newer version of it.
        path: the recorded path.
        visual: the visual features used while sampling ``[B, N_v, d_vis]``, if any.
        per_token: return the per-step, per-target log-probabilities ``[B, N, T]``
            (0 where nothing was committed) instead of their sum ``[B]``.
    """
    net = unwrap_denoiser(denoiser)
    batch, steps, num_targets = path.inputs.shape
    positions = net.layout.target_positions.to(path.inputs.device)
    ids = path.start_ids[:, None, :].expand(batch, steps, -1).clone()  # (B, N, L)
    ids[:, :, positions] = path.inputs
    if visual is not None:
        visual = visual.repeat_interleave(steps, dim=0)  # (B * N, N_v, d_vis)
    temperature = path.temperature.repeat_interleave(steps)  # (B * N,)
    logp = target_log_probs(
        net, ids.reshape(batch * steps, -1), path.noise_levels.reshape(-1), temperature, visual
    )  # (B * N, T, V)
    chosen = logp.gather(-1, path.tokens.reshape(batch * steps, num_targets, 1)).squeeze(-1)
    chosen = torch.where(path.committed.reshape(batch * steps, -1), chosen, torch.zeros_like(chosen))
    chosen = chosen.reshape(batch, steps, num_targets)
    return chosen if per_token else chosen.sum(dim=(-2, -1))
