"""Training utilities shared by the recipes: checkpoints, schedules, loggers, weight averages."""
from mmada_rl.training.checkpoint import (
    Checkpoint,
    latest_checkpoint,
    load_checkpoint,
    make_logger,
    resume_training,
    save_checkpoint,
)
from mmada_rl.training.collect_ahead import CollectAhead, acting_copy
from mmada_rl.training.collect_process import CollectAheadProcess, CollectorParts, CollectorProcessError
from mmada_rl.training.ema import (
    WeightEMA,
    ema_applied,
    ema_checkpointed,
    load_own_weights,
    make_weight_ema,
    resume_own_weights,
)
from mmada_rl.training.optim import PRECISIONS, autocast, cosine_decay, make_optimizer, make_scheduler, optimizer_step
from mmada_rl.training.run import require_cpu, start_run

__all__ = [
    "PRECISIONS",
    "Checkpoint",
    "CollectAhead",
    "CollectAheadProcess",
    "CollectorParts",
    "CollectorProcessError",
    "WeightEMA",
    "acting_copy",
    "autocast",
    "cosine_decay",
    "ema_applied",
    "ema_checkpointed",
    "latest_checkpoint",
    "load_checkpoint",
    "load_own_weights",
    "make_logger",
    "make_optimizer",
    "make_scheduler",
    "make_weight_ema",
    "optimizer_step",
    "require_cpu",
    "resume_own_weights",
    "resume_training",
    "save_checkpoint",
    "start_run",
]
