"""Masked discrete diffusion over the unified sequence: forward process, denoiser, sampler.

Keys of these components that :mod:`mmada_rl.keys` lacks are in
:mod:`mmada_rl.diffusion.keys` (``LOGITS_KEY``, ``NOISY_SEQUENCE_KEY``,
``CORRUPTED_KEY``, ``VISUAL_FEATURES_KEY``).
"""
from mmada_rl.diffusion.denoiser import (
    ConditionCache,
    DenoiserConfig,
    MaskedDiffusionDenoiser,
    make_denoiser_module,
)
from mmada_rl.diffusion.forward_process import (
    AbsorbingKernel,
    Corruption,
    NoiseKernel,
    UniformKernel,
    corrupt,
    make_kernel,
)
from mmada_rl.diffusion.keys import CORRUPTED_KEY, LOGITS_KEY, NOISY_SEQUENCE_KEY, VISUAL_FEATURES_KEY
from mmada_rl.diffusion.path import DecodingPath, path_log_prob, sample_steps, target_log_probs
from mmada_rl.diffusion.sampler import MaskedDiffusionSampler, SampleResult, SamplerConfig, is_greedy
from mmada_rl.diffusion.schedules import (
    CosineNoiseSchedule,
    FullMaskMixture,
    NoiseSchedule,
    UniformNoiseSchedule,
    make_noise_schedule,
    masked_counts,
)

__all__ = [
    "CORRUPTED_KEY",
    "LOGITS_KEY",
    "NOISY_SEQUENCE_KEY",
    "VISUAL_FEATURES_KEY",
    "AbsorbingKernel",
    "CosineNoiseSchedule",
    "ConditionCache",
    "Corruption",
    "DecodingPath",
    "DenoiserConfig",
    "FullMaskMixture",
    "MaskedDiffusionDenoiser",
    "MaskedDiffusionSampler",
    "NoiseKernel",
    "NoiseSchedule",
    "SampleResult",
    "SamplerConfig",
    "UniformKernel",
    "UniformNoiseSchedule",
    "corrupt",
    "is_greedy",
    "make_denoiser_module",
    "make_kernel",
    "make_noise_schedule",
    "masked_counts",
    "path_log_prob",
    "sample_steps",
    "target_log_probs",
]
