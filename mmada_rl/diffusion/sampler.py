"""Parallel iterative decoding (MaskGIT-style) of the goal and action tokens.

Start from fully masked targets (or uniformly random in-range ids for the
uniform kernel). Each of the ``N`` steps runs ONE forward pass predicting
every target, draws a candidate token per position (argmax when greedy),
scores its confidence (its log-probability, Gumbel-perturbed with a scale
that decays linearly to 0 over the steps, as MaskGIT anneals its choice
temperature) and keeps the most confident positions so that, after step
``n``, exactly ``masked_counts(T, N)[n]`` targets remain uncommitted; the
last step commits them all. With ``remasking=True`` the already committed
tokens compete too, scored by their log-probability under the current step's
prediction, so a token whose confidence fell below the new candidates is
re-masked and decided again later (low-confidence remasking).

With a block-causal denoiser the conditioning's keys and values are computed
once per chunk and each step runs the target positions alone
(``SamplerConfig.cache_condition``).

Greedy decoding (argmax tokens, no Gumbel noise) is used when
``greedy=True`` or when the interaction type is ``DETERMINISTIC``/``MODE``/``MEAN``
(``torchrl.envs.utils.set_exploration_type``); sampling otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import tensorclass
from tensordict.nn import InteractionType
from tensordict.nn.probabilistic import interaction_type
from torch import nn

from mmada_rl.diffusion.forward_process import make_kernel
from mmada_rl.diffusion.path import DecodingPath, target_log_probs, unwrap_denoiser
from mmada_rl.diffusion.schedules import masked_counts

__all__ = ["MaskedDiffusionSampler", "SampleResult", "SamplerConfig", "is_greedy"]

_GREEDY_TYPES = (InteractionType.DETERMINISTIC, InteractionType.MODE, InteractionType.MEAN)


@dataclass
class SamplerConfig:
    """Options of :class:`MaskedDiffusionSampler`.

    Attributes:
        num_steps: decoding steps ``N`` (one forward pass each).
        schedule: ``"cosine"`` or ``"linear"``: targets still masked after each step.
        temperature: token-sampling temperature (the recorded log-probabilities
            are under this tempered distribution).
        confidence_temperature: scale of the Gumbel noise added to the
            log-confidence at step 0; it decays linearly to 0 at the last step.
        remasking: let committed tokens be re-masked when their confidence falls
            below the newly committed ones. With the absorbing kernel the loss
            never scores visible positions, so a committed token's confidence is
            the model's untrained self-prediction there; it is a trained
            quantity with the uniform kernel.
        kernel: ``"absorbing"`` (start from ``[MASK]``) or ``"uniform"`` (start
            from random in-range ids; uncommitted positions keep their noise).
        cache_condition: with a block-causal denoiser, compute the conditioning
            once per chunk and run only the target positions at each step (the
            same distributions; no effect with bidirectional attention).
    """

    num_steps: int = 10
    schedule: str = "cosine"
    temperature: float = 1.0
    confidence_temperature: float = 1.0
    remasking: bool = False
    kernel: str = "absorbing"
    cache_condition: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.num_steps, int) or self.num_steps < 1:
            raise ValueError(f"num_steps must be a positive int, got {self.num_steps!r}.")
        if self.schedule not in ("cosine", "linear"):
            raise ValueError(f"schedule must be 'cosine' or 'linear', got {self.schedule!r}.")
        if self.temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature!r}.")
        if self.confidence_temperature < 0:
            raise ValueError(f"confidence_temperature must be >= 0, got {self.confidence_temperature!r}.")
        make_kernel(self.kernel)  # validates the name


@tensorclass
class SampleResult:
    """Output of :meth:`MaskedDiffusionSampler.sample` (batch ``[B]``)."""

    #: Long ``[B, L]``: the decoded sequence (global ids).
    ids: torch.Tensor
    #: Long ``[B, T]``: decoded target ids (global), ordered as ``layout.target_positions``.
    target_ids: torch.Tensor
    #: Long ``[B, K, d_tok]``: local action codes.
    action_tokens: torch.Tensor
    #: Long ``[B, L_g]`` (or ``[B, h, w]``) local goal-image codes; None without goal tokens.
    goal_tokens: torch.Tensor | None
    #: The decoding path (for :func:`path_log_prob`).
    path: DecodingPath
    #: Float ``[B, K, d_tok, V_a]``: the distribution over the local action codes each action
    #: token was (last) committed from; only when ``sample(..., action_probs=True)``.
    action_probs: torch.Tensor | None = None


def is_greedy(greedy: bool | None = None) -> bool:
    """``greedy`` if given, else whether the current interaction type is non-random."""
    if greedy is not None:
        return bool(greedy)
    return interaction_type() in _GREEDY_TYPES


def _gumbel(shape, generator, device) -> torch.Tensor:
    u = torch.rand(shape, generator=generator, device=device).clamp_(1e-20, 1.0 - 1e-7)
    return -torch.log(-torch.log(u))


class MaskedDiffusionSampler:
    """Decode the targets of sequences in ``N`` parallel refinement steps.

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> from mmada_rl.diffusion.denoiser import DenoiserConfig, MaskedDiffusionDenoiser
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> net = MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny"), layout).eval()
        >>> prompt = layout.assemble(torch.zeros(2, 4, dtype=torch.long), torch.zeros(2, 4, dtype=torch.long))
        >>> out = MaskedDiffusionSampler(SamplerConfig(num_steps=4)).sample(net, prompt)
        >>> out.action_tokens.shape, out.path.inputs.shape
        (torch.Size([2, 2, 3]), torch.Size([2, 4, 10]))
    """

    def __init__(self, config: SamplerConfig | None = None) -> None:
        self.config = config or SamplerConfig()
        self.kernel = make_kernel(self.config.kernel)

    @torch.no_grad()
    def sample(
        self,
        denoiser: nn.Module,
        ids: torch.Tensor,
        *,
        visual: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        greedy: bool | None = None,
        action_probs: bool = False,
    ) -> SampleResult:
        """Decode the target positions of ``ids [B, L]``; conditioning positions are kept as given.

        Args:
            denoiser: a :class:`MaskedDiffusionDenoiser` (or its ``TensorDictModule``,
                or any module with a ``layout`` and the same call signature).
            ids: sequences whose conditioning positions hold the prompt (e.g.
                ``layout.assemble(text, obs, proprio_ids=...)``); target positions are ignored.
            visual: visual features for cross-attention, if the denoiser uses them.
            generator: RNG for the initial noise, token sampling and Gumbel noise.
            greedy: force greedy (True) or sampled (False) decoding; None follows
                the interaction type.
            action_probs: also return, per action token, the distribution over its
                modality's codes at the step that committed it (``SampleResult.action_probs``;
                a policy reads the expected bin from it, :meth:`MMaDAModel.act`).
        """
        cfg = self.config
        net = unwrap_denoiser(denoiser)
        layout = net.layout
        if ids.ndim != 2 or ids.shape[1] != layout.length:
            raise ValueError(f"ids: expected shape [B, {layout.length}], got {list(ids.shape)}.")
        greedy = is_greedy(greedy)
        batch, device = ids.shape[0], ids.device
        positions = layout.target_positions.to(device)  # (T,)
        num_targets, steps = positions.numel(), cfg.num_steps
        counts = masked_counts(num_targets, steps, cfg.schedule)
        temperature = torch.full((batch,), float(cfg.temperature), device=device)

        x = ids.clone()
        x[:, positions] = self.kernel.noise_like(ids, layout, generator)[:, positions]
        start_ids = x.clone()
        committed = torch.zeros(batch, num_targets, dtype=torch.bool, device=device)  # (B, T)
        record = {
            "inputs": torch.empty(batch, steps, num_targets, dtype=torch.long, device=device),
            "noise_levels": torch.empty(batch, steps, device=device),
            "committed": torch.empty(batch, steps, num_targets, dtype=torch.bool, device=device),
            "tokens": torch.empty(batch, steps, num_targets, dtype=torch.long, device=device),
            "log_probs": torch.empty(batch, steps, num_targets, device=device),
        }
        action_index = layout.action_target_index.to(device)  # (K * d_tok,) among the targets
        action_low, action_high = layout.vocab.range_of("action")
        probs = torch.zeros(batch, action_index.numel(), action_high - action_low, device=device) if action_probs else None
        cache = None
        if cfg.cache_condition and getattr(net, "supports_condition_cache", False):
            cache, visual = net.cache_condition(x, visual), None  # the conditioning, once for all N steps
        for n in range(steps):
            current = x[:, positions]  # (B, T)
            noise_level = (~committed).float().mean(-1)  # (B,)
            logp = target_log_probs(net, x, noise_level, temperature, visual, cache)  # (B, T, V)
            if greedy:
                candidate = logp.argmax(-1)
            else:
                candidate = (logp + _gumbel(logp.shape, generator, device)).argmax(-1)  # Gumbel-max sample
            candidate_logp = logp.gather(-1, candidate[..., None]).squeeze(-1)  # (B, T)
            if cfg.remasking:
                current_logp = logp.gather(-1, current[..., None]).squeeze(-1)
                confidence = torch.where(committed, current_logp, candidate_logp)
            else:
                confidence = torch.where(committed, torch.full_like(candidate_logp, float("inf")), candidate_logp)
            scale = cfg.confidence_temperature * (1.0 - (n + 1) / steps)
            if not greedy and scale > 0:
                confidence = confidence + scale * _gumbel(confidence.shape, generator, device)

            keep = confidence.topk(num_targets - counts[n], dim=-1).indices
            now_committed = torch.zeros_like(committed).scatter_(1, keep, True)
            newly = now_committed & ~committed
            remasked = committed & ~now_committed
            update = torch.where(newly, candidate, current)
            if remasked.any():
                fresh = self.kernel.noise_like(ids, layout, generator)[:, positions]
                update = torch.where(remasked, fresh, update)
            record["inputs"][:, n] = current
            record["noise_levels"][:, n] = noise_level
            record["committed"][:, n] = newly
            record["tokens"][:, n] = torch.where(newly, candidate, current)
            record["log_probs"][:, n] = torch.where(newly, candidate_logp, torch.zeros_like(candidate_logp))
            x[:, positions] = update
            committed = now_committed
            if probs is not None:  # the distribution each action token is committed from (at this step's temperature)
                step_probs = logp[:, action_index, action_low:action_high].exp()  # (B, K * d_tok, V_a)
                probs = torch.where(newly[:, action_index, None], step_probs, probs)

        path = DecodingPath(start_ids=start_ids, temperature=temperature, batch_size=[batch], **record)
        target_ids = x[:, positions]
        parts = layout.split_targets(target_ids)
        return SampleResult(
            ids=x,
            target_ids=target_ids,
            action_tokens=parts["action"],
            goal_tokens=parts.get("goal"),
            path=path,
            action_probs=None if probs is None else probs.reshape(*parts["action"].shape, -1),
            batch_size=[batch],
        )

    __call__ = sample
