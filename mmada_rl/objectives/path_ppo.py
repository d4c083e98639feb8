"""PPO on the exact log-probability of the parallel decoder's path (denoising as an inner decision process).

Each sampled chunk carries its :class:`~mmada_rl.diffusion.path.DecodingPath`:
which target tokens were committed at which of the ``N`` steps, from which
inputs, with what log-probability. :func:`~mmada_rl.diffusion.path.path_log_prob`
recomputes those log-probabilities under the current parameters, so the
importance ratio of PPO's clipped objective is exact, as DPPO does for Gaussian
diffusion policies and dVLA-RL for discrete ones. The ratio can be taken

* ``"step"`` (default, DPPO): one ratio per denoising step — each step is an
  action of the inner MDP, all sharing the chunk's advantage;
* ``"path"``: one ratio for the whole path (the product of the step ratios;
  high variance with many committed tokens);
* ``"token"``: one ratio per committed token.

Replaying a path costs one denoiser forward pass per decoding step. With
``denoising_steps=S`` each loss call replays ``S`` of the ``N`` steps of every
path, drawn uniformly among the steps that committed a token: the step- and
token-level objectives are means over steps, so this is an unbiased estimate at
``S / N`` of the cost (DPPO likewise fine-tunes a subset of the denoising steps).

The decoder commits goal-image and action tokens along one path, so by default
both enter the ratio (``tokens="all"``). With ``tokens="action"`` only the
committed action tokens are scored: the goal image stays a plan the actions are
conditioned on (their recorded inputs include it) but PPO does not push its
tokens, as reward-weighted fine-tuning leaves the goal tokens to the plain
denoising loss. With a 64-token goal and a 35-token chunk, the goal tokens are
most of each step's ratio otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from mmada_rl.diffusion.denoiser import MaskedDiffusionDenoiser, make_denoiser_module
from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY
from mmada_rl.diffusion.path import path_log_prob, sample_steps, select_steps
from mmada_rl.keys import ADVANTAGE_KEY, VLA_ACTION_KEY

__all__ = ["PathPPOLoss"]

RATIO_LEVELS = ("step", "path", "token")
SCORED_TOKENS = ("all", "action")


class PathPPOLoss(LossModule):
    """Clipped PPO objective on recomputed decoding-path log-probabilities.

    Reads the stored path (``("vla_action", "path")``) and the chunk's advantage
    (``"advantage"``, float ``[*B]``); the behaviour log-probabilities are the
    path's own recorded ones.

    Args:
        denoiser: the denoiser that sampled the paths (being fine-tuned).

    Keyword Args:
        clip_epsilon: PPO's ``epsilon``.
        ratio_level: ``"step"``, ``"path"`` or ``"token"`` (module docstring).
        normalize_advantage: standardise the advantages over the batch.
        denoising_steps: replay this many decoding steps of each path per call
            (drawn afresh each call); ``None``: all of them. Not with ``ratio_level="path"``,
            whose ratio is the product over every step.
        tokens: ``"all"`` (goal-image and action tokens) or ``"action"`` (the action tokens only; module docstring).

    Returns ``loss_objective`` and diagnostics ``clip_fraction``, ``approx_kl``
    (mean of ``old - new`` log-probability per ratio unit) and ``ratio_mean``.
    Keep the denoiser in ``eval()`` mode (no dropout) so that the
    recomputed log-probabilities match the sampler's at unchanged parameters.

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> from mmada_rl.diffusion import DenoiserConfig, MaskedDiffusionSampler, SamplerConfig
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> denoiser = MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny"), layout).eval()
        >>> prompt = layout.assemble(torch.zeros(8, 4, dtype=torch.long), torch.zeros(8, 4, dtype=torch.long))
        >>> sampled = MaskedDiffusionSampler(SamplerConfig(num_steps=4)).sample(denoiser, prompt, greedy=False)
        >>> td = TensorDict({(VLA_ACTION_KEY, "path"): sampled.path, ADVANTAGE_KEY: torch.randn(8)}, batch_size=[8])
        >>> out = PathPPOLoss(denoiser, clip_epsilon=0.2)(td)  # in a collector batch: the actor's stored paths
        >>> round(float(out["ratio_mean"]), 4)  # the parameters have not moved since sampling
        1.0
        >>> out["loss_objective"].backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            path: the stored :class:`DecodingPath` ``[*B]``.
            advantage: the chunk's advantage ``[*B]`` (a trailing singleton dim is accepted).
            visual: the denoiser's visual input while sampling (read with cross-attention
                only): features ``[*B, N, d_vis]``, or the observation images
                ``[*B, 3, H, W]`` when the denoiser encodes them itself.
        """

        path: NestedKey = (VLA_ACTION_KEY, "path")
        advantage: NestedKey = ADVANTAGE_KEY
        visual: NestedKey = VISUAL_FEATURES_KEY

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    denoiser_network: TensorDictModule
    denoiser_network_params: TensorDictParams
    target_denoiser_network_params: TensorDictParams

    def __init__(
        self,
        denoiser: MaskedDiffusionDenoiser | TensorDictModule,
        *,
        clip_epsilon: float = 0.2,
        ratio_level: str = "step",
        normalize_advantage: bool = False,
        denoising_steps: int | None = None,
        tokens: str = "all",
    ) -> None:
        if tokens not in SCORED_TOKENS:
            raise ValueError(f"tokens must be one of {SCORED_TOKENS}, got {tokens!r}.")
        if ratio_level not in RATIO_LEVELS:
            raise ValueError(f"ratio_level must be one of {RATIO_LEVELS}, got {ratio_level!r}.")
        if denoising_steps is not None and (int(denoising_steps) < 1 or ratio_level == "path"):
            raise ValueError(f"denoising_steps={denoising_steps!r}: use a positive number of steps with ratio_level "
                             "'step' or 'token' (the path ratio needs every step), or None for all steps.")
        if not 0 < clip_epsilon < 1:
            raise ValueError(f"clip_epsilon must lie in (0, 1), got {clip_epsilon!r}.")
        super().__init__()
        if not isinstance(denoiser, TensorDictModule):
            denoiser = make_denoiser_module(denoiser)
        self.cross_attention = bool(denoiser.module.config.cross_attention_to_visual)
        self.convert_to_functional(denoiser, "denoiser_network")
        self.clip_epsilon, self.ratio_level = float(clip_epsilon), ratio_level
        self.normalize_advantage = bool(normalize_advantage)
        self.denoising_steps = None if denoising_steps is None else int(denoising_steps)
        layout = denoiser.module.layout
        scored = torch.isin(layout.target_positions, layout.action_positions) if tokens == "action" else \
            torch.ones(layout.target_positions.numel(), dtype=torch.bool)
        device = next(denoiser.parameters()).device  # with the weights, as TorchRL's losses place their buffers
        self.register_buffer("scored_targets", scored.to(device))  # (T,) the target columns that enter the ratio

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = [self.tensor_keys.path, self.tensor_keys.advantage]
        return keys + [self.tensor_keys.visual] if self.cross_attention else keys

    @property
    def out_keys(self) -> list[str]:
        return ["loss_objective", "clip_fraction", "approx_kl", "ratio_mean"]

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        path = tensordict.get(self.tensor_keys.path)
        path = path.reshape(-1)  # (B,)
        advantage = tensordict.get(self.tensor_keys.advantage).reshape(path.shape[0]).float()  # (B,)
        if self.normalize_advantage and advantage.numel() > 1:
            advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(1e-6)
        visual = None
        if self.cross_attention:
            visual = tensordict.get(self.tensor_keys.visual)
            visual = self.denoiser_network.module.flat_visual(visual, path.shape[0])
        committed, steps = path.committed & self.scored_targets, None  # (B, N, T)
        old = torch.where(committed, path.log_probs, torch.zeros_like(path.log_probs))
        if self.denoising_steps is not None and self.denoising_steps < path.num_steps:
            steps = sample_steps(committed, self.denoising_steps)  # (B, S)
            old, committed = select_steps(old, steps), select_steps(committed, steps)
        with self.denoiser_network_params.to_module(self.denoiser_network):
            new = path_log_prob(self.denoiser_network.module, path, visual, per_token=True, steps=steps)  # (B, N|S, T)
        new = torch.where(committed, new, torch.zeros_like(new))  # the scored commits only
        if self.ratio_level == "token":
            log_ratio, valid = new - old, committed
        elif self.ratio_level == "step":
            log_ratio, valid = (new - old).sum(-1), committed.any(-1)  # (B, N)
        else:
            log_ratio, valid = (new - old).sum((-2, -1)), torch.ones_like(advantage, dtype=torch.bool)  # (B,)
        adv = advantage.reshape(-1, *([1] * (log_ratio.ndim - 1))).expand_as(log_ratio)
        ratio = log_ratio.exp()
        clipped = ratio.clamp(1 - self.clip_epsilon, 1 + self.clip_epsilon)
        surrogate = torch.minimum(ratio * adv, clipped * adv)
        count = valid.sum().clamp_min(1)
        loss = -(surrogate * valid).sum() / count
        with torch.no_grad():
            clip_fraction = (((ratio - 1).abs() > self.clip_epsilon) & valid).sum() / count
            approx_kl = (-log_ratio * valid).sum() / count
            ratio_mean = (ratio * valid).sum() / count
        return TensorDict(
            {"loss_objective": loss, "clip_fraction": clip_fraction, "approx_kl": approx_kl, "ratio_mean": ratio_mean},
            batch_size=[],
        )
