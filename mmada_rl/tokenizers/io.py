"""Saving and loading tokenizers: ``config.json`` + ``model.safetensors`` in one directory.

``config.json`` holds ``"type"`` (the class name), ``"config"`` (the config
dataclass), the TensorDict keys and, for action tokenizers, the normaliser
statistics (readable copy; the weights file is what is loaded). Files are
written to temporary names and renamed, so a directory never holds half a
tokenizer.
"""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

__all__ = ["TokenizerIOMixin", "save_tokenizer", "load_tokenizer", "CONFIG_NAME", "WEIGHTS_NAME"]

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
FORMAT_VERSION = 1


def _tokenizer_types() -> dict[str, tuple[type, type]]:
    # imported here: the tokenizer modules import this one
    from mmada_rl.tokenizers.action_bins import UniformBinActionTokenizer, UniformBinActionTokenizerConfig
    from mmada_rl.tokenizers.action_fsq import FSQActionTokenizer, FSQActionTokenizerConfig
    from mmada_rl.tokenizers.action_vq import VQActionTokenizer, VQActionTokenizerConfig
    from mmada_rl.tokenizers.image import VQImageTokenizer, VQImageTokenizerConfig
    from mmada_rl.tokenizers.text import TextTokenizer, TextTokenizerConfig

    pairs = [
        (VQActionTokenizer, VQActionTokenizerConfig),
        (UniformBinActionTokenizer, UniformBinActionTokenizerConfig),
        (FSQActionTokenizer, FSQActionTokenizerConfig),
        (VQImageTokenizer, VQImageTokenizerConfig),
        (TextTokenizer, TextTokenizerConfig),
    ]
    return {cls.__name__: (cls, config_cls) for cls, config_cls in pairs}


def _key_to_json(key):
    return list(key) if isinstance(key, tuple) else key


def _key_from_json(key):
    return tuple(key) if isinstance(key, list) else key


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    write(tmp)
    os.replace(tmp, path)


def save_tokenizer(tokenizer: torch.nn.Module, directory: str | Path) -> Path:
    """Writes ``tokenizer`` into ``directory`` (created if needed); returns the directory."""
    name = type(tokenizer).__name__
    if name not in _tokenizer_types():
        raise ValueError(f"cannot save a {name}; known tokenizer types: {sorted(_tokenizer_types())}.")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    payload = {
        "type": name,
        "format_version": FORMAT_VERSION,
        "config": dataclasses.asdict(tokenizer.config),
        "in_keys": [_key_to_json(k) for k in tokenizer.in_keys],
        "out_keys": [_key_to_json(k) for k in tokenizer.out_keys],
        **tokenizer.extra_state_json(),
    }
    tensors = {k: v.detach().cpu().contiguous() for k, v in tokenizer.state_dict().items()}
    _atomic_write(directory / WEIGHTS_NAME, lambda p: save_file(tensors, str(p), metadata={"type": name}))
    _atomic_write(directory / CONFIG_NAME, lambda p: p.write_text(json.dumps(payload, indent=2) + "\n"))
    return directory


def load_tokenizer(directory: str | Path, *, device: str | torch.device = "cpu") -> torch.nn.Module:
    """Rebuilds the tokenizer saved in ``directory`` (its class is read from ``config.json``), in eval mode."""
    directory = Path(directory)
    config_path, weights_path = directory / CONFIG_NAME, directory / WEIGHTS_NAME
    for path in (config_path, weights_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found: is {directory} a directory written by tokenizer.save()?")
    payload = json.loads(config_path.read_text())
    types = _tokenizer_types()
    if payload.get("type") not in types:
        raise ValueError(f"{config_path} has type {payload.get('type')!r}; known types: {sorted(types)}.")
    cls, config_cls = types[payload["type"]]
    tokenizer = cls(
        config_cls(**payload["config"]),
        in_keys=[_key_from_json(k) for k in payload["in_keys"]],
        out_keys=[_key_from_json(k) for k in payload["out_keys"]],
    )
    tokenizer.load_state_dict(load_file(str(weights_path)), strict=True)
    return tokenizer.to(device).eval()


class TokenizerIOMixin:
    """``save(directory)`` / ``load(directory)`` for the tokenizers (see :mod:`mmada_rl.tokenizers.io`)."""

    def save(self, directory: str | Path) -> Path:
        """Writes ``config.json`` and ``model.safetensors`` into ``directory``."""
        return save_tokenizer(self, directory)

    @classmethod
    def load(cls, directory: str | Path, *, device: str | torch.device = "cpu"):
        """Loads a tokenizer saved by :meth:`save`; it must be of this class."""
        tokenizer = load_tokenizer(directory, device=device)
        if not isinstance(tokenizer, cls):
            raise ValueError(f"{directory} holds a {type(tokenizer).__name__}, not a {cls.__name__}.")
        return tokenizer

    def extra_state_json(self) -> dict:
        """Extra JSON written beside the config (nothing by default)."""
        return {}
