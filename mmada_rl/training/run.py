"""The common start of every training recipe."""
from __future__ import annotations

import warnings
from pathlib import Path

import torch
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from mmada_rl.training.checkpoint import latest_checkpoint

__all__ = ["RunDirGuard", "refuse_occupied_run_dir", "require_cpu", "start_run"]


def refuse_occupied_run_dir(cfg: DictConfig) -> None:
    """Raise ``FileExistsError`` when ``cfg.run_dir`` holds a run's checkpoints and ``checkpoint.resume`` is not
    set: a fresh run there would overwrite them step by step and append its rows to the old run's logs."""
    if cfg.get("checkpoint", {}).get("resume"):
        return
    run_dir = Path(cfg.run_dir)
    newest = latest_checkpoint(run_dir)
    if newest is not None:
        raise FileExistsError(
            f"run_dir={run_dir} already holds a run's checkpoints (newest: {newest.name}); a fresh run there "
            "would overwrite them and append to its logs. Continue that run with checkpoint.resume=true, "
            "or give another run_dir (or remove this one).")


class RunDirGuard(Callback):
    """Hydra callback (``hydra.callbacks`` in each recipe's toy config): refuses an occupied ``run_dir``
    (:func:`refuse_occupied_run_dir`) before Hydra writes its ``.hydra/`` record and log file there, so a
    refused command leaves the earlier run's record of its config as it was."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            refuse_occupied_run_dir(config)
        except FileExistsError as e:
            # Hydra turns a callback's Exception into a warning and goes on; SystemExit stops the command
            # with the message on stderr and exit status 1
            raise SystemExit(f"FileExistsError: {e}") from None


def start_run(cfg: DictConfig) -> tuple[Path, dict]:
    """Set torch's threads (``cfg.num_threads``, 0: torch's default) and seed (``cfg.seed``), create
    ``cfg.run_dir``; return it with the resolved config (what checkpoints store).

    Raises:
        FileExistsError: ``cfg.run_dir`` holds a run's checkpoints and ``checkpoint.resume`` is not set
            (:func:`refuse_occupied_run_dir`; a recipe run from the command line is refused earlier, by
            :class:`RunDirGuard`).

    A fresh run in a ``run_dir`` whose ``logs/`` an earlier run wrote (one stopped before its first checkpoint)
    goes on with a warning: its rows are appended to those logs.
    """
    run_dir = Path(cfg.run_dir)
    refuse_occupied_run_dir(cfg)
    logs = run_dir / "logs"
    if not cfg.get("checkpoint", {}).get("resume") and logs.is_dir() and any(p.is_file() for p in logs.rglob("*")):
        warnings.warn(f"{logs} holds the logs of an earlier run that saved no checkpoint; this run appends its "
                      "rows to them. Remove that folder or give another run_dir for separate logs.", stacklevel=2)
    if cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    torch.manual_seed(int(cfg.seed))
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir, OmegaConf.to_container(cfg, resolve=True)


def require_cpu(cfg: DictConfig, recipe: str) -> None:
    """Raise unless ``cfg.device`` is the CPU: the online recipes collect in CPU simulators and have not
    been run on an accelerator (the pretraining and imitation recipes have; docs/results/measured.md, "On a GPU")."""
    device = torch.device(str(cfg.get("device", "cpu")))
    if device.type != "cpu":
        raise ValueError(f"device={cfg.device}: the {recipe} recipe runs on the CPU only (its collection and "
                         "updates are untested on an accelerator); use device=cpu. Pretraining and the "
                         "imitation baselines take device=cuda.")
