"""Per-dimension action normalisation fitted on data.

Continuous dimensions are mapped affinely so that their ``low_quantile`` and
``high_quantile`` (default 1st / 99th percentiles) land on -1 and +1, the
convention of OpenVLA and of the MMaDA-VLA code. Gripper dimensions are kept
binary: their sign becomes -1 (close) or +1 (open).

Values outside the *covered range* are clipped to it, and every clip is counted
(:attr:`ActionNormalizer.num_out_of_range`, :attr:`ActionNormalizer.out_of_range_per_dim`)
and reported by an :class:`ActionOutOfRangeWarning` that names how many values
and which dimensions. The covered range is either the quantile range itself
(``clip_to="quantiles"``: normalised ``[-1, 1]``, what a uniform-bin tokenizer
can represent) or the full range seen while fitting (``clip_to="data_range"``:
nothing seen in training is clipped, what a learned codebook should cover).
"""
from __future__ import annotations

import os
import sys
import warnings
from typing import Sequence

import numpy as np
import torch
from torch import nn

__all__ = ["ActionNormalizer", "ActionOutOfRangeWarning", "CLIP_MODES", "check_actions"]

#: Accepted values of ``clip_to``.
CLIP_MODES = ("quantiles", "data_range")
# Smallest quantile range of a continuous dimension; a constant dimension would
# otherwise divide by zero.
_MIN_RANGE = 1e-6


def _caller_stacklevel() -> int:
    """``stacklevel`` of the first frame outside this package and torch's ``no_grad`` wrapper."""
    here, level = os.path.dirname(os.path.abspath(__file__)), 2
    frame = sys._getframe(2)  # the function that will call warnings.warn is level 1
    while frame is not None and (
        os.path.dirname(os.path.abspath(frame.f_code.co_filename)) == here
        or frame.f_code.co_filename.endswith(os.path.join("torch", "utils", "_contextlib.py"))
    ):
        frame, level = frame.f_back, level + 1
    return level


class ActionOutOfRangeWarning(UserWarning):
    """Actions fell outside the range a fitted normaliser covers and were clipped."""


def check_actions(actions: torch.Tensor, action_dim: int) -> torch.Tensor:
    """Returns ``actions`` as float32 after checking their last dimension and finiteness.

    Raises:
        ValueError: wrong trailing dimension, or NaN / inf entries (one message each).
    """
    actions = torch.as_tensor(actions)
    if actions.ndim == 0 or actions.shape[-1] != action_dim:
        raise ValueError(
            f"actions must have shape [..., {action_dim}] (the tokenizer's action_dim), "
            f"got {tuple(actions.shape)}."
        )
    if not actions.is_floating_point():
        actions = actions.float()
    if not torch.isfinite(actions).all():
        bad = (~torch.isfinite(actions)).reshape(-1, action_dim).any(0).nonzero().flatten().tolist()
        raise ValueError(f"actions contain NaN or inf values in dimensions {bad}; clean the data first.")
    return actions.float()


