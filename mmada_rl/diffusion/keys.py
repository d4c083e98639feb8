"""TensorDict keys of the diffusion components that :mod:`mmada_rl.keys` does not define.

They live in this one module; everything under ``mmada_rl.diffusion`` and
``mmada_rl.objectives`` imports them from here.
"""
from __future__ import annotations

__all__ = ["CORRUPTED_KEY", "LOGITS_KEY", "NOISY_SEQUENCE_KEY", "VISUAL_FEATURES_KEY"]

#: Denoiser logits over the unified vocabulary, float ``[*B, L, V]``.
LOGITS_KEY = ("sequence", "logits")
#: Corrupted sequence fed to the denoiser, long ``[*B, L]``.
NOISY_SEQUENCE_KEY = ("sequence", "noisy_ids")
#: Positions the forward process corrupted (the ones the loss scores), bool ``[*B, L]``.
CORRUPTED_KEY = ("sequence", "corrupted")
#: Visual features the denoiser cross-attends to (when enabled), float ``[*B, N, d_vis]``.
VISUAL_FEATURES_KEY = ("observation", "visual_features")
