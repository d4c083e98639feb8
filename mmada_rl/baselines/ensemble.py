"""Several imitation baselines acting as one: each predicts its chunk, the executed chunk is their average.

The baselines' counterpart of :class:`~mmada_rl.policy.ensemble.MMaDAEnsemble`, so that an
ensemble of MMaDA-VLA policies is compared with an ensemble of BC (or Diffusion Policy)
policies trained alike: each member predicts its chunk from the same observation (its own
encoder and normalisation), and the chunk executed is their mean, the gripper included
(:func:`~mmada_rl.policy.ensemble.average_chunks`). Unlike an MMaDA-VLA policy's gripper, which
its tokenizer keeps at -1 or +1 (so that ensemble sets it by majority), a regressed gripper is
continuous, and snapping it to the members' majority sign closes it early: three BC seeds on
PickCube-v1 succeed in 25 of 50 episodes with the mean, 4 with the majority (grasping in 12;
``docs/results/pretraining.md``, "BC's three seeds as one ensemble"). It is a
:class:`~mmada_rl.baselines.base.ChunkPolicy` itself, so :func:`~mmada_rl.evaluation.evaluate`
runs it unchanged (``mmada-rl eval --checkpoint RUN_A RUN_B RUN_C``); it has no weights of its
own, so it is neither trained nor saved: it is loaded from its members' directories.

    >>> ensemble = ChunkPolicyEnsemble.load(["runs/bc_s0", "runs/bc_s1", "runs/bc_s2"])  # doctest: +SKIP
    >>> ensemble(env.reset())["vla_action", "chunk"]  # doctest: +SKIP
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn

from mmada_rl.baselines.base import ChunkPolicy, ChunkPolicyConfig
from mmada_rl.baselines.normalization import NormalizationStats
from mmada_rl.policy.ensemble import average_chunks, check_members

__all__ = ["ChunkPolicyEnsemble"]


class ChunkPolicyEnsemble(ChunkPolicy):
    """Chunk policies averaged chunk by chunk (see the module docstring).

    Args:
        members: two or more :class:`ChunkPolicy` that act in the same action space from the
            same observations: the same chunk size, action dimension, observation mode, image
            size, state size and camera. Kinds may differ (BC with Diffusion Policy).
        gripper_dims: action dimensions set by the members' majority sign instead of their mean
            (default ``()``: every dimension averaged; see the module docstring).

    Keyword Args:
        execute_steps, generator, **kwargs: as :class:`ChunkPolicy` (``generator`` reaches the
            members' sampling, e.g. a Diffusion Policy's noise).
    """

    kind = "ensemble"

    def __init__(self, members: Sequence[ChunkPolicy], gripper_dims: Sequence[int] = (), **kwargs) -> None:
        members = check_members(members, ChunkPolicy, {
            "chunk size": lambda m: m.config.chunk_size,
            "action dimension": lambda m: m.config.action_dim,
            "observation mode": lambda m: m.config.obs_mode,
            "image size": lambda m: m.config.image_size,
            "state size": lambda m: m.config.state_dim,
            "camera (camera_fov)": lambda m: m.config.camera_fov,
        })  # fmt: skip
        if any(isinstance(m, ChunkPolicyEnsemble) for m in members):
            raise ValueError("ensemble members must be single policies, not ensembles.")
        lead = members[0].config
        bad = [d for d in gripper_dims if not 0 <= d < lead.action_dim]
        if bad:
            raise ValueError(f"gripper_dims {bad} are outside [0, action_dim={lead.action_dim}).")
        super().__init__(lead, **kwargs)
        self.members = nn.ModuleList(members)
        self.gripper_dims = tuple(int(d) for d in gripper_dims)
        self.num_denoise_steps = sum(m.num_denoise_steps for m in members)  # network evaluations per chunk

    @classmethod
    def load(cls, directories: Sequence[str | Path], *, device: str | torch.device = "cpu",
             **kwargs) -> ChunkPolicyEnsemble:
        """The ensemble of the policies saved in ``directories`` (each as :func:`load_policy` takes it)."""
        from mmada_rl.baselines import load_policy  # the package's loader knows every kind

        return cls([load_policy(d, device=device) for d in directories], **kwargs)

    def _build_encoding(self, config: ChunkPolicyConfig, stats: NormalizationStats | None) -> None:
        """None of its own: each member encodes and normalises."""

    def predict_chunk(self, tensordict: TensorDictBase, generator: torch.Generator | None = None) -> torch.Tensor:
        """The members' chunks ``[B, K, A]`` (env units), averaged (:func:`average_chunks`)."""
        chunks = torch.stack([m.predict_chunk(tensordict, generator or m.generator) for m in self.members])
        return average_chunks(chunks, self.gripper_dims)

    def get_new_version(self, **kwargs) -> ChunkPolicyEnsemble:
        if "num_denoise_steps" in kwargs:
            raise ValueError("an ensemble's members keep their own num_denoise_steps; set it on each member "
                             "(get_new_version) before ensembling them.")
        return super().get_new_version(**kwargs)

    def save(self, directory: str | Path) -> Path:
        raise NotImplementedError("an ensemble has no weights of its own: save its members, and load it "
                                  "from their directories (ChunkPolicyEnsemble.load).")
