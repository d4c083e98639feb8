"""Checks on the checkpoints the recipes write, shared by their tests."""
from __future__ import annotations

from pathlib import Path

import torch
from safetensors.torch import load_file


def weights(ckpt: Path) -> dict:
    """The denoiser's weights a checkpoint saved as its model."""
    return load_file(str(ckpt / "model" / "denoiser.safetensors"))


def check_average_beside_own_weights(ckpt: Path, plain_ckpt: Path, updates: int) -> tuple[dict, dict]:
    """``ckpt``, written by a run that kept a weight average (``ema.enabled``), saved that average as its model
    and, for resuming, the update count and its own weights, which equal those of ``plain_ckpt``, the same run
    without an average at the same step. Returns the checkpoint's ``extra`` and its model's weights."""
    own = torch.load(ckpt / "trainer.pt", weights_only=False)["extra"]
    assert own["ema_updates"] == updates
    saved, plain = weights(ckpt), weights(plain_ckpt)
    for key in plain:
        torch.testing.assert_close(own["train_weights"][key], plain[key], rtol=1e-5, atol=1e-6)
    moved = [k for k in plain if plain[k].is_floating_point() and not torch.allclose(saved[k], plain[k])]
    assert "token_embedding.weight" in moved
    return own, saved
