"""Fit every tokenizer a policy needs on one demonstration buffer (or several, for a multi-task model).

Used by ``mmada-rl fit-tokenizers`` and by the pretraining recipe (which fits
them first when no fitted tokenizers are given).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from mmada_rl.data.windows import append_state_differences, check_state_differences, pad_state
from mmada_rl.keys import ACTION_KEY, IMAGE_KEY, STATE_KEY
from mmada_rl.tokenizers.action_bins import UniformBinActionTokenizer, UniformBinActionTokenizerConfig
from mmada_rl.tokenizers.action_fsq import FSQActionTokenizer, FSQActionTokenizerConfig
from mmada_rl.tokenizers.action_vq import VQActionTokenizer, VQActionTokenizerConfig
from mmada_rl.tokenizers.fit import FitResult, fit_action_tokenizer, fit_image_tokenizer
from mmada_rl.tokenizers.image import VQImageTokenizer, VQImageTokenizerConfig
from mmada_rl.tokenizers.bundle import Tokenizers
from mmada_rl.tokenizers.text import TextTokenizer, TextTokenizerConfig

#: action tokenizer kinds: the paper's EMA codebook and the two baselines
ACTION_TOKENIZERS = {
    "vq": (VQActionTokenizer, VQActionTokenizerConfig),
    "bins": (UniformBinActionTokenizer, UniformBinActionTokenizerConfig),
    "fsq": (FSQActionTokenizer, FSQActionTokenizerConfig),
}


@dataclass
class TokenizerFitConfig:
    """What to fit and how long.

    Attributes:
        action_type: ``"vq"`` (residual EMA codebook), ``"bins"`` (256 uniform bins) or ``"fsq"``.
        action: fields of that tokenizer's config (``action_dim`` is taken from the buffer).
        action_steps: optimisation steps of the action tokenizer (ignored for bins).
        image: fields of :class:`VQImageTokenizerConfig` (``image_size`` from the buffer).
        image_steps, image_batch_size: VQ-VAE training length.
        text_max_len: instruction length in tokens.
        proprio_bins: bins per state dimension for proprioception tokens (0: none).
        state_differences: pairs ``[a, b]`` whose difference ``state[a] - state[b]`` is appended
            to the state before the proprio tokenizer is fitted (the policy's
            ``MMaDAConfig.state_differences``, which must be the same).
        seed: seeds every fit.
    """

    action_type: str = "vq"
    action: dict = field(default_factory=dict)
    action_steps: int = 2000
    image: dict = field(default_factory=dict)
    image_steps: int = 2000
    image_batch_size: int = 32
    text_max_len: int = 16
    proprio_bins: int = 256
    state_differences: list = field(default_factory=list)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.action_type not in ACTION_TOKENIZERS:
            raise ValueError(f"action_type must be one of {sorted(ACTION_TOKENIZERS)}, got {self.action_type!r}.")
        if self.proprio_bins == 1 or self.proprio_bins < 0:
            raise ValueError(f"proprio_bins must be 0 (no proprio tokens) or >= 2, got {self.proprio_bins}.")
        self.state_differences = check_state_differences(self.state_differences)
        if self.state_differences and not self.proprio_bins:
            raise ValueError(f"state_differences={self.state_differences} need proprio tokens (proprio_bins > 0).")


@dataclass
class FittedTokenizers:
    """Tokenizers fitted on a buffer, with their training results."""

    text: TextTokenizer
    image: VQImageTokenizer
    action: torch.nn.Module
    proprio: UniformBinActionTokenizer | None
    fits: dict[str, FitResult] = field(default_factory=dict)

    @property
    def tokenizers(self) -> Tokenizers:
        return Tokenizers(self.text, self.image, self.action, self.proprio)

    def save(self, directory: str | Path) -> Path:
        return self.tokenizers.save(directory)

    @classmethod
    def load(cls, directory: str | Path) -> FittedTokenizers:
        return cls(*Tokenizers.load(directory))


def make_action_tokenizer(kind: str, action_dim: int, **fields) -> torch.nn.Module:
    """An unfitted action tokenizer of ``kind`` for ``action_dim``-dimensional actions."""
    if kind not in ACTION_TOKENIZERS:
        raise ValueError(f"action tokenizer must be one of {sorted(ACTION_TOKENIZERS)}, got {kind!r}.")
    cls, config_cls = ACTION_TOKENIZERS[kind]
    return cls(config_cls(action_dim=action_dim, **fields))


def buffer_arrays(buffer) -> dict[str, torch.Tensor]:
    """Actions, states and images of every stored transition (images only for RGB buffers)."""
    data = buffer.storage[: len(buffer)]
    out = {"action": data.get(ACTION_KEY).clone(), "state": data.get(STATE_KEY).clone()}
    if buffer.metadata.obs_mode == "rgb":
        out["image"] = data.get(IMAGE_KEY).clone()
    return out


def union_arrays(buffers) -> dict[str, torch.Tensor]:
    """:func:`buffer_arrays` of several buffers, concatenated; states are zero-padded to the largest state size.

    Raises:
        ValueError: the buffers differ in action size, control mode, observation mode or image size.
    """
    first = buffers[0].metadata
    for b in buffers[1:]:
        m = b.metadata
        for name in ("action_dim", "control_mode", "obs_mode", "image_size"):
            if getattr(m, name) != getattr(first, name):
                raise ValueError(f"buffers {buffers[0].path} and {b.path} differ in {name} "
                                 f"({getattr(first, name)!r} vs {getattr(m, name)!r}); one model needs them equal.")
    arrays = [buffer_arrays(b) for b in buffers]
    state_dim = max(a["state"].shape[-1] for a in arrays)
    out = {key: torch.cat([a[key] for a in arrays]) for key in arrays[0] if key != "state"}
    out["state"] = torch.cat([pad_state(a["state"], state_dim) for a in arrays])
    return out


def fit_tokenizers(buffers, cfg: TokenizerFitConfig | None = None, *, progress: bool = True) -> FittedTokenizers:
    """Fit text, image, action (and proprio) tokenizers on the transitions of one buffer or of several
    (a multi-task model: every task's instructions, frames, actions and zero-padded states)."""
    cfg = cfg or TokenizerFitConfig()
    buffers = [buffers] if hasattr(buffers, "metadata") else list(buffers)
    for b in buffers:
        if b.metadata.obs_mode != "rgb":
            raise ValueError(f"buffer {b.path} has no images (obs_mode={b.metadata.obs_mode!r}); the policy needs an RGB buffer.")
    meta = buffers[0].metadata
    arrays = union_arrays(buffers)
    instructions = [text for b in buffers for text in b.metadata.instructions]
    text = TextTokenizer(TextTokenizerConfig(max_len=cfg.text_max_len)).fit(instructions)
    image = VQImageTokenizer(VQImageTokenizerConfig(**{"image_size": meta.image_size, **cfg.image}))
    fits = {"image": fit_image_tokenizer(image, arrays["image"], steps=cfg.image_steps, batch_size=cfg.image_batch_size,
                                         seed=cfg.seed, progress=progress)}
    action = make_action_tokenizer(cfg.action_type, meta.action_dim, **cfg.action)
    fits["action"] = fit_action_tokenizer(action, arrays["action"], steps=cfg.action_steps, seed=cfg.seed, progress=progress)
    proprio = None
    if cfg.proprio_bins:
        proprio = fit_proprio_tokenizer(arrays["state"], cfg.proprio_bins, cfg.state_differences)
    return FittedTokenizers(text, image, action, proprio, fits)


def fit_proprio_tokenizer(states: torch.Tensor, num_bins: int = 256, state_differences=()) -> UniformBinActionTokenizer:
    """``num_bins`` uniform bins per dimension of ``states`` ``[N, D]`` with ``state_differences`` appended,
    each over its full data range (nothing seen in training is clipped)."""
    states = append_state_differences(states, state_differences)
    proprio = UniformBinActionTokenizer(
        UniformBinActionTokenizerConfig(action_dim=states.shape[-1], gripper_dims=(), num_bins=num_bins,
                                        low_quantile=0.0, high_quantile=1.0)
    )
    fit_action_tokenizer(proprio, states, progress=False)
    return proprio


def config_dict(cfg: TokenizerFitConfig) -> dict:
    return asdict(cfg)

