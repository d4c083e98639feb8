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

from mmada_rl.diffusion.denoiser import ConditionCache

__all__ = ["DecodingPath", "path_log_prob", "sample_steps", "select_steps", "target_log_probs", "unwrap_denoiser"]


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
    cache: ConditionCache | None = None,
) -> torch.Tensor:
    """Log-probabilities ``[B, T, V]`` of every target position, restricted to its modality.

    The one function both the sampler and :func:`path_log_prob` call, so that
    recording and replay compute exactly the same distribution. With ``cache``
    (a block-causal denoiser's :class:`~mmada_rl.diffusion.denoiser.ConditionCache`
    of these prompts) only the targets are computed and ``visual`` must be None.
    """
    layout = denoiser.layout
    positions = layout.target_positions.to(ids.device)  # (T,)
    if cache is None:
        logits = denoiser(ids, noise_level, visual=visual, positions=positions)  # (B, T, V)
    else:
        logits = denoiser(ids, noise_level, visual=visual, cache=cache)  # (B, T, V)
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
    steps: torch.Tensor | None = None,
    cache_condition: bool = True,
) -> torch.Tensor:
    """Log-probability of a recorded path under the denoiser's current parameters.

    The replayed steps run in one batched forward pass (batch ``B * N``, or
    ``B * S`` with ``steps``) with the recorded inputs and noise levels. Put the
    denoiser in ``eval()`` mode (no dropout) to reproduce the sampler's distribution.

    Args:
        denoiser: the denoiser (or its ``TensorDictModule``) that sampled, or a
            newer version of it.
        path: the recorded path.
        visual: the visual features used while sampling ``[B, N_v, d_vis]``, if any.
        per_token: return the per-step, per-target log-probabilities ``[B, N, T]``
            (0 where nothing was committed) instead of their sum ``[B]``.
        steps: Long ``[B, S]``: replay only these decoding steps of each path
            (``S`` forward passes per path instead of ``N``); the result covers
            those steps only (``[B, S, T]`` with ``per_token``). Each step's
            distribution depends on its recorded inputs alone, so any subset is
            scored exactly.
        cache_condition: with a block-causal denoiser, compute each path's
            conditioning once (with its gradient) and replay only the target
            positions at every step; the same log-probabilities as the full
            forward passes. Ignored with bidirectional attention.
    """
    net = unwrap_denoiser(denoiser)
    inputs, noise_levels, committed, tokens = path.inputs, path.noise_levels, path.committed, path.tokens
    if steps is not None:
        inputs, committed, tokens = (select_steps(x, steps) for x in (inputs, committed, tokens))
        noise_levels = noise_levels.gather(1, steps)
    batch, num_steps, num_targets = inputs.shape
    positions = net.layout.target_positions.to(inputs.device)
    ids = path.start_ids[:, None, :].expand(batch, num_steps, -1).clone()  # (B, S, L)
    ids[:, :, positions] = inputs
    cache = None
    if cache_condition and getattr(net, "supports_condition_cache", False):
        cache = net.cache_condition(path.start_ids, visual).repeat_interleave(num_steps)  # batch B * S
        visual = None
    elif visual is not None:
        visual = visual.repeat_interleave(num_steps, dim=0)  # (B * S, N_v, d_vis)
    temperature = path.temperature.repeat_interleave(num_steps)  # (B * S,)
    logp = target_log_probs(
        net, ids.reshape(batch * num_steps, -1), noise_levels.reshape(-1), temperature, visual, cache
    )  # (B * S, T, V)
    chosen = logp.gather(-1, tokens.reshape(batch * num_steps, num_targets, 1)).squeeze(-1)
    chosen = torch.where(committed.reshape(batch * num_steps, -1), chosen, torch.zeros_like(chosen))
    chosen = chosen.reshape(batch, num_steps, num_targets)
    return chosen if per_token else chosen.sum(dim=(-2, -1))


def select_steps(per_step: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """``per_step[b, steps[b, s]]`` for a per-step record ``[B, N, T]`` and step indices ``[B, S]``."""
    return per_step.gather(1, steps[..., None].expand(-1, -1, per_step.shape[-1]))


def sample_steps(committed: torch.Tensor, num: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``num`` distinct decoding steps per path, uniformly among the steps that committed a token.

    Args:
        committed: Bool ``[B, N, T]`` (a path's ``committed``).
        num: steps per path (``<= N``); a path with fewer committing steps gets
            some that committed nothing, which score 0 and count as invalid.

    Returns Long ``[B, num]``, in increasing order.
    """
    active = committed.any(-1)  # (B, N)
    if not 0 < num <= active.shape[-1]:
        raise ValueError(f"cannot pick {num} of {active.shape[-1]} decoding steps per path.")
    keys = torch.rand(active.shape, generator=generator, device=active.device)
    keys = torch.where(active, keys, keys - 2.0)  # steps that committed something rank first
    return keys.topk(num, dim=-1).indices.sort(dim=-1).values
