"""Fitting the tokenizers on plain tensors.

Both fits are deterministic given the tokenizer's initial weights and ``seed``:
batches come from a seeded generator and the global RNG (which
vector-quantize-pytorch's k-means and dead-code sampling draw from) is seeded
inside a forked RNG state, so the caller's random state is left untouched.

Dead-code restarts are counted by wrapping each codebook's ``expire_codes_``
for the duration of the fit (vector-quantize-pytorch exposes no counter): a
restart is a code row that this call rewrote.
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

import torch
from torch import nn
from tqdm.auto import tqdm
from vector_quantize_pytorch.vector_quantize_pytorch import Codebook

from mmada_rl.tokenizers.action import ActionTokenizer, TokenizerLoss
from mmada_rl.tokenizers.image import VQImageTokenizer, median_background

__all__ = ["FitResult", "fit_action_tokenizer", "fit_image_tokenizer", "count_dead_code_restarts"]


@dataclass
class FitResult:
    """What a fit did.

    Attributes:
        losses: total loss per optimisation step.
        reconstruction_losses: reconstruction term per step.
        commitment_losses: commitment term per step (0 for FSQ).
        dead_codes_restarted: total codes restarted during the fit.
        dead_codes_per_codebook: the same per codebook (per residual quantizer).
        steps: optimisation steps run (0 when there is nothing to train).
        seconds: wall time of the optimisation loop.
        seconds_per_step: ``seconds / steps`` (0 when ``steps == 0``).
        cpu_seconds_per_step: process CPU time per step, all threads summed
            (less sensitive than wall time to other jobs on a shared machine).
    """

    losses: list[float] = field(default_factory=list)
    reconstruction_losses: list[float] = field(default_factory=list)
    commitment_losses: list[float] = field(default_factory=list)
    dead_codes_restarted: int = 0
    dead_codes_per_codebook: list[int] = field(default_factory=list)
    steps: int = 0
    seconds: float = 0.0
    seconds_per_step: float = 0.0
    cpu_seconds_per_step: float = 0.0

    def to_dict(self) -> dict:
        """JSON-ready summary (curves included)."""
        return dict(self.__dict__)


@contextlib.contextmanager
def count_dead_code_restarts(module: nn.Module) -> Iterator[list[int]]:
    """Counts dead-code restarts of every vector-quantize-pytorch codebook in ``module``.

    Yields a list with one running count per codebook (in module order).

    Examples:
        >>> from vector_quantize_pytorch import VectorQuantize
        >>> vq = VectorQuantize(dim=4, codebook_size=64, threshold_ema_dead_code=2)
        >>> with count_dead_code_restarts(vq) as counts:
        ...     _ = vq(torch.randn(1, 8, 4))
        >>> counts[0] > 0
        True
    """
    codebooks = [m for m in module.modules() if isinstance(m, Codebook)]
    counts = [0] * len(codebooks)

    def wrap(index: int, codebook: Codebook) -> Callable:
        original = codebook.expire_codes_

        def expire_codes_(*args, **kwargs):
            before = codebook.embed.detach().clone()
            out = original(*args, **kwargs)
            changed = (codebook.embed.detach() != before).flatten(2).any(-1)  # (heads, codes)
            counts[index] += int(changed.sum())
            return out

        return expire_codes_

    for i, codebook in enumerate(codebooks):
        codebook.expire_codes_ = wrap(i, codebook)
    try:
        yield counts
    finally:
        for codebook in codebooks:
            del codebook.expire_codes_  # back to the class method


def _check_loop_args(steps: int, batch_size: int, lr: float) -> None:
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}.")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
    if lr <= 0:
        raise ValueError(f"lr must be > 0, got {lr}.")


def _fit_loop(
    module: nn.Module,
    data: torch.Tensor,
    to_input: Callable[[torch.Tensor], torch.Tensor],
    *,
    steps: int,
    batch_size: int,
    init_size: int,
    lr: float,
    seed: int,
    progress: bool,
    desc: str,
) -> FitResult:
    """Shared loop: k-means / EMA warm-up pass on ``init_size`` samples, then AdamW steps."""
    result = FitResult()
    generator = torch.Generator().manual_seed(seed)
    n = data.shape[0]
    params = [p for p in module.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=lr)
    device = params[0].device
    cuda_devices = list(range(torch.cuda.device_count()))
    with torch.random.fork_rng(devices=cuda_devices), count_dead_code_restarts(module) as counts:
        torch.manual_seed(seed)
        module.train()
        # first pass on a large sample: k-means initialisation of every codebook
        with torch.no_grad():
            first = torch.randperm(n, generator=generator)[: max(init_size, batch_size)]
            module.loss(to_input(data[first].to(device)))
        start, cpu_start = time.perf_counter(), time.process_time()
        bar = tqdm(range(steps), desc=desc, disable=not progress, leave=False)
        for _ in bar:
            batch = to_input(data[torch.randint(0, n, (batch_size,), generator=generator)].to(device))
            loss: TokenizerLoss = module.loss(batch)
            optimizer.zero_grad(set_to_none=True)
            loss.total.backward()
            optimizer.step()
            result.losses.append(loss.total.item())
            result.reconstruction_losses.append(loss.reconstruction.item())
            result.commitment_losses.append(loss.commitment.detach().item())
            bar.set_postfix(loss=f"{result.losses[-1]:.4f}", dead=sum(counts), refresh=False)
        result.seconds = time.perf_counter() - start
        cpu_seconds = time.process_time() - cpu_start
    module.eval()
    result.steps = steps
    result.seconds_per_step = result.seconds / steps if steps else 0.0
    result.cpu_seconds_per_step = cpu_seconds / steps if steps else 0.0
    result.dead_codes_per_codebook = list(counts)
    result.dead_codes_restarted = sum(counts)
    return result


def fit_action_tokenizer(
    tokenizer: ActionTokenizer,
    actions: torch.Tensor,
    *,
    steps: int = 2000,
    batch_size: int = 512,
    lr: float = 1e-3,
    seed: int = 0,
    progress: bool = True,
) -> FitResult:
    """Fits the normaliser on ``actions [N, d_a]`` (env units), then trains the tokenizer.

    The uniform-bin tokenizer has no weights: only its normaliser is fitted and
    the result has ``steps == 0``. Learned tokenizers start with one no-grad pass
    on up to 8192 actions (k-means initialisation of the codebooks), then run
    ``steps`` AdamW steps on random batches. The tokenizer is left in eval mode.
    """
    _check_loop_args(steps, batch_size, lr)
    tokenizer.normalizer.fit(actions)
    if not tokenizer.is_trainable:
        tokenizer.eval()
        return FitResult()
    # clip (and count, and warn about) once for the whole data set
    normed = tokenizer.normalizer.normalize(actions).reshape(-1, tokenizer.action_dim)  # (N, d_a)
    return _fit_loop(
        tokenizer, normed, lambda x: x,
        steps=steps, batch_size=batch_size, init_size=8192, lr=lr, seed=seed,
        progress=progress, desc=f"fit {type(tokenizer).__name__}",
    )  # fmt: skip


def fit_image_tokenizer(
    tokenizer: VQImageTokenizer,
    images: torch.Tensor,
    *,
    steps: int = 2000,
    batch_size: int = 32,
    lr: float = 1e-3,
    seed: int = 0,
    progress: bool = True,
) -> FitResult:
    """Trains the image VQ-VAE on uint8 ``images [N, C, H, W]``.

    With ``config.foreground_weight > 1`` the background (per-pixel median of
    ``images``) is fitted first. A no-grad pass on up to 128 images initialises
    the codebook by k-means; then ``steps`` AdamW steps. The tokenizer is left in
    eval mode.
    """
    _check_loop_args(steps, batch_size, lr)
    images = tokenizer.check_images(images)
    images = images.reshape(-1, *images.shape[-3:])  # (N, C, H, W)
    if tokenizer.config.weights_foreground:
        tokenizer.background.copy_(median_background(images))
    return _fit_loop(
        tokenizer, images, tokenizer.to_float,
        steps=steps, batch_size=batch_size, init_size=128, lr=lr, seed=seed,
        progress=progress, desc="fit VQImageTokenizer",
    )  # fmt: skip
