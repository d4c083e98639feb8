"""Evaluate a policy on a ManiSkill3 task, and the ``mmada-rl eval`` command.

Any chunk policy runs here: the MMaDA-VLA policy (an :class:`MMaDAModel`, its
:class:`MMaDAActor`, or a directory saved by ``MMaDAModel.save``) and the
imitation baselines of :mod:`mmada_rl.baselines` (a policy object, or a
directory saved by its ``save``), the RL baselines' actors (a checkpoint of
``recipes/baselines/online.py``, run one action per call), or any actor that writes
``("vla_action", "chunk")`` ``[*B, K, A]`` and ``"action"`` ``[*B, k, A]`` and has
``chunk_size``, ``action_dim``, ``execute_steps``, ``get_new_version`` and
``last_decode_seconds`` as :class:`MMaDAActor` does.

Protocol (ManiSkill's): every episode runs to the task's ``max_episode_steps``
with ``ignore_terminations=True`` so that both ``success_once`` (success at any
step) and ``success_at_end`` (success at the last step) are measured; decoding
is greedy (``ExplorationType.DETERMINISTIC``); rates come with 95% Wilson score
intervals. Fine-tuning's two exploration policies can be measured the same way:
tokens sampled at a temperature (``--sample-temperature``) or the greedy chunks
executed with Gaussian noise on the arm's actions (``--action-noise``); so can
an RL baseline's, its actions sampled from the actor (``--sample-actions``).

Seeds: episode ``i`` is reset with seed ``EVAL_SEED_BASE + seed_offset + i``
(``EVAL_SEED_BASE = 1_000_000``). Demonstrations and training envs use seeds
counting up from 0, so the two sets never meet below a million training
episodes; ``seed_offset`` picks another disjoint block of evaluation episodes.
``demo_seeds=DIR`` (``--demo-seeds DIR``) instead resets the episodes with the
seeds of the demonstrations in buffer ``DIR``: their initial states, on which a
policy trained on them can be measured against the unseen evaluation states
(memorisation against generalisation).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tqdm.auto import tqdm

from mmada_rl.baselines import (
    AGENT_CONFIG,
    POLICY_CONFIG,
    ChunkPolicy,
    ChunkPolicyEnsemble,
    OneStepChunkActor,
    is_policy_dir,
    is_rl_agent_dir,
    load_policy,
    load_rl_actor,
)
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.envs.tasks import task_spec
from mmada_rl.keys import IMAGE_KEY, STEP_KEY, SUCCESS_KEY
from mmada_rl.policy.actor import PREDICTED_GOAL_IMAGE_KEY, MMaDAActor
from mmada_rl.policy.ensemble import MMaDAEnsemble
from mmada_rl.policy.execution import ExecutionNoise, PolicyEnv, make_policy_env
from mmada_rl.policy.model import ACTION_READOUTS, MODEL_CONFIG, MMaDAModel

__all__ = ["ENSEMBLE_CHECKPOINT_SEPARATOR", "EVAL_SEED_BASE", "EpisodeResult", "EvalResult", "add_parser",
           "demonstration_seeds", "episode_seeds", "eval_env_config", "eval_seeds", "evaluate", "load_actor",
           "resolve_model_dir", "wilson_interval"]

#: Between an ensemble's member paths in ``eval.json``'s ``checkpoint`` (``"A + B + C"``).
ENSEMBLE_CHECKPOINT_SEPARATOR = " + "
#: First evaluation seed; training and demonstration seeds count up from 0.
EVAL_SEED_BASE = 1_000_000
#: z of a two-sided 95% normal interval.
_Z95 = 1.959963984540054


def eval_seeds(episodes: int, seed_offset: int = 0) -> list[int]:
    """The env seeds of ``episodes`` evaluation episodes: ``EVAL_SEED_BASE + seed_offset + i``."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes!r}.")
    if seed_offset < 0:
        raise ValueError(f"seed_offset must be >= 0 (evaluation seeds start at {EVAL_SEED_BASE}), got {seed_offset!r}.")
    return [EVAL_SEED_BASE + seed_offset + i for i in range(episodes)]


