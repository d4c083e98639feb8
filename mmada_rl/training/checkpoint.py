"""Self-describing, atomically written training checkpoints.

A checkpoint is a directory ``run_dir/checkpoints/step_{step:08d}/`` holding

* ``model/`` — the policy as :meth:`MMaDAModel.save` writes it (tokenizers, configs, weights),
* ``trainer.pt`` — step, optimizer, scheduler and every RNG state (torch, numpy,
  python, and named generators such as the replay sampler's),
* ``config.json`` — the full run configuration.

It is written into a temporary directory and renamed into place, so a killed
run never leaves half a checkpoint; ``latest_checkpoint`` finds the newest.
"""
from __future__ import annotations

import json
import random
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

TRAINER_FILE = "trainer.pt"
CONFIG_FILE = "config.json"
MODEL_DIR = "model"


@dataclass
class Checkpoint:
    """A loaded checkpoint."""

    path: Path
    step: int
    trainer_state: dict
    config: dict

    @property
    def model_dir(self) -> Path:
        return self.path / MODEL_DIR


def rng_state(generators: dict[str, torch.Generator] | None = None) -> dict:
    return {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
        "generators": {name: g.get_state() for name, g in (generators or {}).items()},
    }


def restore_rng_state(state: dict, generators: dict[str, torch.Generator] | None = None) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    for name, g in (generators or {}).items():
        if name in state["generators"]:
            g.set_state(state["generators"][name])


def save_checkpoint(run_dir: str | Path, step: int, *, model, optimizer, scheduler=None, config: dict,
                    generators: dict[str, torch.Generator] | None = None, extra: dict | None = None, keep: int = 3) -> Path:
    """Write the checkpoint of ``step`` under ``run_dir/checkpoints`` and keep the newest ``keep``."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"step_{step:08d}"
    tmp = root / f".tmp_step_{step:08d}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    model.save(tmp / MODEL_DIR)
    torch.save(
        {
            "step": step,
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict() if scheduler is not None else None,
            "rng": rng_state(generators),
            "extra": extra or {},
        },
        tmp / TRAINER_FILE,
    )
    (tmp / CONFIG_FILE).write_text(json.dumps(config, indent=2, default=str))
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)
    for old in sorted(root.glob("step_*"))[:-keep] if keep > 0 else []:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint under ``run_dir/checkpoints``, if any."""
    root = Path(run_dir) / "checkpoints"
    found = sorted(p for p in root.glob("step_*") if (p / TRAINER_FILE).exists()) if root.exists() else []
    return found[-1] if found else None


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Load a checkpoint directory (or the newest one inside a run directory)."""
    path = Path(path)
    if not (path / TRAINER_FILE).exists():
        newest = latest_checkpoint(path)
        if newest is None:
            raise FileNotFoundError(f"no checkpoint at {path} (expected {TRAINER_FILE}, or a run directory with checkpoints/).")
        path = newest
    state = torch.load(path / TRAINER_FILE, weights_only=False)
    config = json.loads((path / CONFIG_FILE).read_text()) if (path / CONFIG_FILE).exists() else {}
    return Checkpoint(path, int(state["step"]), state, config)


def resume_training(resume: bool | str | Path | None, run_dir: str | Path, *, load_weights, optimizer, scheduler=None,
                    generators: dict[str, torch.Generator] | None = None, restore_rng: bool = True) -> Checkpoint | None:
    """Restore weights, optimizer, scheduler and RNG states for ``checkpoint.resume``-style settings.

    Args:
        resume: falsy for a fresh run, ``True`` for the newest checkpoint in ``run_dir``, or a checkpoint path.
        load_weights: called with the checkpoint's model directory. It runs before the RNG
            states are restored, so building modules while loading does not shift them.
        restore_rng: ``False`` keeps the RNG states (torch, numpy, python, ``generators``) as this run
            seeded them: the run continues the checkpoint's training with its own draws (batches,
            noise, augmentation), a fork of it rather than its exact continuation.

    Returns:
        the loaded :class:`Checkpoint` (``step`` is the step to continue from), or ``None`` for a fresh run.
    """
    if not resume:
        return None
    path = latest_checkpoint(run_dir) if resume is True else Path(resume)
    if path is None:
        raise FileNotFoundError(f"checkpoint.resume=true but {Path(run_dir) / 'checkpoints'} holds no checkpoint.")
    ckpt = load_checkpoint(path)
    load_weights(ckpt.model_dir)
    optimizer.load_state_dict(ckpt.trainer_state["optimizer"])
    if scheduler is not None and ckpt.trainer_state.get("scheduler") is not None:
        scheduler.load_state_dict(ckpt.trainer_state["scheduler"])
    if restore_rng:
        restore_rng_state(ckpt.trainer_state["rng"], generators)
    return ckpt


def make_logger(backend: str, run_dir: str | Path):
    """A TorchRL logger (``csv``, ``tensorboard``, ``wandb``) writing under ``run_dir/logs``."""
    from torchrl.record.loggers import get_logger

    return get_logger(backend, logger_name=str(run_dir), experiment_name="logs")
