"""How well a policy fits demonstration windows: masked-token scores and the error of its predicted chunks.

The pretraining recipe reports these on a held-out buffer while it trains
(``validation.dir``), so overfitting shows as it happens: on PickCube-v1 the
masked-diffusion policy's chunk error on its training windows keeps falling
while the error on unseen demonstrations stops falling and the action
cross-entropy there rises (docs/results/pretraining.md, "Why PickCube-v1 fails").
``benchmarks/demo_fit.py`` reports the same quantities for saved checkpoints.

* :func:`masked_token_scores` — accuracy and cross-entropy of the masked action
  (and goal) tokens with the targets masked at one fixed ratio (1.0: what the
  first of the N decoding steps sees).
* :func:`chunk_error` — the mean absolute error per action dimension of the
  chunks a policy predicts (:func:`predicted_chunks`: an :class:`~mmada_rl.policy.MMaDAModel` decoded
  greedily, or any chunk policy such as the BC baseline, as it acts) against the
  demonstrated chunks, in the environment's action units.

Both take a fixed list of window batches (:func:`fixed_windows`), so that
successive calls, and two checkpoints, are scored on the same windows.
"""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from mmada_rl.data import DemoBuffer, make_window_buffer
from mmada_rl.diffusion.schedules import UniformNoiseSchedule
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_IS_PAD_KEY

__all__ = ["chunk_abs_errors", "chunk_error", "fixed_windows", "masked_token_scores", "predicted_chunks", "validation_metrics"]


def fixed_windows(demos: DemoBuffer | str | Path, chunk_size: int, minibatches: int, batch_size: int,
                  seed: int = 0) -> list[TensorDictBase]:
    """``minibatches`` batches of ``batch_size`` chunk windows of ``demos``, drawn once with ``seed``."""
    if minibatches < 1 or batch_size < 1:
        raise ValueError(f"minibatches and batch_size must be >= 1, got {minibatches} and {batch_size}.")
    demos = demos if isinstance(demos, DemoBuffer) else DemoBuffer.open(demos)
    windows = make_window_buffer(demos, chunk_size, batch_size, seed=seed)
    return [windows.sample() for _ in range(minibatches)]


@torch.no_grad()
def masked_token_scores(model, batches: list[TensorDictBase], ratio: float = 1.0, seed: int = 0) -> dict[str, float]:
    """Mean ``action_accuracy``, ``loss_action`` (cross-entropy) and, with goal tokens, ``goal_accuracy`` and
    ``loss_goal`` of an :class:`~mmada_rl.policy.MMaDAModel` over ``batches``, the targets masked at ``ratio``
    (the same positions for a given ``seed``)."""
    from mmada_rl.objectives import MaskedDiffusionLoss

    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"ratio must lie in (0, 1], got {ratio!r}.")
    loss = MaskedDiffusionLoss(model.denoiser, schedule=UniformNoiseSchedule(ratio, ratio))
    device = next(model.denoiser.parameters()).device
    loss.generator = torch.Generator(device=device).manual_seed(seed)  # the same masks at every call
    totals: dict[str, float] = {}
    for batch in batches:
        out = loss(model.loss_inputs(batch))
        for key in ("action_accuracy", "loss_action", "goal_accuracy", "loss_goal"):
            if key in out.keys():
                totals[key] = totals.get(key, 0.0) + float(out[key]) / len(batches)
    return totals


@torch.no_grad()
def predicted_chunks(policy, batch: TensorDictBase) -> torch.Tensor:
    """The chunks ``[B, K, A]`` ``policy`` predicts for a batch of windows: an :class:`~mmada_rl.policy.MMaDAModel`
    or :class:`~mmada_rl.policy.MMaDAEnsemble` decoded greedily (its own N and read-out), or a chunk policy (BC,
    Diffusion Policy, their ensembles) called on a copy of the batch (it writes its chunk where the window holds
    the demonstrated one)."""
    from mmada_rl.policy import MMaDAEnsemble, MMaDAModel

    if isinstance(policy, (MMaDAModel, MMaDAEnsemble)):
        return policy.act(batch, greedy=True, decode_goal=False).chunk
    return policy(batch.clone()).get(ACTION_CHUNK_KEY)


def chunk_abs_errors(chunk: torch.Tensor, batch: TensorDictBase) -> torch.Tensor:
    """The absolute errors ``[M, A]`` of predicted chunks ``[B, K, A]`` against the windows' demonstrated chunks
    at their ``M`` real (not padded) steps."""
    real = ~batch.get(ACTION_IS_PAD_KEY).bool().to(chunk.device)  # (B, K)
    return (chunk - batch.get(ACTION_CHUNK_KEY).to(chunk)).abs()[real]


@torch.no_grad()
def chunk_error(policy, batches: list[TensorDictBase]) -> list[float]:
    """Mean absolute error per action dimension of ``policy``'s chunks (:func:`predicted_chunks`) against the
    demonstrated ones, padded steps left out (:func:`chunk_abs_errors`)."""
    errors = [chunk_abs_errors(predicted_chunks(policy, batch), batch) for batch in batches]
    return torch.cat(errors).mean(0).tolist()


def validation_metrics(model, batches: list[TensorDictBase], prefix: str = "val/") -> dict[str, float]:
    """The recipe's held-out report of an :class:`~mmada_rl.policy.MMaDAModel`: its masked-token scores with
    every target masked and its greedy chunks' mean absolute error (``chunk_mae``), under ``prefix``. The model
    is scored in eval mode and left in the mode it was in."""
    was_training = model.training
    model.eval()
    try:
        scores = masked_token_scores(model, batches, ratio=1.0)
        mae = chunk_error(model, batches)
    finally:
        model.train(was_training)
    return {f"{prefix}{key}": value for key, value in {**scores, "chunk_mae": sum(mae) / len(mae)}.items()}