def demonstration_seeds(buffer_dir: str | Path, episodes: int, task: str | None = None) -> list[int]:
    """The env seeds of the first ``episodes`` demonstrations in the buffer ``buffer_dir``
    (their initial states); ``task``, when given, must be the buffer's."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes!r}.")
    meta = BufferMetadata.load(buffer_dir)
    if task is not None and meta.task != task:
        raise ValueError(f"{buffer_dir} holds {meta.task} demonstrations, not {task}.")
    if episodes > len(meta.seeds):
        raise ValueError(f"{buffer_dir} holds {len(meta.seeds)} demonstrations; ask for at most that many episodes "
                         f"(got {episodes}).")
    return [int(s) for s in meta.seeds[:episodes]]


def episode_seeds(episodes: int, seed_offset: int = 0, demo_seeds: str | Path | None = None,
                  task: str | None = None) -> list[int]:
    """The env seeds an evaluation runs: :func:`eval_seeds`, or with ``demo_seeds`` (a buffer)
    :func:`demonstration_seeds` of ``task``."""
    if demo_seeds is None:
        return eval_seeds(episodes, seed_offset)
    if seed_offset:
        raise ValueError(f"seed_offset={seed_offset} applies to evaluation seeds; demo_seeds runs the demonstrations' own.")
    return demonstration_seeds(demo_seeds, episodes, task)


class Interval(NamedTuple):
    low: float
    high: float


def wilson_interval(successes: int, trials: int, z: float = _Z95) -> Interval:
    """Wilson score interval of a binomial rate (default 95%); ``(0, 1)`` for no trials."""
    if not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials, got successes={successes}, trials={trials}.")
    if trials == 0:
        return Interval(0.0, 1.0)
    p, z2 = successes / trials, z * z
    denom = 1.0 + z2 / trials
    center = (p + z2 / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials)) / denom
    # at 0 or all successes the bound is exactly 0 or 1 (centre - half rounds to about +-1e-17 there)
    low = 0.0 if successes == 0 else max(0.0, center - half)
    high = 1.0 if successes == trials else min(1.0, center + half)
    return Interval(low, high)


def resolve_model_dir(path: str | Path) -> Path:
    """The directory holding ``model.json`` (or a baseline's ``policy.json`` or ``rl_agent.json``): ``path`` itself,
    ``path/model``, or, for a training run directory, its newest checkpoint's ``model``."""
    from mmada_rl.training import latest_checkpoint

    path = Path(path)
    newest = latest_checkpoint(path)
    candidates = [path, path / "model"] + ([newest / "model"] if newest is not None else [])
    for candidate in candidates:
        if (candidate / MODEL_CONFIG).is_file() or is_policy_dir(candidate) or is_rl_agent_dir(candidate):
            return candidate
    raise FileNotFoundError(
        f"no MMaDA policy at {path}: expected {path / MODEL_CONFIG} or {path / 'model' / MODEL_CONFIG} "
        "(a directory written by MMaDAModel.save, a checkpoint directory holding one under model/, or a run "
        "directory with checkpoints/), "
        f"or a baseline's {POLICY_CONFIG} or {AGENT_CONFIG} there."
    )


class EpisodeResult(NamedTuple):
    """One evaluation episode."""

    seed: int
    success_once: bool  # success at any step
    success_at_end: bool  # success after the last step
    length: int  # steps until the first success, or all steps run
    steps: int  # env steps run
    decode_ms: list[float]  # policy latency of each chunk (model.act for MMaDA)
    stages: dict[str, bool]  # each of the task's progress flags (TaskSpec.stages): true after any action


@dataclass
class EvalResult:
    """Metrics of :func:`evaluate`; :meth:`to_dict` flattens them as ``eval/...``."""

    task: str
    episodes: int
    execute_steps: int
    temporal_ensemble: bool
    num_denoise_steps: int
    max_episode_steps: int
    success_once: float
    success_once_ci_low: float
    success_once_ci_high: float
    success_at_end: float
    success_at_end_ci_low: float
    success_at_end_ci_high: float
    episode_length: float  # mean of EpisodeResult.length
    decode_ms_mean: float
    decode_ms_p95: float
    env_steps_per_second: float
    seeds: list[int] = field(default_factory=list)
    per_episode: list[EpisodeResult] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    sample_temperature: float = 0.0  # 0: greedy decoding; > 0: tokens sampled at this temperature
    action_noise: float = 0.0  # > 0: greedy chunks executed with N(0, action_noise^2) on the arm's actions
    sample_actions: bool = False  # an RL baseline's actions sampled from its distribution, not its mean
    action_readout: str | None = None  # MMaDA-VLA: "token" or "mean" (MMaDAConfig.action_readout); None for baselines
    checkpoint: str | None = None  # the policy's path when it was given as one (provenance in eval.json)
    demo_seeds: str | None = None  # the buffer whose demonstrations' seeds were run (None: evaluation seeds)
    own_weights: bool = False  # the checkpoints' own weights were evaluated, not their moving average (ema.enabled)
    stages: dict[str, float] = field(default_factory=dict)  # share of episodes reaching each TaskSpec.stages flag

    def stage_interval(self, flag: str) -> Interval:
        """95% Wilson interval of the share of episodes that reached ``flag``."""
        return wilson_interval(sum(r.stages.get(flag, False) for r in self.per_episode), self.episodes)

    def to_dict(self) -> dict:
        """Flat metrics: ``{"eval/success_once": ..., "eval/success_once_ci_low": ..., ...}``, and
        ``eval/reached/<flag>`` for each of the task's progress flags."""
        skip = {"task", "seeds", "per_episode", "files", "checkpoint", "action_readout", "demo_seeds", "stages",
                "own_weights"}
        out = {f"eval/{k}": int(v) if isinstance(v, bool) else v for k, v in asdict(self).items() if k not in skip}
        return {**out, **{f"eval/reached/{flag}": share for flag, share in self.stages.items()}}

    def history_record(self) -> dict:
        """What a training run's ``eval_history.json`` keeps of this evaluation: ``success_once`` with its 95%
        interval, ``success_at_end``, ``episodes``, and each episode's env seed and success (``per_episode``,
        what ``benchmarks/paired.py`` pairs on)."""
        return {"success_once": self.success_once, "success_once_ci_low": self.success_once_ci_low,
                "success_once_ci_high": self.success_once_ci_high, "success_at_end": self.success_at_end,
                "episodes": self.episodes,
                "per_episode": [{"seed": int(r.seed), "success_once": bool(r.success_once)} for r in self.per_episode]}

    def save(self, out_dir: str | Path) -> list[Path]:
        """Write ``eval.json`` (the metrics of :meth:`to_dict`, the provenance and each episode's record, what
        ``benchmarks/seeds.py`` and ``benchmarks/paired.py`` read) and ``eval.md`` (:meth:`table`) into ``out_dir``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        payload = {**self.to_dict(), "task": self.task, "checkpoint": self.checkpoint,
                   "action_readout": self.action_readout, "demo_seeds": self.demo_seeds,
                   "own_weights": self.own_weights, "seeds": self.seeds,
                   "per_episode": [r._asdict() for r in self.per_episode]}
        files = [out / "eval.json", out / "eval.md"]
        files[0].write_text(json.dumps(payload, indent=2))
        files[1].write_text(self.table() + "\n")
        return files

    def table(self) -> str:
        """A small Markdown table of the headline numbers."""
        rows = [
            ("success_once", f"{self.success_once:.3f} [{self.success_once_ci_low:.3f}, {self.success_once_ci_high:.3f}]"),
            ("success_at_end", f"{self.success_at_end:.3f} [{self.success_at_end_ci_low:.3f}, {self.success_at_end_ci_high:.3f}]"),
            *((f"reached {flag}", f"{share:.3f} [{self.stage_interval(flag).low:.3f}, {self.stage_interval(flag).high:.3f}]")
              for flag, share in self.stages.items()),
            ("episode length", f"{self.episode_length:.1f} / {self.max_episode_steps}"),
            ("decode ms / chunk", f"{self.decode_ms_mean:.1f} (p95 {self.decode_ms_p95:.1f})"),
            ("env steps / s", f"{self.env_steps_per_second:.1f}"),
        ]
        on_demos = f", on the demonstrations' initial states ({self.demo_seeds})" if self.demo_seeds else ""
        sampled = (f", tokens sampled at T={self.sample_temperature:g}" if self.sample_temperature else "") + (
            ", actions sampled from the actor" if self.sample_actions else "")
        head = (f"{self.task}, {self.episodes} episodes, k={self.execute_steps}"
                f"{' + temporal ensemble' if self.temporal_ensemble else ''}, N={self.num_denoise_steps}"
                f"{sampled or ', greedy'}"
                f"{', mean read-out' if self.action_readout == 'mean' and not self.sample_temperature else ''}"
                f"{f' + N(0, {self.action_noise:g}^2) on the arm actions' if self.action_noise else ''}"
                f"{on_demos}{', the own weights beside the moving average' if self.own_weights else ''} (95% Wilson CI)")
        lines = [head, "", "| metric | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)]
        return "\n".join(lines)


def load_actor(model: MMaDAModel | MMaDAEnsemble | TensorDictModuleBase | str | Path | Sequence[str | Path],
               device: str = "cpu", *, own_weights: bool = False) -> TensorDictModuleBase:
    """The chunk actor of a policy: an :class:`MMaDAActor` for an MMaDA-VLA model or an
    :class:`MMaDAEnsemble`, the baseline itself otherwise (an RL baseline's actor as a one-step
    chunk policy); loaded first when given as a run, checkpoint or model directory. A list of two
    or more such directories is loaded as their ensemble: an :class:`MMaDAEnsemble` of MMaDA-VLA
    policies, or a :class:`~mmada_rl.baselines.ChunkPolicyEnsemble` of imitation baselines.

    ``own_weights``: a run that kept a moving average of its weights (``ema.enabled``) saves the average as its
    checkpoints' model and the optimizer's own weights beside it; load those instead (every member's; the
    policy given as run or checkpoint directories)."""
    if isinstance(model, (list, tuple)) and len(model) == 1:
        model = model[0]
    if own_weights and not isinstance(model, (str, Path, list, tuple)):
        raise ValueError("own_weights reads a training checkpoint: give the policy as a run or checkpoint directory.")
    if isinstance(model, (list, tuple)):
        members = [_load_policy(resolve_model_dir(d), device, own_weights) for d in model]
        baselines = [isinstance(m, ChunkPolicy) for m in members]
        if all(baselines):
            return ChunkPolicyEnsemble(members)
        if any(baselines) or not all(isinstance(m, MMaDAModel) for m in members):
            raise ValueError("an ensemble's members are all MMaDA-VLA policies or all imitation baselines (BC, "
                             f"Diffusion Policy); got {', '.join(str(d) for d in model)}.")
        model = MMaDAEnsemble(members)
    elif not isinstance(model, (MMaDAModel, MMaDAEnsemble, TensorDictModuleBase)):
        model = _load_policy(resolve_model_dir(model), device, own_weights)
    return MMaDAActor(model) if isinstance(model, (MMaDAModel, MMaDAEnsemble)) else model


def _load_policy(directory: Path, device: str, own_weights: bool) -> MMaDAModel | TensorDictModuleBase:
    """The policy saved in ``directory`` (:func:`resolve_model_dir`'s); with ``own_weights``, the optimizer's own
    weights of the checkpoint holding it (:func:`~mmada_rl.training.load_own_weights`) in place of its average."""
    from mmada_rl.training import load_own_weights

    if is_rl_agent_dir(directory):
        if own_weights:
            raise ValueError(f"{directory}: an RL baseline keeps no moving average of its weights (own_weights).")
        return load_rl_actor(directory, device=device)
    if (directory / MODEL_CONFIG).is_file():
        policy = MMaDAModel.load(directory, device=device)
        trained = policy.denoiser  # what the recipes average (make_weight_ema)
    else:
        policy = trained = load_policy(directory, device=device)
    if own_weights:
        load_own_weights(trained, directory.parent)
    return policy


def _image_size(actor) -> int | None:
    """The image side the policy was fitted on (``None``: it does not say)."""
    if isinstance(actor, MMaDAActor):
        return actor.model.image_size
    return getattr(actor, "image_size", None)


def _camera_fov(actor, task: str) -> float | None:
    """The camera field of view (degrees) of the policy's training images of ``task`` (``None``: the task's own)."""
    if isinstance(actor, MMaDAActor):
        return actor.model.config.camera_fov_for(task)
    return getattr(actor, "camera_fov", None)


def eval_env_config(actor: TensorDictModuleBase, task: str, image_size: int | None = None, **kwargs) -> EnvConfig:
    """The evaluation env of ``actor`` on ``task``: its observation mode, image size and camera, episodes
    running past success (``success_once`` and ``success_at_end``); ``kwargs`` go to :class:`EnvConfig`."""
    policy_size, obs_mode = _image_size(actor), getattr(actor, "obs_mode", "rgb")  # "state": a reference policy
    if image_size is not None and policy_size is not None and image_size != policy_size:
        raise ValueError(
            f"env image_size={image_size} but the policy's image tokenizer / encoder was fitted on "
            f"{policy_size}x{policy_size} images; evaluate with image_size={policy_size}."
        )
    size = policy_size or image_size
    camera = {"camera_fov": _camera_fov(actor, task)} if obs_mode == "rgb" else {}
    return EnvConfig(task=task, obs_mode=obs_mode, ignore_terminations=True, **({"image_size": size} if size else {}),
                     **camera, **kwargs)


class _Rollout(NamedTuple):
    result: EpisodeResult
    decisions: list  # (env step of the decision, predicted goal image or None)
    frames: torch.Tensor  # uint8 (T+1, 3, H, W): the reset frame, then one per action


def _run_episode(penv: PolicyEnv, seed: int, max_decisions: int, stages: tuple[str, ...] = ()) -> _Rollout:
    """One episode from ``reset(seed=seed)`` until the env reports done; ``stages``: the progress flags
    the env reads (``EnvConfig.stage_flags``), each recorded as reached if true after any action."""
    td = penv.env.reset(seed=seed)
    decode_ms, decisions = [], []
    for _ in range(max_decisions):
        step = int(td.get(STEP_KEY))
        td = penv.policy(td)
        decode_ms.append(1e3 * float(getattr(penv.actor, "last_decode_seconds", float("nan"))))
        decisions.append((step, td.get(PREDICTED_GOAL_IMAGE_KEY, None)))
        td = penv.env.step(td)
        if td.get(("next", "done")).any():
            break
        td = step_mdp(td)
    steps = penv.step_log.steps
    success = [bool(s.get(SUCCESS_KEY)) for s in steps[1:]]  # after each action
    first = success.index(True) + 1 if any(success) else len(success)
    reached = {flag: any(bool(s.get(flag)) for s in steps[1:]) for flag in stages}
    result = EpisodeResult(seed, any(success), bool(success and success[-1]), first, len(success), decode_ms, reached)
    frames = torch.stack([s.get(IMAGE_KEY) for s in steps]) if IMAGE_KEY in steps[0].keys(True) else torch.empty(0)
    return _Rollout(result, decisions, frames)  # no frames for a state-observation policy


def evaluate(
    model: MMaDAModel | MMaDAEnsemble | TensorDictModuleBase | str | Path | Sequence[str | Path],
    task: str,
    episodes: int = 50,
    *,
    seed_offset: int = 0,
    demo_seeds: str | Path | None = None,
    execute_steps: int | None = None,
    temporal_ensemble: bool = False,
    num_denoise_steps: int | None = None,
    sample_temperature: float | None = None,
    action_noise: float | None = None,
    sample_actions: bool = False,
    action_readout: str | None = None,
    max_episode_steps: int | None = None,
    control_mode: str = "pd_ee_delta_pose",
    image_size: int | None = None,
    out_dir: str | Path | None = None,
    video: bool = False,
    goal_grid: bool = False,
    device: str = "cpu",
    progress: bool = True,
    own_weights: bool = False,
) -> EvalResult:
    """Roll the policy out on fixed evaluation seeds (greedy by default) and measure success.

    Args:
        model: the policy: an :class:`MMaDAModel` or its :class:`MMaDAActor`, a
            baseline policy (:mod:`mmada_rl.baselines`) or any chunk actor (see the
            module docstring), or a directory saved by ``MMaDAModel.save`` or a
            baseline's ``save`` (or a checkpoint directory holding one under ``model/``);
            an :class:`~mmada_rl.policy.MMaDAEnsemble` or a list of two or more MMaDA-VLA
            policy directories: their ensemble (greedy only).
        task: ManiSkill3 task id.
        episodes: evaluation episodes (seeds :func:`eval_seeds`).
        seed_offset: first evaluation seed is ``EVAL_SEED_BASE + seed_offset``.
        demo_seeds: a demonstration buffer: run its first ``episodes`` demonstrations'
            seeds (:func:`demonstration_seeds`, their initial states) instead of evaluation seeds.
        execute_steps: actions executed per chunk (``None``: the whole chunk).
        temporal_ensemble: replan every step with ACT's temporal ensemble.
        num_denoise_steps: decoding steps ``N`` (``None``: the policy's own; a
            baseline takes it as ``get_new_version(num_denoise_steps=N)``).
        sample_temperature: MMaDA policies only: sample the tokens at this
            temperature instead of decoding greedily (the stochastic policy an
            online fine-tuning run collects with, ``collector.temperature``).
            Every episode draws from torch's RNG seeded with its env seed, so a
            sampled evaluation (or a Diffusion Policy's) repeats exactly; the
            caller's RNG state is left as it was.
        action_noise: MMaDA policies only: execute the greedy chunks with
            ``N(0, action_noise^2)`` noise on the arm's actions
            (:class:`~mmada_rl.policy.ExecutionNoise`): the exploration policy of
            fine-tuning with ``collector.action_noise``. The noise is drawn from
            torch's RNG seeded with each episode's env seed, as sampled tokens are.
        sample_actions: RL baselines only (the actors of ``recipes/baselines/online.py``):
            sample each action from the actor's TanhNormal, the policy its training
            rollouts ran, instead of executing its mean ``tanh(loc)``; seeded per
            episode as sampled tokens are.
        action_readout: MMaDA policies only: ``"token"`` or ``"mean"``, how greedy chunks
            become actions (:attr:`~mmada_rl.policy.MMaDAConfig.action_readout`;
            ``None``: the policy's own).
        max_episode_steps: episode length (``None``: the task registry's).
        control_mode: ManiSkill controller; must match the one the policy was trained in.
        image_size: checked against the policy's image size (``None``: take it).
        out_dir: write ``eval.json``, ``eval.md`` (and videos, goal grid) here.
        video: save each episode's frames (MP4 with imageio-ffmpeg, else GIF).
        goal_grid: save a PNG of the first episode's predicted goals beside the real frames.
        device: torch device the model runs on when loaded here.
        progress: show a ``tqdm`` bar over episodes.
        own_weights: for a run that kept a moving average of its weights (``ema.enabled``; the average is its
            checkpoints' model), evaluate the optimizer's own weights saved beside it instead (``model`` given as
            run or checkpoint directories; :func:`load_actor`).

    Returns:
        an :class:`EvalResult`; ``result.to_dict()`` is the flat ``eval/...`` metrics dict.

    Examples:
        >>> result = evaluate("runs/pick/checkpoint", "PickCube-v1", episodes=50, execute_steps=5)  # doctest: +SKIP
        >>> result.to_dict()["eval/success_once"], result.success_once_ci_low, result.decode_ms_p95  # doctest: +SKIP
    """
    EnvConfig(task=task)  # an unknown task fails before the model loads
    seeds = episode_seeds(episodes, seed_offset, demo_seeds, task)
    actor = load_actor(model, device, own_weights=own_weights)
    if sample_actions and not isinstance(actor, OneStepChunkActor):
        raise ValueError("sample_actions needs an RL baseline's actor (PPO, SAC or IQL of recipes/baselines/online.py; "
                         f"got a {type(actor).__name__}); an MMaDA-VLA policy samples with sample_temperature.")
    cfg = eval_env_config(actor, task, image_size, control_mode=control_mode, max_episode_steps=max_episode_steps,
                          stage_flags=True)
    stages = task_spec(task).stages
    mmada = actor.model if isinstance(actor, MMaDAActor) else None
    if sample_temperature is not None and isinstance(mmada, MMaDAEnsemble):
        raise ValueError("an ensemble decodes greedily only: sample_temperature applies to one policy at a time.")
    if sample_temperature is not None and (mmada is None or not sample_temperature > 0):
        raise ValueError("sample_temperature needs an MMaDA-VLA policy and a value > 0 "
                         f"(got {sample_temperature!r} for a {type(actor).__name__}).")
    if action_noise is not None and (mmada is None or not action_noise > 0):
        raise ValueError("action_noise needs an MMaDA-VLA policy and a value > 0 "
                         f"(got {action_noise!r} for a {type(actor).__name__}).")
    if action_noise is not None and (sample_temperature is not None or temporal_ensemble):
        raise ValueError("action_noise perturbs greedy chunks executed whole: it does not combine with "
                         "sample_temperature or temporal_ensemble.")
    if action_readout is not None and mmada is None:
        raise ValueError(f"action_readout needs an MMaDA-VLA policy (got a {type(actor).__name__}).")
    penv, readout = None, None  # readout: the MMaDA policy's action read-out in this evaluation
    restore = contextlib.ExitStack()  # gives the policy its own sampler and read-out back at the end
    try:
        if mmada is not None:
            restore.enter_context(mmada.decoding(num_steps=num_denoise_steps, temperature=sample_temperature,
                                                 readout=action_readout))
            num_steps, readout = mmada.sampler.config.num_steps, mmada.action_readout
        else:
            if num_denoise_steps is not None:
                actor = actor.get_new_version(num_denoise_steps=num_denoise_steps)
            num_steps = int(getattr(actor, "num_denoise_steps", 0))
        penv = make_policy_env(
            cfg, actor, execute_steps=execute_steps, temporal_ensemble=temporal_ensemble,
            log_keys=[IMAGE_KEY, SUCCESS_KEY, STEP_KEY, *stages],
        )  # fmt: skip
        if action_noise is not None:  # the policy's greedy chunks, perturbed; the noise draws from the seeded global RNG
            penv = penv._replace(policy=ExecutionNoise(penv.policy, action_noise))
        env_dim = int(penv.env.action_spec.shape[-1])
        if env_dim != penv.actor.action_dim:
            raise ValueError(f"{task} with control_mode={control_mode!r} takes {env_dim}-d actions but the policy "
                             f"outputs {penv.actor.action_dim}-d ones; pass the control mode it was trained in.")
        limit = cfg.episode_steps  # None: ManiSkill's own TimeLimit ends the episode
        results, frames, first_episode = [], [], None
        decoding = ExplorationType.RANDOM if sample_temperature or sample_actions else ExplorationType.DETERMINISTIC
        devices = list(range(torch.cuda.device_count()))
        with set_exploration_type(decoding), torch.no_grad(), torch.random.fork_rng(devices=devices):
            penv.actor(penv.env.reset(seed=seeds[0]))  # warm-up: the first decode is not a steady-state latency
            start = time.perf_counter()
            bar = tqdm(seeds, desc=f"eval {task}", disable=not progress, unit="ep")
            for seed in bar:
                torch.manual_seed(seed)  # sampled tokens (or a diffusion policy's noise) repeat with the episode
                rollout = _run_episode(penv, seed, max_decisions=(limit or 100_000) + 1, stages=stages)
                results.append(rollout.result)
                if first_episode is None:
                    first_episode = rollout  # its chunks go into the goal grid
                if video:
                    frames.append(rollout.frames)
                bar.set_postfix(success=f"{np.mean([r.success_once for r in results]):.2f}")
        seconds = time.perf_counter() - start
    finally:
        restore.close()
        if penv is not None:
            penv.env.close()

    n, once, end = len(results), sum(r.success_once for r in results), sum(r.success_at_end for r in results)
    once_ci, end_ci = wilson_interval(once, n), wilson_interval(end, n)
    latencies = np.array([ms for r in results for ms in r.decode_ms])  # one per chunk decoded
    metrics = EvalResult(
        task=task, episodes=n, execute_steps=penv.actor.execute_steps, temporal_ensemble=temporal_ensemble,
        num_denoise_steps=num_steps, max_episode_steps=limit or max(r.steps for r in results),
        success_once=once / n, success_once_ci_low=once_ci.low, success_once_ci_high=once_ci.high,
        success_at_end=end / n, success_at_end_ci_low=end_ci.low, success_at_end_ci_high=end_ci.high,
        episode_length=float(np.mean([r.length for r in results])),
        decode_ms_mean=float(latencies.mean()), decode_ms_p95=float(np.percentile(latencies, 95)),
        env_steps_per_second=sum(r.steps for r in results) / seconds,
        seeds=seeds, per_episode=results, sample_temperature=float(sample_temperature or 0.0),
        action_noise=float(action_noise or 0.0), sample_actions=sample_actions,
        action_readout=readout,
        checkpoint=_checkpoint_label(model),
        demo_seeds=None if demo_seeds is None else str(demo_seeds),
        own_weights=own_weights,
        stages={flag: sum(r.stages[flag] for r in results) / n for flag in stages},
    )  # fmt: skip
    if out_dir is not None:
        metrics.files = _write_outputs(Path(out_dir), metrics, frames if video else None,
                                       (first_episode.decisions, first_episode.frames, actor.chunk_size) if goal_grid else None)
    return metrics


def _checkpoint_label(model) -> str | None:
    """The policy's path(s) when given as such (provenance in eval.json): an ensemble's joined by " + "."""
    if isinstance(model, (str, Path)):
        return str(model)
    if isinstance(model, (list, tuple)) and all(isinstance(m, (str, Path)) for m in model):
        return ENSEMBLE_CHECKPOINT_SEPARATOR.join(str(m) for m in model)
    return None


# -- outputs ----------------------------------------------------------------------
def _write_outputs(out: Path, metrics: EvalResult, videos, goal) -> list[str]:
    files = metrics.save(out)
    if videos is not None:
        files += [_write_video(f, out / "videos" / f"episode{i:03d}_seed{s}") for i, (f, s) in enumerate(zip(videos, metrics.seeds))]
    if goal is not None:
        files.append(_write_goal_grid(out / "goal_grid.png", *goal))
    return [str(f) for f in files]


def _write_video(frames: torch.Tensor, stem: Path, fps: int = 20) -> Path:
    """Frames ``uint8 [T, 3, H, W]`` → ``stem.mp4`` (imageio-ffmpeg) or ``stem.gif`` (Pillow)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    hwc = frames.permute(0, 2, 3, 1).cpu().numpy()  # (T, H, W, 3)
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (MP4 needs the ffmpeg binary it ships)

        path = stem.with_suffix(".mp4")
        imageio.mimsave(path, list(hwc), fps=fps, macro_block_size=1)
    except ImportError:
        from PIL import Image

        path = stem.with_suffix(".gif")
        images = [Image.fromarray(f) for f in hwc]
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path


def _write_goal_grid(path: Path, decisions: list, frames: torch.Tensor, chunk_size: int, max_rows: int = 8) -> Path:
    """Rows: frame at decision step ``s``, predicted goal ``o_{s+K}``, real frame ``s+K``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [d for d in decisions if d[1] is not None]
    if len(rows) > max_rows:
        rows = [rows[i] for i in np.linspace(0, len(rows) - 1, max_rows).round().astype(int)]
    fig, axes = plt.subplots(max(len(rows), 1), 3, figsize=(6, 2 * max(len(rows), 1)), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for row, (step, goal) in enumerate(rows):
        target = step + chunk_size
        panels = [(frames[step], f"o_{step}"), (goal, f"predicted o_{target}"),
                  (frames[target] if target < len(frames) else None, f"real o_{target}")]
        for ax, (image, title) in zip(axes[row], panels):
            if image is not None:
                ax.imshow(image.permute(1, 2, 0).cpu().numpy())
            ax.set_title(title if image is not None else f"{title} (past the end)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# -- command line ---------------------------------------------------------------
def add_parser(sub) -> None:
    """Register ``mmada-rl eval``."""
    p = sub.add_parser("eval", help="evaluate a saved policy on a ManiSkill3 task (success rates with 95%% CIs)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, nargs="+", metavar="CHECKPOINT",
                   help="directory saved by MMaDAModel.save or by a baseline's save "
                   "(recipes/baselines: BC, Diffusion Policy, and the RL baselines' actors), a checkpoint directory "
                   "with one under model/, or a run directory (its newest checkpoint). Two or more MMaDA-VLA "
                   "policies (e.g. the same recipe's training seeds), or two or more BC / Diffusion Policy ones, are "
                   "evaluated as one ensemble: each predicts its chunk (MMaDA-VLA: greedily) and the mean chunk "
                   "runs (an MMaDA-VLA gripper by majority: MMaDAEnsemble, ChunkPolicyEnsemble).")
    p.add_argument("--task", required=True, help="ManiSkill3 task id, e.g. PickCube-v1.")
    p.add_argument("--episodes", type=int, default=50, help="evaluation episodes (default: %(default)s).")
    p.add_argument("--seed-offset", type=int, default=0, help=f"first env seed is {EVAL_SEED_BASE} + this (default: %(default)s).")
    p.add_argument("--demo-seeds", default=None, metavar="BUFFER",
                   help="run the first EPISODES demonstrations' seeds of this buffer (their initial states, which a "
                   "policy trained on them has seen) instead of the evaluation seeds: memorisation against "
                   "generalisation (default: evaluation seeds).")
    p.add_argument("--execute-steps", type=int, default=None, help="actions executed per chunk before replanning, 1..K (default: K).")
    p.add_argument("--temporal-ensemble", action="store_true", help="replan every step and average overlapping chunks (ACT).")
    p.add_argument("--num-denoise-steps", type=int, default=None, help="decoding steps N per chunk: MMaDA's parallel refinement steps, "
                   "a diffusion_policy baseline's DDIM steps (default: the policy's).")
    p.add_argument("--sample-temperature", type=float, default=None,
                   help="MMaDA-VLA only: sample the action tokens at this temperature instead of greedy decoding "
                   "(how good the exploration policy of fine-tuning is; default: greedy).")
    p.add_argument("--action-noise", type=float, default=None, metavar="STD",
                   help="MMaDA-VLA only: execute the greedy chunks with Gaussian noise of this std on the arm's "
                   "actions (the exploration policy of fine-tuning with collector.action_noise; default: none).")
    p.add_argument("--sample-actions", action="store_true",
                   help="RL baselines only (PPO, SAC, IQL): sample each action from the actor's distribution, as its "
                   "training rollouts did, instead of executing its mean (default: the mean).")
    p.add_argument("--action-readout", choices=ACTION_READOUTS, default=None,
                   help="MMaDA-VLA with uniform-bin action tokens only: how a greedy chunk becomes actions; 'token': the "
                   "committed bins' centres, 'mean': each dimension's expected value under the distribution its token was "
                   "committed from (default: the policy's own, MMaDAConfig.action_readout).")
    p.add_argument("--max-episode-steps", type=int, default=None, help="episode length (default: the task registry's).")
    p.add_argument("--control-mode", default="pd_ee_delta_pose", help="ManiSkill controller the policy acts in (default: %(default)s).")
    p.add_argument("--image-size", type=int, default=None, help="camera image side; must match the policy (default: the policy's).")
    p.add_argument("--device", default="cpu", help="torch device of the model (default: %(default)s).")
    p.add_argument("--num-threads", type=int, default=1,
                   help="torch CPU threads; 1 leaves the cores to SAPIEN's CPU renderer (default: %(default)s).")
    p.add_argument("--out", default=None, help="output directory for eval.json / eval.md (default: CHECKPOINT/eval; "
                   "for an ensemble, the first CHECKPOINT's eval_ensemble).")
    p.add_argument("--video", action="store_true", help="save every episode as MP4 (GIF without imageio-ffmpeg).")
    p.add_argument("--goal-grid", action="store_true", help="save a PNG of predicted goal images beside the real frames.")
    p.add_argument("--own-weights", action="store_true",
                   help="for a run that kept a moving average of its weights (ema.enabled), evaluate the optimizer's own "
                        "weights its checkpoints save beside the average (their model) instead.")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar.")
    p.set_defaults(func=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    if args.num_threads < 1:
        print(f"mmada-rl eval: error: --num-threads must be >= 1, got {args.num_threads}.", file=sys.stderr)
        return 2
    # measured on 2 busy cores: a tiny model decodes a chunk in ~15 ms with 1 thread, ~450 ms with 2
    torch.set_num_threads(args.num_threads)
    try:
        model_dirs = [resolve_model_dir(c) for c in args.checkpoint]
        default_out = Path(args.checkpoint[0]) / ("eval" if len(model_dirs) == 1 else "eval_ensemble")
        result = evaluate(
            model_dirs[0] if len(model_dirs) == 1 else model_dirs, args.task, args.episodes, seed_offset=args.seed_offset, demo_seeds=args.demo_seeds,
            execute_steps=args.execute_steps,
            temporal_ensemble=args.temporal_ensemble, num_denoise_steps=args.num_denoise_steps,
            sample_temperature=args.sample_temperature, action_noise=args.action_noise,
            sample_actions=args.sample_actions, action_readout=args.action_readout, max_episode_steps=args.max_episode_steps, control_mode=args.control_mode, image_size=args.image_size,
            out_dir=args.out or default_out, video=args.video, goal_grid=args.goal_grid,
            device=args.device, progress=not args.no_progress, own_weights=args.own_weights,
        )  # fmt: skip
    except (FileNotFoundError, ValueError) as err:
        print(f"mmada-rl eval: error: {err}", file=sys.stderr)
        return 2
    print(result.table())
    print(f"wrote {', '.join(result.files)}")
    return 0
