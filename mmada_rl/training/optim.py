"""Optimizer, learning-rate schedule (AdamW, linear warm-up, cosine decay) and the gradient step of the recipes."""
from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable, Mapping

import torch

#: What ``autocast`` takes: the precision of a training step's forward pass.
PRECISIONS = ("fp32", "bf16")


def autocast(precision: str, device: str | torch.device = "cpu") -> contextlib.AbstractContextManager:
    """The context a training step's forward pass runs in at ``precision``: ``fp32`` changes nothing; ``bf16``
    is ``torch.autocast`` to bfloat16, so matrix products and convolutions run in bfloat16 while the weights,
    their gradients and the optimizer's state stay float32 (and the ops autocast keeps in float32 stay so).
    On CPUs with AVX512-BF16 (these machines' AMD EPYC) a step of the d = 256 policy takes 0.73× the time
    and one at d = 128 1.07× (benchmarks/results/train_throughput_bf16.md); on GPUs it is the usual mixed
    precision (not measured here)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}.")
    if precision == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)


def make_optimizer(params, *, lr: float, weight_decay: float = 0.01, betas=(0.9, 0.95)) -> torch.optim.AdamW:
    if lr <= 0:
        raise ValueError(f"lr must be > 0, got {lr}.")
    return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, betas=tuple(betas))


def cosine_decay(progress: float, min_lr_ratio: float = 0.1) -> float:
    """The fraction of the base rate at ``progress`` (0 at the start, 1 at the end, clamped) of a cosine decay
    from 1 to ``min_lr_ratio``."""
    if not 0.0 <= min_lr_ratio <= 1.0:
        raise ValueError(f"min_lr_ratio must lie in [0, 1], got {min_lr_ratio!r}.")
    progress = min(1.0, max(0.0, progress))
    return min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def make_scheduler(optimizer, *, warmup_steps: int, total_steps: int, min_lr_ratio: float = 0.1):
    """Linear warm-up to the base rate, then cosine decay to ``min_lr_ratio`` of it at ``total_steps``."""
    if total_steps < 1 or warmup_steps < 0:
        raise ValueError(f"need total_steps >= 1 and warmup_steps >= 0, got {total_steps}, {warmup_steps}.")

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        return cosine_decay((step - warmup_steps) / max(1, total_steps - warmup_steps), min_lr_ratio)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def optimizer_step(losses: Mapping[str, torch.Tensor], params: Iterable[torch.nn.Parameter], optimizer,
                   *, grad_clip: float, scheduler=None, ema=None) -> dict[str, float]:
    """One update from a loss module's output: back-propagate the sum of its ``loss_*`` entries, clip the
    gradient norm of ``params`` to ``grad_clip``, step the optimizer, then the scheduler and the weight
    average (``ema``, a :class:`~mmada_rl.training.ema.WeightEMA`) when given.

    Returns the step's scalars: every entry of ``losses``, ``loss`` (the sum), ``grad_norm`` (before
    clipping), and ``lr`` / ``ema_decay`` with a scheduler / weight average.
    """
    loss = sum(v for k, v in losses.items() if k.startswith("loss_"))
    if not torch.is_tensor(loss):
        raise ValueError(f"no loss_* entry to optimize among {sorted(losses.keys())}.")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(params, float(grad_clip))
    optimizer.step()
    scalars = {k: float(v.detach()) for k, v in losses.items()}
    scalars.update(loss=float(loss.detach()), grad_norm=float(grad_norm))
    if scheduler is not None:
        scheduler.step()
        scalars["lr"] = scheduler.get_last_lr()[0]
    if ema is not None:
        ema.update()
        scalars["ema_decay"] = ema.decay()
    return scalars
