"""Noise schedules: how much of the targets is masked.

Training draws a masking ratio ``ρ`` per sample (:class:`UniformNoiseSchedule`,
the paper's ``U[0.5, 0.95]``; :class:`CosineNoiseSchedule`, MaskGIT's
``cos(π t / 2)`` with ``t ~ U(0, 1)`` as in the authors' released code), and
:class:`FullMaskMixture` sets ``ρ = 1`` for a share of the samples, the state a
one-step decoder predicts from (every decoder's first step does too).
Decoding asks the same kind of curve how many targets are still masked after
each step (:func:`masked_counts`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "CosineNoiseSchedule",
    "FullMaskMixture",
    "NoiseSchedule",
    "UniformNoiseSchedule",
    "check_probability",
    "make_noise_schedule",
    "masked_counts",
]


def check_probability(name: str, value: float) -> None:
    """Raise a ``ValueError`` naming ``name`` unless ``value`` lies in ``[0, 1]``."""
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {value!r}.")


class NoiseSchedule:
    """Base class: ``sample(batch_size)`` returns masking ratios ``ρ`` in (0, 1], float ``[B]``."""

    name: str = ""

    def sample(
        self, batch_size: int, *, generator: torch.Generator | None = None, device: torch.device | str | None = None
    ) -> torch.Tensor:
        raise NotImplementedError

    @property
    def support(self) -> tuple[float, float]:
        """``(min, max)`` of the ratios this schedule can draw."""
        raise NotImplementedError


@dataclass
class UniformNoiseSchedule(NoiseSchedule):
    """``ρ ~ U[low, high]`` per sample (the paper's ``[0.5, 0.95]`` by default).

    Examples:
        >>> rho = UniformNoiseSchedule().sample(4)
        >>> bool(((rho >= 0.5) & (rho <= 0.95)).all())
        True
    """

    low: float = 0.5
    high: float = 0.95
    name = "uniform"

    def __post_init__(self) -> None:
        if not 0.0 < self.low <= self.high <= 1.0:
            raise ValueError(f"need 0 < low <= high <= 1, got low={self.low!r}, high={self.high!r}.")

    def sample(self, batch_size, *, generator=None, device=None):
        u = torch.rand(batch_size, generator=generator, device=device)
        return self.low + (self.high - self.low) * u

    @property
    def support(self) -> tuple[float, float]:
        return (self.low, self.high)


@dataclass
class CosineNoiseSchedule(NoiseSchedule):
    """``ρ = cos(π t / 2)`` with ``t ~ U(0, 1)`` (MaskGIT), clamped to ``[min_ratio, 1]``.

    Examples:
        >>> rho = CosineNoiseSchedule().sample(4)
        >>> bool(((rho > 0) & (rho <= 1)).all())
        True
    """

    min_ratio: float = 1e-3
    name = "cosine"

    def __post_init__(self) -> None:
        if not 0.0 < self.min_ratio < 1.0:
            raise ValueError(f"min_ratio must lie in (0, 1), got {self.min_ratio!r}.")

    def sample(self, batch_size, *, generator=None, device=None):
        t = torch.rand(batch_size, generator=generator, device=device)
        return torch.cos(0.5 * math.pi * t).clamp(self.min_ratio, 1.0)

    @property
    def support(self) -> tuple[float, float]:
        return (self.min_ratio, 1.0)


@dataclass
class FullMaskMixture(NoiseSchedule):
    """``ρ = 1`` (every target masked) with probability ``prob``, otherwise ``base``'s draw.

    Greedy one-step decoding (``num_denoise_steps=1``, the mean read-out) predicts
    every target from a fully masked chunk, yet the base schedules rarely train
    on that state: under the cosine schedule about 1 window in 9 (0.115 of
    200,000 draws) has every action token of a 51-target sequence masked, the
    rest see some of the chunk's own actions. This mixture trains ``prob`` of the
    windows on the decoder's state and keeps the base schedule for the others.

    Examples:
        >>> rho = FullMaskMixture(CosineNoiseSchedule(), prob=1.0).sample(3)
        >>> rho.tolist()
        [1.0, 1.0, 1.0]
    """

    base: NoiseSchedule
    prob: float = 0.5
    name = "full_mask_mixture"

    def __post_init__(self) -> None:
        if not isinstance(self.base, NoiseSchedule):
            raise TypeError(f"base must be a NoiseSchedule, got {type(self.base).__name__}.")
        check_probability("prob", self.prob)

    def sample(self, batch_size, *, generator=None, device=None):
        rho = self.base.sample(batch_size, generator=generator, device=device)
        full = torch.rand(batch_size, generator=generator, device=device) < self.prob
        return torch.where(full, torch.ones_like(rho), rho)

    @property
    def support(self) -> tuple[float, float]:
        return (1.0, 1.0) if self.prob == 1.0 else (self.base.support[0], 1.0)


_SCHEDULES = {"uniform": UniformNoiseSchedule, "cosine": CosineNoiseSchedule}


def make_noise_schedule(schedule: str | NoiseSchedule = "uniform", **kwargs) -> NoiseSchedule:
    """A schedule from its name (``"uniform"`` or ``"cosine"``) and options, or passed through."""
    if isinstance(schedule, NoiseSchedule):
        if kwargs:
            raise ValueError(f"options {sorted(kwargs)} given with an already-built schedule {schedule!r}.")
        return schedule
    if schedule not in _SCHEDULES:
        raise ValueError(f"noise schedule must be one of {sorted(_SCHEDULES)}, got {schedule!r}.")
    return _SCHEDULES[schedule](**kwargs)


def masked_counts(num_targets: int, num_steps: int, kind: str = "cosine") -> list[int]:
    """Number of targets still masked after each of ``num_steps`` decoding steps.

    ``kind="cosine"``: ``floor(L cos(π/2 · (n+1)/N))``; ``"linear"``:
    ``floor(L (1 - (n+1)/N))``. The counts never increase, at least one target is
    committed per step while any remain, and the last count is 0 (all committed).

    Examples:
        >>> masked_counts(10, 4, "linear")
        [7, 5, 2, 0]
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps!r}.")
    if kind not in ("cosine", "linear"):
        raise ValueError(f"decoding schedule must be 'cosine' or 'linear', got {kind!r}.")
    counts, previous = [], num_targets
    for n in range(num_steps):
        r = (n + 1) / num_steps
        gamma = math.cos(0.5 * math.pi * r) if kind == "cosine" else 1.0 - r
        count = 0 if n == num_steps - 1 else int(math.floor(num_targets * gamma + 1e-9))
        count = max(0, min(count, previous - 1))
        counts.append(count)
        previous = count
    return counts
