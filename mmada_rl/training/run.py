"""The common start of every training recipe."""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

__all__ = ["start_run"]


def start_run(cfg: DictConfig) -> tuple[Path, dict]:
    """Set torch's threads (``cfg.num_threads``, 0: torch's default) and seed (``cfg.seed``), create
    ``cfg.run_dir``; return it with the resolved config (what checkpoints store)."""
    if cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    torch.manual_seed(int(cfg.seed))
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir, OmegaConf.to_container(cfg, resolve=True)
