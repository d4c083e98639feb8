"""Imitation baselines the MMaDA-VLA policy is compared with, on the same data, keys and evaluation.

* :class:`BCPolicy` — chunked behaviour cloning, trained with TorchRL's ``BCLoss``
  (:func:`make_bc_loss`: chunk target, ``action_is_pad`` mask).
* :class:`DiffusionPolicy` — Gaussian DDPM over the flattened chunk (Chi et al.),
  trained with TorchRL's ``DiffusionBCLoss`` (:class:`ChunkDiffusionBCLoss`).

The reinforcement-learning baselines (PPO, SAC/RLPD, IQL on TorchRL's losses) build
their networks with :mod:`mmada_rl.baselines.rl` (:func:`make_actor`,
:func:`make_qvalue`, :func:`make_value`; :class:`OneStepChunkActor` lets
``evaluate`` run them; :func:`load_rl_actor` rebuilds a checkpoint's actor).

Both are TorchRL ``VLAWrapperBase`` actors writing ``("vla_action", "chunk")``
and ``"action"`` like :class:`~mmada_rl.policy.MMaDAActor`, so
:func:`~mmada_rl.policy.make_policy_env` and :func:`~mmada_rl.evaluation.evaluate`
run them as they are. :func:`make_policy` builds one by name, :func:`load_policy`
rebuilds a saved one, and :class:`ChunkPolicyEnsemble` runs several as one (their chunks
averaged, as :class:`~mmada_rl.policy.MMaDAEnsemble` does for MMaDA-VLA policies).
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from mmada_rl.baselines.base import POLICY_CONFIG, POLICY_WEIGHTS, ChunkPolicy, ChunkPolicyConfig
from mmada_rl.baselines.bc import BCConfig, BCPolicy, NormalizedChunkError, make_bc_loss
from mmada_rl.baselines.diffusion_policy import ChunkDiffusionBCLoss, DiffusionPolicy, DiffusionPolicyConfig
from mmada_rl.baselines.encoders import EncoderConfig, ObservationEncoder, RandomShift, random_shift
from mmada_rl.baselines.ensemble import ChunkPolicyEnsemble
from mmada_rl.baselines.normalization import ChunkNormalizer, NormalizationStats, StateStandardizer
from mmada_rl.baselines.rl import (
    ACTOR_WEIGHTS,
    AGENT_CONFIG,
    AGENT_WEIGHTS,
    ObservationTrunk,
    OneStepChunkActor,
    RLAgent,
    RLNetworkConfig,
    is_rl_agent_dir,
    load_rl_actor,
    make_actor,
    make_qvalue,
    make_value,
    observation_keys,
)

__all__ = [
    "ACTOR_WEIGHTS",
    "AGENT_CONFIG",
    "AGENT_WEIGHTS",
    "ALGOS",
    "BCConfig",
    "BCPolicy",
    "ChunkDiffusionBCLoss",
    "ChunkNormalizer",
    "ChunkPolicy",
    "ChunkPolicyConfig",
    "ChunkPolicyEnsemble",
    "DiffusionPolicy",
    "DiffusionPolicyConfig",
    "EncoderConfig",
    "NormalizationStats",
    "NormalizedChunkError",
    "ObservationEncoder",
    "ObservationTrunk",
    "OneStepChunkActor",
    "POLICY_CONFIG",
    "POLICY_WEIGHTS",
    "RLAgent",
    "RLNetworkConfig",
    "RandomShift",
    "StateStandardizer",
    "is_policy_dir",
    "is_rl_agent_dir",
    "load_policy",
    "load_rl_actor",
    "make_actor",
    "make_bc_loss",
    "make_loss",
    "make_policy",
    "make_qvalue",
    "make_value",
    "observation_keys",
    "random_shift",
]

#: The baselines by name (``policy.json``'s ``kind``, the recipe's ``algo``).
ALGOS: dict[str, type[ChunkPolicy]] = {BCPolicy.kind: BCPolicy, DiffusionPolicy.kind: DiffusionPolicy}


def _policy_class(algo: str) -> type[ChunkPolicy]:
    if algo not in ALGOS:
        raise ValueError(f"unknown baseline {algo!r}; choose one of {sorted(ALGOS)}.")
    return ALGOS[algo]


def make_policy(algo: str, config: dict, stats: NormalizationStats | None = None, **kwargs) -> ChunkPolicy:
    """A new ``algo`` policy (``"bc"`` | ``"diffusion_policy"``) from a config dict and data statistics."""
    cls = _policy_class(algo)
    return cls(cls.config_class(**config), stats, **kwargs)


def make_loss(policy: ChunkPolicy, **kwargs):
    """The TorchRL loss of ``policy``: ``BCLoss`` (:func:`make_bc_loss`) or :class:`ChunkDiffusionBCLoss`."""
    if isinstance(policy, BCPolicy):
        return make_bc_loss(policy, **kwargs)
    if isinstance(policy, DiffusionPolicy):
        return ChunkDiffusionBCLoss(policy, **kwargs)
    raise TypeError(f"no baseline loss for {type(policy).__name__}.")


def is_policy_dir(path: str | Path) -> bool:
    """Whether ``path`` holds a saved baseline policy (``policy.json``)."""
    return (Path(path) / POLICY_CONFIG).is_file()


def load_policy(directory: str | Path, *, device: str | torch.device = "cpu") -> ChunkPolicy:
    """Rebuild the policy saved in ``directory`` by ``ChunkPolicy.save``.

    Examples:
        >>> policy = load_policy("runs/bc_PickCube-v1_s0/checkpoints/step_00005000/model")  # doctest: +SKIP
        >>> type(policy).__name__, policy.chunk_size  # doctest: +SKIP
        ('BCPolicy', 5)
    """
    directory = Path(directory)
    if not is_policy_dir(directory):
        raise FileNotFoundError(f"{directory} holds no baseline policy ({POLICY_CONFIG} missing).")
    payload = json.loads((directory / POLICY_CONFIG).read_text())
    return _policy_class(payload.get("kind")).from_payload(payload, directory, device=device)
