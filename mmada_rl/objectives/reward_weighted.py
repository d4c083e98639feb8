"""Reward-weighted masked-diffusion fine-tuning of the action tokens (AWR / RWR, wd1-style signed).

The masked-diffusion cross-entropy of the **action tokens** of each sample is
weighted by a function of its advantage; the goal-image tokens keep the plain,
unweighted denoising loss (for online data the goal is the frame actually
observed ``K`` steps later), so the world-model signal keeps learning from
every chunk. Demonstrations ride in the same batch with a fixed weight
(``demo_weight``; ``1``: plain imitation, as RLPD keeps its demos in the mix).

Weightings of the advantage ``A`` (temperature ``beta``):

* ``"exp"`` (AWR/RWR): ``w = min(exp(A / beta), max_weight)``, always positive:
  low-advantage chunks are imitated less, never pushed down.
* ``"binary"`` (CRR's indicator, Wang et al. 2020; with episode returns of a
  sparse success reward this is filtered self-imitation of successful
  rollouts, as rejection-sampling fine-tuning does): ``w = 1[A > 0]``. It has no
  scale to tune and bounds the step size whatever the advantage estimate.
* ``"signed"`` (as wd1 does for masked-diffusion language models):
  ``w = clip(A / beta, -max_weight, max_weight)``; a negative weight lowers the
  likelihood of that chunk's tokens. Its cross-entropy is capped at
  ``max_negative_nll`` so the push-down stops once a token is unlikely
  (otherwise the objective is unbounded below).

An optional penalty ``kl_coef * KL(p_ref || p_theta)`` on the scored action
positions keeps the policy near a frozen reference denoiser (the pretrained one).

``weight_goal=True`` weights each row's goal-image cross-entropy by the same
weight as its actions instead: the sampler generates goal and chunk jointly, so
the predicted goal acts as the plan, and learning the goals of failed rollouts
unweighted can pull the plan toward failure.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey

from mmada_rl.diffusion.denoiser import MaskedDiffusionDenoiser
from mmada_rl.diffusion.path import unwrap_denoiser
from mmada_rl.keys import ADVANTAGE_KEY, IS_DEMO_KEY
from mmada_rl.objectives.masked_diffusion import ACTION_SEGMENT, GOAL_SEGMENT, MaskedDiffusionLoss

__all__ = ["RewardWeightedDiffusionLoss", "advantage_weights"]

WEIGHTINGS = ("exp", "binary", "signed")


def advantage_weights(advantage: torch.Tensor, weighting: str = "exp", temperature: float = 1.0,
                      max_weight: float = 20.0) -> torch.Tensor:
    """Per-sample weights of advantages ``[B]`` (see the module docstring)."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}.")
    scaled = advantage / temperature
    if weighting == "exp":
        return torch.exp(scaled.clamp(max=torch.log(torch.tensor(max_weight)).item()))
    if weighting == "binary":
        return (advantage > 0).to(advantage.dtype)
    return scaled.clamp(-max_weight, max_weight)


