"""The instruction texts of a tensordict, written and read in one way.

TorchRL's VLA schema keeps the instruction at ``language_instruction`` as a
string, or a ``NonTensorStack`` of strings for a batch. Two places write it
(the environment's :class:`~mmada_rl.envs.instruction.InstructionTransform`,
the demonstration buffer's :class:`~mmada_rl.data.buffer.InstructionLookup`)
and two read it (the text tokenizer, the model); the helpers here are what they share.
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import NonTensorData, NonTensorStack

__all__ = ["instruction_entry", "instruction_texts"]


def instruction_entry(
    texts: Sequence[str], ids: Sequence[int], shape: torch.Size, device: torch.device | None = None
) -> NonTensorData | NonTensorStack:
    """``texts[i]`` for each ``i`` of ``ids`` (flat, row-major), as one entry of batch ``shape``.

    One ``NonTensorData`` per distinct text, already on ``device`` (the tensordict's), is shared by
    every element of the stack, so setting the entry converts nothing per element. An empty
    ``shape`` gives the text itself.
    """
    ids = list(ids)
    if len(ids) != shape.numel():
        raise ValueError(f"got {len(ids)} instruction ids for a batch of shape {tuple(shape)}.")
    if not shape:
        return NonTensorData(texts[ids[0]], device=device)
    elements = {i: NonTensorData(texts[i], device=device) for i in set(ids)}
    return NonTensorStack(*[elements[i] for i in ids]).reshape(shape)


def instruction_texts(value, shape: torch.Size) -> list[str]:
    """The texts of an instruction entry (a string, a ``NonTensorData``, a ``NonTensorStack`` or
    nested lists of strings), one per element of batch ``shape`` in row-major order; one text is
    shared by the whole batch."""
    if isinstance(value, NonTensorStack):
        value = value.tolist()
    elif isinstance(value, NonTensorData):
        value = value.data
    texts = _flatten(value)
    n = shape.numel()
    if len(texts) == 1 and n != 1:
        texts = texts * n
    if len(texts) != n:
        raise ValueError(f"got {len(texts)} instructions for a tensordict of batch size {tuple(shape)}.")
    return texts


def _flatten(value) -> list[str]:
    if isinstance(value, str):
        return [value]
    return [text for item in value for text in _flatten(item)]
