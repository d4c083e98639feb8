"""Exponential moving average of a module's weights, with Diffusion Policy's warm-up.

Diffusion Policy (Chi et al., RSS 2023) evaluates and ships an EMA of its
weights, not the weights the optimizer last wrote: the DDPM's samples swing
from one checkpoint to the next without it. :class:`WeightEMA` keeps that
average beside a module, with the decay schedule Diffusion Policy takes from
``diffusers.EMAModel``: after ``n`` updates the decay is
``min(max_decay, 1 - n ** -power)`` (about 0.9967 after 2,000 updates and
0.9985 after 6,000 at ``power=0.75``), and 0 at the first update, so the
average starts as a copy. Floating-point parameters and buffers are averaged;
integer buffers (counters) are copied.

Examples:
    >>> import torch
    >>> policy = torch.nn.Linear(2, 1)
    >>> optimizer = torch.optim.SGD(policy.parameters(), lr=0.1)
    >>> ema = WeightEMA(policy)
    >>> for _ in range(3):
    ...     optimizer.zero_grad(); policy(torch.ones(1, 2)).sum().backward(); optimizer.step()
    ...     ema.update()
    >>> ema.updates, round(ema.decay(), 4)
    (3, 0.5613)
    >>> with ema.applied():           # the policy holds the averaged weights here (evaluate it inside)
    ...     torch.equal(policy.bias.data, ema.shadow["bias"])
    True
    >>> with ema.checkpointed() as extra:   # what a checkpoint saves: the average as the model, the own weights
    ...     sorted(extra)                   # and the update count in ``extra``
    ['ema_updates', 'train_weights']
"""
from __future__ import annotations

from contextlib import AbstractContextManager, contextmanager, nullcontext
from pathlib import Path
from typing import Iterator

import torch

__all__ = ["WeightEMA", "ema_applied", "ema_checkpointed", "load_own_weights", "make_weight_ema", "resume_own_weights"]


class WeightEMA:
    """The moving average of ``module``'s ``state_dict``.

    Args:
        module: the trained module; it is read at each :meth:`update` and
            swapped to the averaged weights inside :meth:`applied`.

    Keyword Args:
        power: warm-up exponent of the decay schedule (Diffusion Policy: 0.75).
        max_decay: upper bound of the decay (Diffusion Policy: 0.9999).

    Attributes:
        updates: number of :meth:`update` calls so far.
    """

    def __init__(self, module: torch.nn.Module, *, power: float = 0.75, max_decay: float = 0.9999) -> None:
        if not power > 0:
            raise ValueError(f"power must be > 0, got {power!r}.")
        if not 0.0 <= max_decay < 1.0:
            raise ValueError(f"max_decay must be in [0, 1), got {max_decay!r}.")
        self.module = module
        self.power = float(power)
        self.max_decay = float(max_decay)
        self.updates = 0
        self.shadow = {name: value.detach().clone() for name, value in module.state_dict().items()}
        self._floats = [name for name, value in self.shadow.items() if value.is_floating_point()]  # averaged
        self._others = [name for name, value in self.shadow.items() if not value.is_floating_point()]  # copied (counters)

    def decay(self, updates: int | None = None) -> float:
        """The decay applied at update number ``updates`` (default: the last one made)."""
        n = self.updates if updates is None else updates
        return 0.0 if n <= 1 else min(self.max_decay, 1.0 - float(n) ** -self.power)

    @torch.no_grad()
    def update(self) -> None:
        """Move the average towards the module's current weights."""
        self.updates += 1
        weight = 1.0 - self.decay()
        current = self.module.state_dict()
        torch._foreach_lerp_([self.shadow[n] for n in self._floats], [current[n].detach() for n in self._floats], weight)
        for name in self._others:
            self.shadow[name].copy_(current[name])

    @contextmanager
    def checkpointed(self) -> Iterator[dict]:
        """Save a checkpoint inside the block: the module holds the average (what a checkpoint's model is: it is
        evaluated and loaded), and the block receives the checkpoint's ``extra`` entries that let training resume,
        the module's own weights and the update count (:meth:`resume_from`)."""
        extra = {"train_weights": {name: value.detach().clone() for name, value in self.module.state_dict().items()},
                 "ema_updates": self.updates}
        with self.applied():
            yield extra

    def resume_from(self, extra: dict) -> None:
        """After loading a checkpoint's model (the average) into the module: keep it as the average, give the module
        its own weights back and continue the update count. Nothing changes when the checkpoint kept no average:
        the average starts from the loaded weights."""
        if "train_weights" not in extra:
            return
        self.shadow = {name: value.detach().clone() for name, value in self.module.state_dict().items()}
        self.module.load_state_dict(extra["train_weights"])
        self.updates = int(extra["ema_updates"])

    @contextmanager
    def applied(self) -> Iterator[torch.nn.Module]:
        """Within the block the module holds the averaged weights; its own come back afterwards, even on error."""
        own = {name: value.detach().clone() for name, value in self.module.state_dict().items()}
        self.module.load_state_dict(self.shadow)
        try:
            yield self.module
        finally:
            self.module.load_state_dict(own)


