"""The forward (corruption) process of masked discrete diffusion.

:func:`corrupt` draws a ratio ``ρ`` per sample from a noise schedule, picks
``round(ρ · L_target)`` target positions (at least one) and replaces them with
the kernel's noise: ``[MASK]`` for the absorbing kernel (the default), or a
uniformly random id from the position's own modality range for D3PM's
uniform-transition kernel.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from mmada_rl.diffusion.schedules import NoiseSchedule, check_probability, make_noise_schedule
from mmada_rl.tokenizers.layout import SequenceLayout

__all__ = [
    "AbsorbingKernel",
    "Corruption",
    "NoiseKernel",
    "UniformKernel",
    "check_probability",
    "corrupt",
    "make_kernel",
]


class NoiseKernel:
    """What a corrupted position becomes: ``noise_like(ids, layout)`` returns noise ids ``[B, L]``."""

    name: str = ""

    def noise_like(
        self, ids: torch.Tensor, layout: SequenceLayout, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class AbsorbingKernel(NoiseKernel):
    """Every corrupted position becomes ``[MASK]``."""

    name = "absorbing"

    def noise_like(self, ids, layout, generator=None):
        return torch.full_like(ids, layout.vocab.mask_id)


class UniformKernel(NoiseKernel):
    """Every corrupted position becomes a uniformly drawn id of its own modality."""

    name = "uniform"

    def noise_like(self, ids, layout, generator=None):
        low, high = layout.logit_bounds()
        low, high = low.to(ids.device), high.to(ids.device)  # (L,)
        u = torch.rand(ids.shape, generator=generator, device=ids.device)  # (B, L)
        noise = low + (u * (high - low)).long()
        return torch.minimum(noise, high - 1)


_KERNELS = {"absorbing": AbsorbingKernel, "uniform": UniformKernel}


def make_kernel(kernel: str | NoiseKernel = "absorbing") -> NoiseKernel:
    """A kernel from its name (``"absorbing"`` or ``"uniform"``), or passed through."""
    if isinstance(kernel, NoiseKernel):
        return kernel
    if kernel not in _KERNELS:
        raise ValueError(f"noise kernel must be one of {sorted(_KERNELS)}, got {kernel!r}.")
    return _KERNELS[kernel]()


class Corruption(NamedTuple):
    """Result of :func:`corrupt`."""

    #: Long ``[B, L]``: the corrupted sequence fed to the denoiser.
    noisy_ids: torch.Tensor
    #: Bool ``[B, L]``: positions that were corrupted (the ones the loss scores).
    corrupted: torch.Tensor
    #: Float ``[B]``: the drawn ratio ``ρ`` (the denoiser's noise-level input).
    noise_level: torch.Tensor


def corrupt(
    ids: torch.Tensor,
    layout: SequenceLayout,
    schedule: str | NoiseSchedule = "uniform",
    kernel: str | NoiseKernel = "absorbing",
    generator: torch.Generator | None = None,
    condition_mask_prob: float = 0.0,
    proprio_drop_prob: float = 0.0,
    proprio_drop_index: torch.Tensor | None = None,
) -> Corruption:
    """Corrupt the target tokens of clean sequences ``ids [B, L]``.

    Args:
        ids: clean global ids ``[B, L]`` laid out by ``layout``.
        layout: the sequence layout (its vocabulary gives ``[MASK]`` and ranges).
        schedule: noise schedule or its name (``"uniform"``, ``"cosine"``).
        kernel: ``"absorbing"`` (default) or ``"uniform"``, or a kernel object.
        generator: optional RNG for reproducible corruption.
        condition_mask_prob: probability with which each conditioning content
            token (text, observation, proprio; never a separator) is also
            corrupted, for the multimodal pretraining objective. 0 keeps the
            conditioning clean.
        proprio_drop_prob: probability with which a sample's whole proprio
            segment is corrupted (state dropout): that sample's targets are
            then predicted from the image and the instruction alone, so a
            policy cannot fit every window by continuing the arm's motion from
            its state and must read the scene from the image. Its proprio
            tokens are scored like other corrupted conditioning. 0: off.
        proprio_drop_index: which tokens of the proprio segment state dropout
            masks (indices into the segment, e.g. the arm's state but not the
            goal position, which the image does not show); None: all of them.

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> clean = layout.assemble(torch.zeros(2, 4, dtype=torch.long), torch.zeros(2, 4, dtype=torch.long),
        ...                         torch.zeros(2, 4, dtype=torch.long), torch.zeros(2, 2, 3, dtype=torch.long))
        >>> out = corrupt(clean, layout)
        >>> bool((out.corrupted & ~layout.is_target).any())
        False
    """
    if ids.ndim != 2 or ids.shape[1] != layout.length:
        raise ValueError(f"ids: expected shape [B, {layout.length}], got {list(ids.shape)}.")
    check_probability("condition_mask_prob", condition_mask_prob)
    check_probability("proprio_drop_prob", proprio_drop_prob)
    schedule = make_noise_schedule(schedule)
    kernel = make_kernel(kernel)
    batch, device = ids.shape[0], ids.device
    targets = layout.target_positions.to(device)  # (T,)
    num_targets = targets.numel()

    rho = schedule.sample(batch, generator=generator, device=device)  # (B,)
    count = (rho * num_targets).round().long().clamp(1, num_targets)  # (B,)
    # Exactly ``count`` positions per sample: the ranks of random scores.
    scores = torch.rand(batch, num_targets, generator=generator, device=device)  # (B, T)
    ranks = scores.argsort(dim=-1).argsort(dim=-1)
    corrupted = torch.zeros_like(ids, dtype=torch.bool)  # (B, L)
    corrupted[:, targets] = ranks < count[:, None]

    if condition_mask_prob > 0:
        content = (layout.is_condition & ~layout.is_separator).to(device)  # (L,)
        draw = torch.rand(ids.shape, generator=generator, device=device) < condition_mask_prob
        corrupted |= draw & content
    if proprio_drop_prob > 0 and layout.config.proprio_tokens:
        drop = torch.rand(batch, generator=generator, device=device) < proprio_drop_prob  # (B,)
        proprio = layout.positions("proprio")
        if proprio_drop_index is not None:
            proprio = proprio[proprio_drop_index.to(proprio.device)]
        corrupted[:, proprio.to(device)] |= drop[:, None]

    noise = kernel.noise_like(ids, layout, generator)
    noisy = torch.where(corrupted, noise, ids)
    return Corruption(noisy_ids=noisy, corrupted=corrupted, noise_level=rho)
