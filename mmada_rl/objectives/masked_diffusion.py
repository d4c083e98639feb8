"""Masked-diffusion denoising loss (the pretraining / imitation objective)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey

from torchrl.objectives.common import LossModule

from mmada_rl.diffusion.denoiser import MaskedDiffusionDenoiser, make_denoiser_module
from mmada_rl.diffusion.forward_process import NoiseKernel, check_probability, corrupt, make_kernel
from mmada_rl.diffusion.keys import CORRUPTED_KEY, NOISY_SEQUENCE_KEY, VISUAL_FEATURES_KEY
from mmada_rl.diffusion.schedules import NoiseSchedule, make_noise_schedule
from mmada_rl.keys import ACTION_GRIPPER_ONLY_KEY, ACTION_IS_PAD_KEY, NOISE_LEVEL_KEY, SEQUENCE_KEY
from mmada_rl.tokenizers.layout import SEGMENTS

__all__ = ["MaskedDiffusionLoss", "ScoredPositions", "gaussian_bin_targets"]

ACTION_SEGMENT, GOAL_SEGMENT = SEGMENTS.index("action"), SEGMENTS.index("goal")


def gaussian_bin_targets(num_ids: int, sigma: float) -> torch.Tensor:
    """``[n, n]``: row ``c`` is the mass of ``N(c, sigma^2)`` on each id's interval ``[i - 1/2, i + 1/2]``,
    renormalised over the ``n`` ids (HL-Gauss soft targets of ordered bins)."""
    edges = torch.arange(num_ids + 1, dtype=torch.float64) - 0.5  # (n + 1,)
    centres = torch.arange(num_ids, dtype=torch.float64)[:, None]  # (n, 1)
    cdf = torch.special.ndtr((edges[None, :] - centres) / sigma)  # (n, n + 1)
    mass = cdf[:, 1:] - cdf[:, :-1]
    return (mass / mass.sum(-1, keepdim=True)).float()


class ScoredPositions(NamedTuple):
    """The ``M`` scored positions of a batch of ``B`` samples, each corrupted ``C`` times
    (``corruptions_per_sample``; :meth:`MaskedDiffusionLoss.score`)."""

    rows: torch.Tensor  # (M,) row of the corrupted batch (B * C rows: sample b's corruptions are rows b*C .. b*C+C-1)
    sample: torch.Tensor  # (M,) sample index (rows // C)
    cols: torch.Tensor  # (M,) sequence position
    logits: torch.Tensor  # (M, V)
    targets: torch.Tensor  # (M,) clean ids
    ce: torch.Tensor  # (M,) cross-entropy of the clean id (of its soft target: action ids with action_label_sigma)
    segment: torch.Tensor  # (M,) segment id (SEGMENTS order)
    noisy: torch.Tensor  # (B * C, L) the denoiser's input
    noise_level: torch.Tensor  # (B * C,)
    visual: torch.Tensor | None  # the denoiser's visual input (features or images; B * C rows), if any
    num_scored: torch.Tensor  # () M
    batch: int  # B


class MaskedDiffusionLoss(LossModule):
    """Cross-entropy of the clean tokens at the corrupted positions.

    The loss owns the forward process: it reads the clean sequence, corrupts
    it (schedule + kernel), runs the denoiser and scores only the corrupted
    positions, so a training loop feeds it replay-buffer samples unchanged.
    If the input already carries a corruption (``noisy_sequence``,
    ``corrupted`` and ``noise_level`` entries, e.g. written by :meth:`corrupt`
    once to evaluate on a fixed corruption), that one is scored instead.

    Action and goal tokens are averaged separately, each over its own
    corrupted positions, then weighted, so that the ``L_g`` image tokens do
    not outweigh the ``K · d_tok`` action tokens unless asked to.

    Args:
        denoiser: a :class:`~mmada_rl.diffusion.MaskedDiffusionDenoiser` or the
            ``TensorDictModule`` from :func:`~mmada_rl.diffusion.make_denoiser_module`.

    Keyword Args:
        schedule: noise schedule (name or object); the paper's ``"uniform"`` by default.
        kernel: ``"absorbing"`` (default) or ``"uniform"``.
        action_weight: weight of ``loss_action``.
        goal_weight: weight of ``loss_goal`` (0 without goal tokens).
        condition_mask_prob: also corrupt this fraction of the conditioning
            tokens (multimodal pretraining objective), scored as ``loss_condition``.
        proprio_drop_prob: corrupt a sample's whole proprio segment with this
            probability (state dropout, :func:`~mmada_rl.diffusion.corrupt`),
            scored as ``loss_condition``.
        proprio_drop_index: the tokens of the proprio segment state dropout
            masks (indices into the segment, e.g. from
            :meth:`~mmada_rl.policy.MMaDAModel.proprio_segment_index`); None: all.
        condition_weight: weight of ``loss_condition``.
        corruptions_per_sample: corrupt each sample this many times, each at
            its own noise level, and score them all (a given corruption in the
            input is scored once, as given).
        cache_condition: with a block-causal denoiser and clean conditioning,
            run the conditioning once per sample
            (:meth:`~mmada_rl.diffusion.MaskedDiffusionDenoiser.cache_condition`)
            and the targets of each corruption against it: the same logits and
            gradients as full passes, at a fraction of the cost when
            ``corruptions_per_sample > 1``. Other denoisers run full passes.
        action_label_sigma: > 0 scores each action token against a Gaussian
            over the neighbouring ids instead of the one clean id (HL-Gauss:
            Imani & White, 2018; Farebrother et al., 2024, "Stop Regressing"):
            the mass of ``N(c, sigma^2)`` on each id's interval ``[i - 1/2,
            i + 1/2]`` around the clean id ``c``, renormalised over the action
            range; ``sigma`` in ids (0.75 in that paper). Only for ordered
            action ids, one id per bin (:class:`~mmada_rl.tokenizers.UniformBinActionTokenizer`):
            a near miss then costs less than a far one. 0 (default): plain
            cross-entropy.
        action_mean_weight: > 0 adds ``loss_action_mean``, this weight times the
            L1 error between each scored action token's expected bin centre (its
            predicted distribution's mean over the action range, the value the mean
            read-out executes) and the clean bin's centre, in the bins' normalised
            units ([-1, 1] over the range), averaged over the scored action tokens:
            the ordered loss BC's regression head trains, on the read-out the policy
            acts with. Only for ordered action ids, one id per bin, as
            ``action_label_sigma``. 0 (default): off.

    Returns (from ``forward``) a TensorDict with ``loss_action``, ``loss_goal``
    (``loss_condition`` when the forward process corrupts conditioning tokens,
    ``loss_action_mean`` when ``action_mean_weight > 0``), plus detached
    diagnostics ``action_accuracy``, ``goal_accuracy`` (with goal tokens),
    ``noise_level`` (mean ρ) and ``num_scored`` (scored positions).

    Padded chunk steps (``action_is_pad``, ``[B, K]``) and samples flagged
    invalid by TorchRL's loss masks (:attr:`loss_mask_key`) are not scored. Of a
    sample flagged ``action_gripper_only`` (``[B]``, a window starting in the hold after a
    grasp) only the last token of each action, the gripper's, is scored among its action
    tokens (one token per action entry, as ordered-bin tokenizers give).

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> from mmada_rl.diffusion import DenoiserConfig, MaskedDiffusionDenoiser
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> loss_fn = MaskedDiffusionLoss(MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny"), layout))
        >>> clean = layout.assemble(torch.zeros(8, 4, dtype=torch.long), torch.zeros(8, 4, dtype=torch.long),
        ...                         torch.zeros(8, 4, dtype=torch.long), torch.zeros(8, 2, 3, dtype=torch.long))
        >>> out = loss_fn(TensorDict({SEQUENCE_KEY: clean}, batch_size=[8]))
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            sequence: clean global ids ``[*B, L]``. Defaults to ``SEQUENCE_KEY``.
            noisy_sequence: a given corruption of it ``[*B, L]`` (optional input).
            corrupted: the positions it corrupted, bool ``[*B, L]`` (optional input).
            noise_level: its masking ratio ``[*B]`` (optional input). Defaults to ``NOISE_LEVEL_KEY``.
            visual: visual features ``[*B, N, d_vis]``, or the observation images
                ``[*B, 3, H, W]`` when the denoiser encodes them itself (read with
                cross-attention only).
            action_is_pad: bool ``[*B, K]``, chunk steps past the episode end (optional).
            action_gripper_only: bool ``[*B]``, samples of which only the gripper's action tokens are
                scored (optional). Defaults to ``ACTION_GRIPPER_ONLY_KEY``.
        """

        sequence: NestedKey = SEQUENCE_KEY
        noisy_sequence: NestedKey = NOISY_SEQUENCE_KEY
        corrupted: NestedKey = CORRUPTED_KEY
        noise_level: NestedKey = NOISE_LEVEL_KEY
        visual: NestedKey = VISUAL_FEATURES_KEY
        action_is_pad: NestedKey = ACTION_IS_PAD_KEY
        action_gripper_only: NestedKey = ACTION_GRIPPER_ONLY_KEY

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    denoiser_network: TensorDictModule
    denoiser_network_params: TensorDictParams
    target_denoiser_network_params: TensorDictParams

    def __init__(
        self,
        denoiser: MaskedDiffusionDenoiser | TensorDictModule,
        *,
        schedule: str | NoiseSchedule = "uniform",
        kernel: str | NoiseKernel = "absorbing",
        action_weight: float = 1.0,
        goal_weight: float = 1.0,
        condition_mask_prob: float = 0.0,
        condition_weight: float = 1.0,
        proprio_drop_prob: float = 0.0,
        proprio_drop_index: Sequence[int] | torch.Tensor | None = None,
        corruptions_per_sample: int = 1,
        cache_condition: bool = True,
        action_label_sigma: float = 0.0,
        action_mean_weight: float = 0.0,
    ) -> None:
        for name, value in (("action_weight", action_weight), ("goal_weight", goal_weight),
                            ("condition_weight", condition_weight), ("action_label_sigma", action_label_sigma),
                            ("action_mean_weight", action_mean_weight)):
            if value < 0:
                raise ValueError(f"{name} must be >= 0, got {value!r}.")
        if int(corruptions_per_sample) != corruptions_per_sample or corruptions_per_sample < 1:
            raise ValueError(f"corruptions_per_sample must be a positive integer, got {corruptions_per_sample!r}.")
        check_probability("condition_mask_prob", condition_mask_prob)
        check_probability("proprio_drop_prob", proprio_drop_prob)
        super().__init__()
        if not isinstance(denoiser, TensorDictModule):
            denoiser = make_denoiser_module(denoiser)
        self.layout = denoiser.module.layout
        self.cross_attention = bool(getattr(denoiser.module.config, "cross_attention_to_visual", False))
        self.convert_to_functional(denoiser, "denoiser_network")
        self.schedule = make_noise_schedule(schedule)
        self.kernel = make_kernel(kernel)
        self.action_weight = float(action_weight)
        self.goal_weight = float(goal_weight)
        self.condition_mask_prob = float(condition_mask_prob)
        self.condition_weight = float(condition_weight)
        self.proprio_drop_prob = float(proprio_drop_prob)
        self.proprio_drop_index = self._check_proprio_drop_index(proprio_drop_index)
        self.corruptions_per_sample = int(corruptions_per_sample)
        self.cache_condition = bool(cache_condition)
        self.action_range = self.layout.vocab.range_of("action")
        self.action_mean_weight = float(action_mean_weight)
        num_bins = self.action_range[1] - self.action_range[0]
        device = next(denoiser.parameters()).device  # with the weights, as TorchRL's losses place their buffers
        #: each action id's bin centre in the bins' normalised units, ``[-1, 1]`` over the range (ordered ids)
        self.register_buffer("action_bin_centres", torch.linspace(-1 + 1 / num_bins, 1 - 1 / num_bins, num_bins,
                                                                  device=device), persistent=False)
        #: row ``c``: the soft target of clean action id ``c`` over the action range (None: one-hot); a buffer,
        #: so it moves with the loss module instead of at every step
        self.register_buffer("action_soft_targets", (
            gaussian_bin_targets(num_bins, float(action_label_sigma)).to(device) if action_label_sigma > 0 else None
        ), persistent=False)
        #: each target position's index in ``layout.target_positions``, the order of the cached pass's outputs
        target_index = torch.full((self.layout.length,), -1, dtype=torch.long)
        target_index[self.layout.target_positions] = torch.arange(self.layout.num_targets)
        self.register_buffer("_target_index", target_index.to(device), persistent=False)
        #: Optional RNG of the forward process (None: torch's global RNG).
        self.generator: torch.Generator | None = None

    def _check_proprio_drop_index(self, index) -> torch.Tensor | None:
        """``proprio_drop_index`` as a long tensor, after checking it names distinct proprio tokens."""
        if index is None:
            return None
        index = torch.as_tensor(index, dtype=torch.long).flatten()
        size = self.layout.config.proprio_tokens
        if not size:
            raise ValueError("proprio_drop_index needs proprio tokens in the sequence, but the layout has none.")
        if index.numel() == 0 or index.unique().numel() != index.numel() or not ((index >= 0) & (index < size)).all():
            raise ValueError(f"proprio_drop_index={index.tolist()} must name distinct tokens of the proprio segment, "
                             f"0..{size - 1}.")
        return index

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = [self.tensor_keys.sequence]
        if self.cross_attention:
            keys.append(self.tensor_keys.visual)
        return keys

    @property
    def out_keys(self) -> list[str]:
        keys = ["loss_action", "loss_goal"]
        if self.corrupts_condition:
            keys.append("loss_condition")
        if self.action_mean_weight > 0:
            keys.append("loss_action_mean")
        keys += ["action_accuracy"] + (["goal_accuracy"] if self.layout.has_goal else [])
        return keys + ["noise_level", "num_scored"]

    @property
    def corrupts_condition(self) -> bool:
        """Whether the forward process also corrupts conditioning tokens (then scored as ``loss_condition``)."""
        return self.condition_mask_prob > 0 or self.proprio_drop_prob > 0

    # -- forward process -----------------------------------------------------
    def corrupt(self, tensordict: TensorDictBase, generator: torch.Generator | None = None) -> TensorDictBase:
        """Write a corruption of the clean sequence into ``tensordict`` (noisy ids, mask, noise level)."""
        clean = tensordict.get(self.tensor_keys.sequence)
        flat = clean.reshape(-1, clean.shape[-1])
        out = corrupt(flat, self.layout, self.schedule, self.kernel,
                      generator if generator is not None else self.generator, self.condition_mask_prob,
                      self.proprio_drop_prob, self.proprio_drop_index)
        tensordict.set(self.tensor_keys.noisy_sequence, out.noisy_ids.reshape(clean.shape))
        tensordict.set(self.tensor_keys.corrupted, out.corrupted.reshape(clean.shape))
        tensordict.set(self.tensor_keys.noise_level, out.noise_level.reshape(clean.shape[:-1]))
        return tensordict

    def _sample_valid(self, tensordict: TensorDictBase, batch: int, device: torch.device) -> torch.Tensor:
        """Bool ``[B]``: samples TorchRL's loss masks (``loss_mask_key``) keep."""
        valid = torch.ones(tensordict.batch_size, dtype=torch.bool, device=device)
        for key in self._loss_mask_keys():
            mask = tensordict.get(key, None)
            if mask is not None:
                valid = valid & self._expand_loss_mask(mask.bool().to(device), valid)
        return valid.reshape(batch)

    def _can_cache(self, net, noisy: torch.Tensor, clean: torch.Tensor) -> bool:
        """Whether the conditioning may be computed once per sample: a block-causal denoiser, and a corruption
        that left the conditioning clean (``condition_mask_prob = 0``, no proprio dropped)."""
        if not (self.cache_condition and getattr(net, "supports_condition_cache", False)):
            return False
        condition = net.condition_positions
        return torch.equal(noisy[:, condition], clean[:, condition])

    # -- loss ----------------------------------------------------------------
    def score(self, tensordict: TensorDictBase) -> ScoredPositions:
        """Corrupt (or read the given corruption), run the denoiser, and return the
        logits and cross-entropies of every scored position (what every loss aggregates)."""
        keys, layout = self.tensor_keys, self.layout
        clean = tensordict.get(keys.sequence)
        clean = clean.reshape(-1, clean.shape[-1])  # (B, L)
        batch, device = clean.shape[0], clean.device
        given = tensordict.get(keys.noisy_sequence, None) is not None
        copies = 1 if given else self.corruptions_per_sample  # C
        rows_clean = clean.repeat_interleave(copies, dim=0) if copies > 1 else clean  # (B * C, L)
        if given:
            missing = [k for k in (keys.corrupted, keys.noise_level) if tensordict.get(k, None) is None]
            if missing:
                raise ValueError(
                    f"the input carries {keys.noisy_sequence!r} but not {missing}: a given corruption needs "
                    "noisy ids, corrupted mask and noise level (see MaskedDiffusionLoss.corrupt)."
                )
            noisy = tensordict.get(keys.noisy_sequence).reshape(batch, -1)
            corrupted = tensordict.get(keys.corrupted).reshape(batch, -1).bool()
            noise_level = tensordict.get(keys.noise_level).reshape(batch)
        else:
            noisy, corrupted, noise_level = corrupt(
                rows_clean, layout, self.schedule, self.kernel, self.generator, self.condition_mask_prob,
                self.proprio_drop_prob, self.proprio_drop_index,
            )
        visual = rows_visual = None
        if self.cross_attention:
            visual = self.denoiser_network.module.flat_visual(tensordict.get(keys.visual), batch)  # (B, ...)
            rows_visual = visual.repeat_interleave(copies, dim=0) if copies > 1 else visual  # (B*C, ...)

        scored = corrupted & self._sample_valid(tensordict, batch, device).repeat_interleave(copies)[:, None]  # (B*C, L)
        is_pad = tensordict.get(keys.action_is_pad, None)
        if is_pad is not None:
            pad = is_pad.reshape(batch, -1).bool().repeat_interleave(layout.config.tokens_per_action, dim=1)
            scored[:, layout.action_positions.to(device)] &= ~pad.repeat_interleave(copies, dim=0)
        gripper_only = tensordict.get(keys.action_gripper_only, None)
        if gripper_only is not None:
            per_action = layout.config.tokens_per_action
            if per_action < 2:
                raise ValueError(f"{keys.action_gripper_only!r} scores only the gripper's token of each action, so it "
                                 f"needs one token per action entry; this layout has {per_action} per action.")
            arm = torch.arange(layout.action_positions.numel(), device=device) % per_action != per_action - 1
            rows_only = gripper_only.reshape(batch).bool().to(device).repeat_interleave(copies)  # (B*C,)
            scored[:, layout.action_positions.to(device)] &= ~(rows_only[:, None] & arm)

        rows, cols = scored.nonzero(as_tuple=True)  # (M,), (M,)
        with self.denoiser_network_params.to_module(self.denoiser_network):
            net = self.denoiser_network.module
            if self._can_cache(net, noisy, rows_clean):
                cache = net.cache_condition(clean, visual)  # once per sample, with its gradient
                if copies > 1:
                    cache = cache.repeat_interleave(copies)
                hidden = net.encode_targets(noisy, noise_level, cache)  # (B*C, T, D), in target_positions order
                logits = net.project(hidden[rows, self._target_index[cols]], cols)  # (M, V)
            else:
                hidden = net.encode(noisy, noise_level, rows_visual)  # (B*C, L, D)
                logits = net.project(hidden[rows, cols], cols)  # (M, V)
        logits = logits.float()  # under autocast (optim.precision=bf16) the scores and their softmaxes in float32
        targets = rows_clean[rows, cols]
        segment = layout.segment_ids.to(device)[cols]
        ce = self._cross_entropy(logits, targets, segment == ACTION_SEGMENT)  # (M,)
        return ScoredPositions(
            rows=rows, sample=rows // copies, cols=cols, logits=logits, targets=targets, ce=ce, segment=segment,
            noisy=noisy, noise_level=noise_level, visual=rows_visual, num_scored=scored.sum(), batch=batch,
        )

    def _cross_entropy(self, logits: torch.Tensor, targets: torch.Tensor, is_action: torch.Tensor) -> torch.Tensor:
        """``(M,)`` cross-entropy of each scored position: of the clean id, or for action positions with
        ``action_label_sigma > 0`` of its Gaussian soft target over the action range."""
        ce = F.cross_entropy(logits, targets, reduction="none")
        if self.action_soft_targets is None or not is_action.any():
            return ce
        start, stop = self.action_range
        soft = self.action_soft_targets[targets[is_action] - start]  # (Ma, n_action)
        log_p = F.log_softmax(logits[is_action, start:stop], dim=-1)  # the restricted logits are -inf elsewhere
        return ce.masked_scatter(is_action, -(soft * log_p).sum(-1))

    def action_mean_error(self, logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """``(Ma,)`` L1 error of the expected bin centre of action logits ``(Ma, V)`` against the clean ids'
        centres ``(Ma,)``, in the bins' normalised units (what ``loss_action_mean`` averages)."""
        start, stop = self.action_range
        probs = logits[:, start:stop].softmax(-1)  # the restricted logits are -inf elsewhere
        return (probs @ self.action_bin_centres - self.action_bin_centres[targets - start]).abs()

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        layout = self.layout
        s = self.score(tensordict)
        ce, segment = s.ce, s.segment
        correct = (s.logits.argmax(-1) == s.targets).float()

        out = {}
        groups = {"action": segment == ACTION_SEGMENT, "goal": segment == GOAL_SEGMENT}
        if self.corrupts_condition:
            groups["condition"] = (segment != ACTION_SEGMENT) & (segment != GOAL_SEGMENT)
        weights = {"action": self.action_weight, "goal": self.goal_weight, "condition": self.condition_weight}
        for name, select in groups.items():
            count = select.sum().clamp_min(1)
            out[f"loss_{name}"] = weights[name] * torch.where(select, ce, torch.zeros_like(ce)).sum() / count
            if name != "condition" and (name != "goal" or layout.has_goal):
                out[f"{name}_accuracy"] = (correct * select).sum().detach() / count
        if self.action_mean_weight > 0:
            select = groups["action"]
            error = self.action_mean_error(s.logits[select], s.targets[select])
            out["loss_action_mean"] = self.action_mean_weight * error.sum() / select.sum().clamp_min(1)
        out["noise_level"] = s.noise_level.float().mean().detach()
        out["num_scored"] = s.num_scored.detach().float()
        return TensorDict(out, batch_size=[])