class RewardWeightedDiffusionLoss(MaskedDiffusionLoss):
    """Advantage-weighted cross-entropy of the action tokens, plain denoising loss on the goal tokens.

    Reads, besides :class:`MaskedDiffusionLoss`'s keys, ``advantage`` (float
    ``[*B]``, ignored for demonstrations) and ``is_demo`` (bool ``[*B]``,
    optional: all online when absent).

    Args:
        denoiser: the denoiser being fine-tuned (or its ``TensorDictModule``).

    Keyword Args:
        weighting: ``"exp"``, ``"binary"`` or ``"signed"``.
        temperature: ``beta``, the advantage scale.
        max_weight: weight clip (both signs for ``"signed"``).
        max_negative_nll: cap of the cross-entropy pushed up by negative weights.
        demo_weight: weight of demonstration samples.
        normalize_weights: divide the weights by their mean absolute value over the
            batch (keeps the step size independent of the advantage scale).
        standardize_advantage: standardise the online rows' advantages over the batch
            (zero mean, unit std) before weighting, so ``temperature`` is in units of
            the batch's advantage spread rather than of the reward.
        reference: a frozen reference denoiser for the KL penalty (copied, never trained).
        kl_coef: weight of ``loss_kl`` (needs ``reference``).
        weight_goal: weight each row's goal-image cross-entropy like its action
            tokens (default ``False``: the plain, unweighted denoising loss).
        **kwargs: :class:`MaskedDiffusionLoss` options (schedule, kernel, goal_weight, the state
            dropout of ``proprio_drop_prob`` / ``proprio_drop_index``, which here only masks the
            inputs, ...). Its ``action_mean_weight`` scores the demonstrations' rows alone: the
            L1 error of their expected bins, unweighted, as pretraining scored it.

    Returns ``loss_action`` (weighted), ``loss_goal`` (unweighted unless ``weight_goal``), ``loss_kl``
    (when ``kl_coef > 0``), ``loss_action_mean`` (when ``action_mean_weight > 0``) and diagnostics (``weight_mean``, ``weight_max``,
    ``negative_fraction``, ``action_accuracy``, ``noise_level``, ``num_scored``).

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> from mmada_rl.diffusion import DenoiserConfig
        >>> from mmada_rl.keys import SEQUENCE_KEY
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> denoiser = MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny"), layout)
        >>> loss_fn = RewardWeightedDiffusionLoss(denoiser, weighting="signed", standardize_advantage=True)
        >>> ids = layout.assemble(torch.zeros(8, 4, dtype=torch.long), torch.zeros(8, 4, dtype=torch.long),
        ...                       torch.zeros(8, 4, dtype=torch.long), torch.randint(8, (8, 2, 3)))
        >>> is_demo = torch.arange(8) < 4  # four demonstration windows, four online chunks
        >>> td = TensorDict({SEQUENCE_KEY: ids, ADVANTAGE_KEY: torch.randn(8), IS_DEMO_KEY: is_demo}, batch_size=[8])
        >>> losses = loss_fn(td)
        >>> (losses["loss_action"] + losses["loss_goal"]).backward()
    """

    @dataclass
    class _AcceptedKeys(MaskedDiffusionLoss._AcceptedKeys):
        """:class:`MaskedDiffusionLoss` keys plus ``advantage`` and ``is_demo``."""

        advantage: NestedKey = ADVANTAGE_KEY
        is_demo: NestedKey = IS_DEMO_KEY

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(
        self,
        denoiser: MaskedDiffusionDenoiser | TensorDictModule,
        *,
        weighting: str = "exp",
        temperature: float = 1.0,
        max_weight: float = 20.0,
        max_negative_nll: float = 5.0,
        demo_weight: float = 1.0,
        normalize_weights: bool = False,
        standardize_advantage: bool = False,
        reference: MaskedDiffusionDenoiser | TensorDictModule | None = None,
        kl_coef: float = 0.0,
        weight_goal: bool = False,
        **kwargs,
    ) -> None:
        if weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}.")
        for name, value in (("temperature", temperature), ("max_weight", max_weight), ("max_negative_nll", max_negative_nll)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}.")
        if demo_weight < 0 or kl_coef < 0:
            raise ValueError(f"demo_weight and kl_coef must be >= 0, got {demo_weight!r} and {kl_coef!r}.")
        if kl_coef > 0 and reference is None:
            raise ValueError("kl_coef > 0 needs a reference denoiser (e.g. a copy of the pretrained one).")
        super().__init__(denoiser, **kwargs)
        self.weighting, self.temperature, self.max_weight = weighting, float(temperature), float(max_weight)
        self.max_negative_nll, self.demo_weight = float(max_negative_nll), float(demo_weight)
        self.normalize_weights, self.kl_coef = bool(normalize_weights), float(kl_coef)
        self.standardize_advantage, self.weight_goal = bool(standardize_advantage), bool(weight_goal)
        self.reference = None
        if reference is not None and kl_coef > 0:
            self.reference = copy.deepcopy(unwrap_denoiser(reference)).requires_grad_(False).eval()

    @property
    def in_keys(self) -> list[NestedKey]:
        return [*super().in_keys, self.tensor_keys.advantage, self.tensor_keys.is_demo]

    @property
    def out_keys(self) -> list[str]:
        keys = ["loss_action", "loss_goal"] + (["loss_kl"] if self.kl_coef > 0 else [])
        keys += ["loss_action_mean"] if self.action_mean_weight > 0 else []
        return keys + ["weight_mean", "weight_max", "negative_fraction", "action_accuracy", "noise_level", "num_scored"]

    def demo_rows(self, tensordict: TensorDictBase, batch: int, device: torch.device) -> torch.Tensor:
        """Bool ``[B]``: the demonstration samples (``is_demo``; none when it is absent)."""
        is_demo = tensordict.get(self.tensor_keys.is_demo, None)
        if is_demo is None:
            return torch.zeros(batch, dtype=torch.bool, device=device)
        return is_demo.reshape(batch).bool().to(device)

    def sample_weights(self, tensordict: TensorDictBase, batch: int, device: torch.device) -> torch.Tensor:
        """Float ``[B]``: the advantage weight of each sample (``demo_weight`` for demonstrations)."""
        is_demo = self.demo_rows(tensordict, batch, device)
        advantage = tensordict.get(self.tensor_keys.advantage, None)
        if advantage is None:
            if not is_demo.all():
                raise KeyError(f"online samples need {self.tensor_keys.advantage!r}; only demonstrations may omit it.")
            advantage = torch.zeros(batch, device=device)
        advantage = advantage.reshape(batch).float().to(device)
        online = ~is_demo
        if self.standardize_advantage and online.sum() > 1:
            mean, std = advantage[online].mean(), advantage[online].std().clamp_min(1e-6)
            advantage = torch.where(online, (advantage - mean) / std, advantage)
        weights = advantage_weights(advantage, self.weighting, self.temperature, self.max_weight)
        weights = torch.where(is_demo, torch.full_like(weights, self.demo_weight), weights)
        if self.normalize_weights:
            weights = weights / weights.abs().mean().clamp_min(1e-8)
        return weights

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        s = self.score(tensordict)
        device = s.ce.device
        weights = self.sample_weights(tensordict, s.batch, device)  # (B,)
        is_action, is_goal = s.segment == ACTION_SEGMENT, s.segment == GOAL_SEGMENT

        # per-sample mean cross-entropy over its scored action tokens
        zeros = torch.zeros(s.batch, device=device)
        ce = torch.where(weights[s.sample] < 0, s.ce.clamp(max=self.max_negative_nll), s.ce)
        ce_sum = zeros.index_add(0, s.sample, torch.where(is_action, ce, torch.zeros_like(ce)))  # over all its corruptions
        count = zeros.index_add(0, s.sample, is_action.float())
        has_action = count > 0
        per_sample = ce_sum / count.clamp_min(1)
        loss_action = (weights * per_sample * has_action).sum() / has_action.sum().clamp_min(1)

        goal_count = is_goal.sum().clamp_min(1)
        goal_ce = torch.where(is_goal, s.ce, torch.zeros_like(s.ce))
        if self.weight_goal:  # signed weights push goals down too: cap them as the actions' are
            goal_ce = torch.where(weights[s.sample] < 0, goal_ce.clamp(max=self.max_negative_nll), goal_ce) * weights[s.sample]
        loss_goal = self.goal_weight * goal_ce.sum() / goal_count
        correct = (s.logits.argmax(-1) == s.targets).float()
        out = {
            "loss_action": self.action_weight * loss_action,
            "loss_goal": loss_goal,
        }
        if self.kl_coef > 0:
            out["loss_kl"] = self.kl_coef * self._kl(s, is_action)
        if self.action_mean_weight > 0:  # the demonstrations' expected bins, as pretraining scored them
            select = is_action & self.demo_rows(tensordict, s.batch, device)[s.sample]
            error = self.action_mean_error(s.logits[select], s.targets[select])
            out["loss_action_mean"] = self.action_mean_weight * error.sum() / select.sum().clamp_min(1)
        out.update(
            weight_mean=weights.mean().detach(),
            weight_max=weights.max().detach(),
            negative_fraction=(weights < 0).float().mean().detach(),
            action_accuracy=(correct * is_action).sum().detach() / is_action.sum().clamp_min(1),
            noise_level=s.noise_level.float().mean().detach(),
            num_scored=s.num_scored.detach().float(),
        )
        return TensorDict(out, batch_size=[])

    def _kl(self, s, is_action: torch.Tensor) -> torch.Tensor:
        """Mean ``KL(p_ref || p_theta)`` over the scored action positions."""
        rows, cols = s.rows[is_action], s.cols[is_action]
        if rows.numel() == 0:
            return s.logits.sum() * 0.0
        with torch.no_grad():
            self.reference.to(s.noisy.device)
            ref_hidden = self.reference.encode(s.noisy, s.noise_level, s.visual)
            ref_logp = F.log_softmax(self.reference.project(ref_hidden[rows, cols], cols).float(), -1)
        logp = F.log_softmax(s.logits[is_action], -1)
        finite = torch.isfinite(ref_logp) & torch.isfinite(logp)  # out-of-modality entries are -inf in both
        ref_p = ref_logp.exp()
        terms = torch.where(finite, ref_p * (ref_logp - logp), torch.zeros_like(logp))
        return terms.sum(-1).mean()