class ActionNormalizer(nn.Module):
    """Maps actions to ``[-1, 1]`` per dimension from statistics fitted on data.

    Args:
        action_dim: number of action dimensions ``d_a``.
        gripper_dims: dimensions kept binary (sign -> -1 / +1).
        low_quantile: quantile mapped to -1 (default 0.01).
        high_quantile: quantile mapped to +1 (default 0.99).
        clip_to: ``"quantiles"`` (clip to normalised [-1, 1]) or ``"data_range"``
            (clip to the min / max seen in :meth:`fit`).

    Examples:
        >>> import torch
        >>> norm = ActionNormalizer(3, gripper_dims=(2,))
        >>> data = torch.cat([torch.linspace(-0.5, 0.5, 101)[:, None].repeat(1, 2),
        ...                   torch.ones(101, 1)], -1)
        >>> norm = norm.fit(data)
        >>> norm.normalize(torch.tensor([[0.49, -0.49, -0.3]]))
        tensor([[ 1., -1., -1.]])
    """

    def __init__(
        self,
        action_dim: int,
        gripper_dims: Sequence[int] = (),
        *,
        low_quantile: float = 0.01,
        high_quantile: float = 0.99,
        clip_to: str = "quantiles",
    ) -> None:
        super().__init__()
        if action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}.")
        bad = [d for d in gripper_dims if not 0 <= d < action_dim]
        if bad:
            raise ValueError(f"gripper_dims {bad} are outside [0, {action_dim}).")
        if not 0.0 <= low_quantile < high_quantile <= 1.0:
            raise ValueError(
                f"need 0 <= low_quantile < high_quantile <= 1, got {low_quantile} and {high_quantile}."
            )
        if clip_to not in CLIP_MODES:
            raise ValueError(f"clip_to must be one of {CLIP_MODES}, got {clip_to!r}.")
        self.action_dim = int(action_dim)
        self.gripper_dims = tuple(int(d) for d in gripper_dims)
        self.low_quantile = float(low_quantile)
        self.high_quantile = float(high_quantile)
        self.clip_to = clip_to
        is_gripper = torch.zeros(action_dim, dtype=torch.bool)
        is_gripper[list(self.gripper_dims)] = True
        self.register_buffer("is_gripper", is_gripper)
        # env units: quantiles mapped to -1 / +1, and the extremes seen in fit
        self.register_buffer("low", -torch.ones(action_dim))
        self.register_buffer("high", torch.ones(action_dim))
        self.register_buffer("data_min", -torch.ones(action_dim))
        self.register_buffer("data_max", torch.ones(action_dim))
        self.register_buffer("fitted", torch.tensor(False))
        # running clip counters (not saved)
        self.register_buffer("out_of_range_per_dim", torch.zeros(action_dim, dtype=torch.long), persistent=False)
        self.num_out_of_range = 0
        self.num_actions_seen = 0

    # -- fitting -------------------------------------------------------------
    @torch.no_grad()
    def fit(self, actions: torch.Tensor) -> ActionNormalizer:
        """Computes the quantiles and extremes of ``actions [..., d_a]``; returns ``self``."""
        actions = check_actions(actions, self.action_dim).reshape(-1, self.action_dim)  # (N, d_a)
        if actions.shape[0] < 2:
            raise ValueError(f"need at least 2 actions to fit a normaliser, got {actions.shape[0]}.")
        # numpy: torch.quantile refuses inputs above 2**24 elements
        data = actions.double().cpu().numpy()
        low = torch.from_numpy(np.quantile(data, self.low_quantile, axis=0)).float()
        high = torch.from_numpy(np.quantile(data, self.high_quantile, axis=0)).float()
        centre = (low + high) / 2
        half = ((high - low) / 2).clamp_min(_MIN_RANGE / 2)
        self.low.copy_(centre - half)
        self.high.copy_(centre + half)
        self.data_min.copy_(actions.min(0).values)
        self.data_max.copy_(actions.max(0).values)
        self.fitted.fill_(True)
        self.reset_out_of_range()
        return self

    def reset_out_of_range(self) -> None:
        """Sets the running clip counters back to zero."""
        self.out_of_range_per_dim.zero_()
        self.num_out_of_range = 0
        self.num_actions_seen = 0

    def _check_fitted(self) -> None:
        if not bool(self.fitted):
            raise RuntimeError("the action normaliser is not fitted; call fit(actions) or fit the tokenizer first.")

    # -- ranges --------------------------------------------------------------
    def covered_range(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The env-unit range ``(low, high)`` that is kept; anything outside is clipped."""
        if self.clip_to == "quantiles":
            return self.low, self.high
        return torch.minimum(self.data_min, self.low), torch.maximum(self.data_max, self.high)

    # -- maps ----------------------------------------------------------------
    def affine(self, actions: torch.Tensor) -> torch.Tensor:
        """Quantile-to-[-1, 1] map without clipping or gripper snapping (for measurements)."""
        self._check_fitted()
        return 2 * (actions - self.low) / (self.high - self.low) - 1

    @torch.no_grad()
    def normalize(self, actions: torch.Tensor) -> torch.Tensor:
        """Env units ``[..., d_a]`` -> normalised units; clips (counting and warning) what is out of range."""
        actions = check_actions(actions, self.action_dim)
        self._check_fitted()
        lo, hi = self.covered_range()
        outside = ((actions < lo) | (actions > hi)) & ~self.is_gripper  # (..., d_a)
        self._count(outside)
        clipped = torch.minimum(torch.maximum(actions, lo), hi)
        normed = self.affine(clipped)
        gripper = torch.where(actions > 0, 1.0, -1.0)
        return torch.where(self.is_gripper, gripper, normed)

    def denormalize(self, normed: torch.Tensor) -> torch.Tensor:
        """Normalised units ``[..., d_a]`` -> env units; gripper dimensions snapped to -1 / +1."""
        self._check_fitted()
        actions = (normed + 1) / 2 * (self.high - self.low) + self.low
        gripper = torch.where(normed > 0, 1.0, -1.0).to(actions.dtype)
        return torch.where(self.is_gripper, gripper, actions)

    def _count(self, outside: torch.Tensor) -> None:
        flat = outside.reshape(-1, self.action_dim)  # (N, d_a)
        self.num_actions_seen += flat.shape[0]
        if not flat.any():
            return
        per_dim = flat.sum(0)
        rows = int(flat.any(-1).sum())
        self.out_of_range_per_dim += per_dim.to(self.out_of_range_per_dim)
        self.num_out_of_range += rows
        dims = {int(d): int(per_dim[d]) for d in per_dim.nonzero().flatten()}
        lo, hi = self.covered_range()
        warnings.warn(
            f"{rows} of {flat.shape[0]} actions ({rows / flat.shape[0]:.2%}) fall outside the fitted "
            f"range ({self.clip_to}) and were clipped to it; out-of-range values per dimension: {dims}; "
            f"covered range low={[round(v, 4) for v in lo.tolist()]}, high={[round(v, 4) for v in hi.tolist()]}. "
            f"Running total: {self.num_out_of_range} actions.",
            ActionOutOfRangeWarning,
            stacklevel=_caller_stacklevel(),
        )

    # -- serialisation -------------------------------------------------------
    def statistics(self) -> dict:
        """The fitted statistics as a JSON-ready dict."""
        return {
            "fitted": bool(self.fitted),
            "low_quantile": self.low_quantile,
            "high_quantile": self.high_quantile,
            "clip_to": self.clip_to,
            "gripper_dims": list(self.gripper_dims),
            "low": self.low.tolist(),
            "high": self.high.tolist(),
            "data_min": self.data_min.tolist(),
            "data_max": self.data_max.tolist(),
        }

    def extra_repr(self) -> str:
        return (
            f"action_dim={self.action_dim}, gripper_dims={self.gripper_dims}, "
            f"quantiles=({self.low_quantile}, {self.high_quantile}), clip_to={self.clip_to!r}"
        )