def make_weight_ema(module: torch.nn.Module, cfg, *, enabled: bool | None = None) -> WeightEMA | None:
    """The recipes' ``ema`` config group (``enabled``, ``power``, ``max_decay``) as a :class:`WeightEMA` of ``module``,
    or ``None`` when it is off: ``enabled`` when given (a recipe's own default for a null ``cfg.enabled``), else
    ``cfg.enabled``."""
    if not (cfg.enabled if enabled is None else enabled):
        return None
    return WeightEMA(module, power=float(cfg.power), max_decay=float(cfg.max_decay))


def ema_applied(ema: WeightEMA | None) -> AbstractContextManager:
    """:meth:`WeightEMA.applied`, or nothing for a run that keeps no average: within the block the module holds
    the weights the run evaluates and saves."""
    return ema.applied() if ema is not None else nullcontext()


def ema_checkpointed(ema: WeightEMA | None) -> AbstractContextManager[dict]:
    """:meth:`WeightEMA.checkpointed`, or an empty ``extra`` for a run that keeps no average."""
    return ema.checkpointed() if ema is not None else nullcontext({})


def resume_own_weights(module: torch.nn.Module, ema: WeightEMA | None, extra: dict) -> None:
    """After a checkpoint's model was loaded into ``module``, give it the weights training continues from: with an
    average kept, :meth:`WeightEMA.resume_from`; without one, the module's own weights when the checkpoint saved them
    (it was written by a run that kept an average), else the loaded weights as they are."""
    if ema is not None:
        ema.resume_from(extra)
    elif "train_weights" in extra:
        module.load_state_dict(extra["train_weights"])


def load_own_weights(module: torch.nn.Module, checkpoint: str | Path) -> None:
    """Load into ``module`` the weights its optimizer last wrote, which a training checkpoint (the directory holding
    ``trainer.pt``) of a run that kept a moving average saved beside it: the checkpoint's model is the average.

    Raises:
        FileNotFoundError: ``checkpoint`` is not a training checkpoint.
        ValueError: the run kept no average (its model is already the weights training left).
    """
    from mmada_rl.training.checkpoint import TRAINER_FILE, load_checkpoint

    checkpoint = Path(checkpoint)
    if not (checkpoint / TRAINER_FILE).is_file():
        raise FileNotFoundError(f"{checkpoint} is no training checkpoint ({TRAINER_FILE} missing): a run's own "
                                "weights beside its moving average are kept in its checkpoints.")
    extra = load_checkpoint(checkpoint).trainer_state.get("extra") or {}
    if "train_weights" not in extra:
        raise ValueError(f"{checkpoint} kept no moving average of its weights (ema.enabled=false): its model is "
                         "already the weights training left.")
    module.load_state_dict(extra["train_weights"])
