"""Optional initialisation of the text embeddings from a local HuggingFace checkpoint.

Only the input-embedding matrix is loaded, and only when its width equals the
denoiser's ``d_model``: a small, honest warm start for the text range of the
unified vocabulary (row ``i`` of the checkpoint goes to text id ``i``, so the
text tokenizer must be that checkpoint's tokenizer). ``transformers`` stays an
optional dependency and nothing is ever downloaded.
"""
from __future__ import annotations

import os

import torch
from torch import nn

__all__ = ["load_pretrained_text_embeddings"]


def load_pretrained_text_embeddings(
    embedding: nn.Embedding, text_range: tuple[int, int], path: str
) -> int:
    """Copy a local checkpoint's input embeddings into ``embedding``'s text rows.

    Returns the number of rows copied. Raises FileNotFoundError if ``path`` does
    not exist, ImportError if ``transformers`` is not installed, and ValueError
    if the checkpoint's embedding width differs from ``embedding``'s.
    """
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"DenoiserConfig.pretrained_path={path!r} does not exist; give a local HuggingFace "
            "checkpoint directory (nothing is downloaded) or set pretrained_path=None."
        )
    try:
        import transformers
    except ImportError as err:
        raise ImportError(
            f"DenoiserConfig.pretrained_path={path!r} needs the optional 'transformers' package, "
            "which is not installed; install it or set pretrained_path=None."
        ) from err
    model = transformers.AutoModel.from_pretrained(path, local_files_only=True)
    weight = model.get_input_embeddings().weight.detach().float()  # (V_hf, D_hf)
    width = embedding.weight.shape[1]
    if weight.shape[1] != width:
        raise ValueError(
            f"checkpoint {path!r} has embedding width {weight.shape[1]} but d_model={width}; "
            f"only matching widths are supported: set DenoiserConfig.d_model={weight.shape[1]}."
        )
    start, stop = text_range
    rows = min(weight.shape[0], stop - start)
    with torch.no_grad():
        embedding.weight[start : start + rows] = weight[:rows].to(embedding.weight)
    return rows
