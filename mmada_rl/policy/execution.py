"""Executing action chunks in a TorchRL env: receding horizon and temporal ensembling.

One policy call decodes a chunk of ``K`` actions; the env then executes its first
``k`` (``1 <= k <= K``) before the policy is called again. ``k = K`` is the
authors' open-loop choice; smaller ``k`` replans more often (closed loop) at the
price of more decodes.

The env side is TorchRL's :class:`~torchrl.envs.transforms.MultiAction`: the
actor writes ``"action"`` as ``[*B, k, A]`` and one outer ``env.step`` runs the
``k`` inner steps, stopping early at ``done``. We use it rather than the
policy-side ``MultiStepActorWrapper`` because it keeps one outer transition per
decision (the chunk's tokens, log-probability and decoding path ride along on
it, which is what reward-weighted fine-tuning consumes), replays nothing when an
episode ends inside a chunk, and works unchanged with ``ParallelEnv``.
``stack_rewards=False``: the outer transition carries one reward entry (not a
ragged stack); see :func:`make_policy_env` for what it holds.

:class:`TemporalEnsemble` is the policy-side alternative of ACT: replan at every
step (``k = 1``) and execute a weighted average of the predictions for the
current step made by the last ``K`` chunks.
"""
from __future__ import annotations

import warnings
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Compose, EnvBase, InitTracker, TransformedEnv
from torchrl.envs.transforms import MultiAction, Transform

from mmada_rl.envs.maniskill import EnvConfig, make_env
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, STEP_KEY
from mmada_rl.policy.actor import MMaDAActor, check_execute_steps
from mmada_rl.tokenizers import ActionOutOfRangeWarning

__all__ = ["ChunkReward", "ExecutionNoise", "PolicyEnv", "StepLog", "TemporalEnsemble", "make_policy_env"]

#: written by :class:`~torchrl.envs.transforms.InitTracker`: True on the first step after a reset.
INIT_KEY = "is_init"


class TemporalEnsemble(TensorDictModuleBase):
    """ACT-style temporal ensembling of overlapping chunks (policy side, replans every step).

    Every call decodes a new chunk ``[*B, K, A]``; the action written to
    ``"action"`` (``[*B, 1, A]``) averages the predictions for the current step
    of the last ``K`` chunks (the chunk decoded ``h`` steps ago predicts it at
    its index ``h``), with ACT's weights ``w_i = exp(-decay * i)``, ``i = 0``
    for the oldest prediction. ``decay > 0`` trusts older chunks more, ``0``
    averages uniformly. The history of an env is dropped when ``"is_init"``
    (TorchRL's :class:`~torchrl.envs.transforms.InitTracker`) marks a reset.

    Args:
        actor: an :class:`~mmada_rl.policy.actor.MMaDAActor` (any ``execute_steps``).
        decay: ``m`` in ``exp(-m * i)``; ACT uses 0.01.

    Examples (``model``: an :class:`MMaDAModel`; ``env``: one ManiSkill env with an ``InitTracker``):
        >>> policy = TemporalEnsemble(MMaDAActor(model), decay=0.01)  # doctest: +SKIP
        >>> td = policy(env.reset())  # doctest: +SKIP
        >>> td["action"].shape  # doctest: +SKIP
        torch.Size([1, 7])
    """

    def __init__(self, actor: MMaDAActor, decay: float = 0.01) -> None:
        super().__init__()
        if not decay >= 0:
            raise ValueError(f"decay must be >= 0 (weights exp(-decay * i), i=0 the oldest), got {decay!r}.")
        self.actor = actor
        self.decay = float(decay)
        self.in_keys = [*actor.in_keys, INIT_KEY]
        self.out_keys = list(actor.out_keys)
        self.reset_history()

    def reset_history(self) -> None:
        """Forget every stored chunk."""
        self._chunks: torch.Tensor | None = None  # (*B, H=K, K, A): slot h holds the chunk decoded h steps ago
        self._valid: torch.Tensor | None = None  # (*B, H)

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        out = self.actor(tensordict, **kwargs)
        chunk = out.get(ACTION_CHUNK_KEY)  # (*B, K, A)
        batch, horizon = chunk.shape[:-2], chunk.shape[-2]
        if self._chunks is None or self._chunks.shape[:-3] != batch or self._chunks.device != chunk.device:
            self._chunks = chunk.new_zeros(*batch, horizon, *chunk.shape[-2:])
            self._valid = torch.zeros(*batch, horizon, dtype=torch.bool, device=chunk.device)
        is_init = tensordict.get(INIT_KEY, None)
        valid = self._valid
        if is_init is not None:
            valid = valid & ~is_init.reshape(*batch, 1).to(valid.device)  # a reset drops the history
        self._valid = torch.cat([torch.ones_like(valid[..., :1]), valid[..., :-1]], -1)  # (*B, H)
        self._chunks = torch.cat([chunk.unsqueeze(-3), self._chunks[..., :-1, :, :]], -3)  # (*B, H, K, A)
        age = torch.arange(horizon, device=chunk.device)  # (H,): slot h predicts the current step at index h
        index = age.view(horizon, 1, 1).expand(*batch, horizon, 1, chunk.shape[-1])
        current = self._chunks.gather(-2, index).squeeze(-2)  # (*B, H, A)
        # exp(-decay * i) with i counted from the oldest valid slot equals exp(decay * h) up to a constant
        weights = torch.exp(self.decay * (age - (horizon - 1)).to(chunk.dtype)) * self._valid  # (*B, H)
        action = (weights[..., None] * current).sum(-2) / weights.sum(-1, keepdim=True)  # (*B, A)
        out.set(ACTION_KEY, action.unsqueeze(-2))  # (*B, 1, A)
        return out


class ExecutionNoise(TensorDictModuleBase):
    """Gaussian exploration around a chunk policy's own actions, with the tokens of what is executed.

    Calls ``actor`` (greedy under a deterministic exploration type: with
    ``action_readout="mean"`` the regression read-out), adds ``N(0, std^2)``
    noise to every non-gripper dimension of the chunk, clips it to the env's
    ``[-1, 1]`` and re-tokenizes it with the policy's action tokenizer (which
    clips each dimension to the range it was fitted on, silently here); the
    chunk, its tokens and the executed ``"action"`` are all replaced by the
    decoded re-tokenized chunk, so the stored tokens are exactly what the env
    ran (a training row built from them imitates the executed actions). It is
    DART's noise injection with the policy as its own expert; the decoding path
    and log-probability the actor wrote no longer describe the chunk, so the
    rows are for reward-weighted regression, not for path-likelihood PPO.

    Args:
        actor: an :class:`~mmada_rl.policy.actor.MMaDAActor`.
        std: noise standard deviation in the env's normalised action units (> 0).
        generator: RNG of the noise (``None``: torch's global RNG).

    Examples (the greedy chunk, perturbed; its tokens match ``td["action"]``):
        >>> noise = torch.Generator().manual_seed(0)
        >>> policy = ExecutionNoise(MMaDAActor(model), std=0.1, generator=noise)  # doctest: +SKIP
        >>> with set_exploration_type(ExplorationType.DETERMINISTIC):  # doctest: +SKIP
        ...     td = policy(env.reset())
    """

    def __init__(self, actor: MMaDAActor, std: float, generator: torch.Generator | None = None) -> None:
        super().__init__()
        if not std > 0:
            raise ValueError(f"std must be > 0 (the noise's standard deviation in normalised action units), got {std!r}.")
        self.actor, self.std, self.generator = actor, float(std), generator
        self.in_keys, self.out_keys = list(actor.in_keys), list(actor.out_keys)

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        out = self.actor(tensordict, **kwargs)
        keys = self.actor.tensor_keys
        chunk = out.get(keys.action_chunk)  # (*B, K, A)
        tokenizer = self.actor.model.action_tokenizer
        arm = ~tokenizer.normalizer.is_gripper.cpu()  # (A,): the dimensions that get noise
        noise = torch.randn(chunk.shape, generator=self.generator, dtype=chunk.dtype) * self.std * arm.to(chunk.dtype)
        with warnings.catch_warnings():  # noise past the tokenizer's fitted range is clipped to it, by design
            warnings.simplefilter("ignore", ActionOutOfRangeWarning)
            tokens = tokenizer.encode((chunk + noise.to(chunk.device)).clamp(-1.0, 1.0))  # (*B, K, d_tok)
        executed = tokenizer.decode(tokens).to(chunk)  # (*B, K, A): what the tokens say
        out.set(keys.action_chunk, executed)
        out.set(keys.action_tokens, tokens.to(out.get(keys.action_tokens).device))
        out.set(keys.action, executed[..., : self.actor.execute_steps, :])
        return out


class ChunkReward(MultiAction):
    """:class:`~torchrl.envs.transforms.MultiAction` whose outer reward is the chunk's discounted return.

    A chunk is one macro-action: its reward is ``sum_i gamma**i * r_i`` over the
    ``k`` executed steps (fewer when a ``done`` cuts the chunk short; the skipped
    steps count 0), so a chunk-level value function bootstraps with ``gamma**k``.
    TorchRL's ``MultiAction(stack_rewards=False)`` keeps only the last step's
    reward, which loses every dense reward but one per chunk.

    Batch-locked envs (``SerialEnv``/``ParallelEnv``) stop stepping an env after its
    ``done`` but leave that step's reward in the remaining slots of the stack; the
    step counter (TorchRL's ``StepCounter``, which ``make_env`` adds) tells how many
    steps each env ran, and only those are summed.

    Args:
        gamma: per-step discount inside the chunk.
        step_count_key: the step counter's key.

    Examples:
        >>> env = TransformedEnv(make_env("PushCube-v1"), ChunkReward(gamma=0.99), auto_unwrap=False)
        >>> td = env.reset().set("action", torch.zeros(5, 7))   # a 5-step chunk
        >>> env.step(td)["next", "reward"].shape                 # one reward per chunk
        torch.Size([1])
    """

    def __init__(self, gamma: float = 1.0, *, step_count_key: str = STEP_KEY, **kwargs) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}.")
        if kwargs.get("stack_rewards") is False:
            raise ValueError("ChunkReward sums the stacked rewards; stack_rewards cannot be False.")
        kwargs["stack_rewards"] = True
        super().__init__(**kwargs)
        self.gamma, self.step_count_key = float(gamma), step_count_key

    def _transform_reward_spec(self, reward_spec, ndim):
        return reward_spec  # one (summed) reward per chunk, shaped as a single step's

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = super()._step(tensordict, next_tensordict)  # rewards stacked along the chunk dim
        dim = next_tensordict.batch_dims + self.dim - 1  # where MultiAction stacked the steps
        executed = self._executed(tensordict, next_tensordict)  # (*B,) or None
        for key in self.parent.reward_keys:
            stacked = next_tensordict.get(key)  # (*B, n, *R)
            n = stacked.shape[dim]
            trailing = [1] * (stacked.ndim - dim - 1)
            steps = torch.arange(n, device=stacked.device)
            discount = (self.gamma ** steps.to(stacked.dtype)).view(n, *trailing)
            if executed is not None:
                # batch-locked envs (SerialEnv, ParallelEnv) skip the steps after a done but repeat
                # that step's reward in the stack: keep only the steps that ran
                valid = steps < executed.to(stacked.device).unsqueeze(-1)  # (*B, n)
                stacked = torch.where(valid.view(*valid.shape, *trailing), stacked, torch.zeros_like(stacked))
            next_tensordict.set(key, (stacked * discount).sum(dim))
        return next_tensordict

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # the step counter at the decision, before MultiAction runs the inner steps
        self._start_count = tensordict.get(self.step_count_key, None)
        return super()._inv_call(tensordict)

    def _executed(self, tensordict: TensorDictBase | None, next_tensordict: TensorDictBase) -> torch.Tensor | None:
        """Inner steps each env ran in this chunk, from the step counter (``None`` when unavailable)."""
        before, after = getattr(self, "_start_count", None), next_tensordict.get(self.step_count_key, None)
        if before is None or after is None:
            return None
        return (after - before.to(after.device)).reshape(next_tensordict.batch_size)


class StepLog(Transform):
    """Keep selected entries of every executed env step in memory (single env, for evaluation),
    and the action each step executed.

    Placed before :class:`~torchrl.envs.transforms.MultiAction`, it sees each
    inner step of a chunk, which the outer transition does not show. ``steps[0]``
    is the reset observation, ``steps[t]`` the state after ``t`` actions, and
    ``actions[t]`` the action that led from one to the other. The log lives in the
    process that steps the env, so it is empty for ``ParallelEnv``.

    Args:
        keys: the entries to keep (e.g. ``("observation", "image")``, ``"success"``).
    """

    def __init__(self, keys: list) -> None:
        super().__init__()
        self.keys = list(keys)
        # MultiAction steps a rebuilt parent env holding a shallow clone of this transform:
        # keep the records in shared lists that are cleared, never rebound.
        self._steps: list[TensorDictBase] = []
        self._actions: list[torch.Tensor] = []

    @property
    def steps(self) -> list[TensorDictBase]:
        """The entries of every step since the last reset (``steps[t]``: after ``t`` actions)."""
        return self._steps

    @property
    def actions(self) -> list[torch.Tensor]:
        """The action of every step since the last reset (``actions[t]``: from ``steps[t]`` to ``steps[t + 1]``)."""
        return self._actions

    def transitions(self) -> TensorDictBase:
        """The steps since the last reset as a ``[T]`` tensordict in TorchRL's rollout layout: the entries
        logged at reset, of the state each action was taken in; the action; under ``"next"`` the entries
        logged after it."""
        if not self._actions:
            raise ValueError("no step executed since the last reset.")
        before = self._steps[0].keys(True, True)
        episode = torch.stack([step.select(*before) for step in self._steps[:-1]])
        episode.set(ACTION_KEY, torch.stack(self._actions))
        episode.set("next", torch.stack(self._steps[1:]))
        return episode

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._steps.clear()
        self._actions.clear()
        self._steps.append(tensordict_reset.select(*self.keys, strict=False).clone())
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._steps.append(next_tensordict.select(*self.keys, strict=False).clone())
        self._actions.append(tensordict.get(ACTION_KEY).clone())
        return next_tensordict


class PolicyEnv(NamedTuple):
    """What :func:`make_policy_env` returns."""

    env: TransformedEnv  # one outer step = k inner steps
    policy: TensorDictModuleBase  # the actor (or its TemporalEnsemble) to pass to env.rollout / collectors
    actor: MMaDAActor  # the actor inside ``policy`` (``last_decode_seconds``)
    step_log: StepLog | None  # every inner step, when ``log_keys`` was given


def make_policy_env(
    env: EnvConfig | EnvBase,
    actor: MMaDAActor,
    *,
    execute_steps: int | None = None,
    temporal_ensemble: bool = False,
    ensemble_decay: float = 0.01,
    log_keys: list | None = None,
    chunk_gamma: float | None = None,
) -> PolicyEnv:
    """Wrap an env so that one policy call decodes a chunk and the first ``k`` actions run.

    Args:
        env: an :class:`~mmada_rl.envs.maniskill.EnvConfig` (built with ``make_env``)
            or an env already built (it is wrapped, not copied).
        actor: the actor; it is not modified (a shallow copy gets ``execute_steps``).
        execute_steps: ``k``, actions executed per chunk before replanning,
            ``1 <= k <= K``; ``None``: ``K`` (open loop), or 1 with ``temporal_ensemble``.
        temporal_ensemble: replan every step and execute ACT's ensemble of the
            last ``K`` chunks' predictions (needs ``k = 1``).
        ensemble_decay: ``m`` of the ensemble weights ``exp(-m * i)``.
        log_keys: keep these entries of every inner step in ``step_log`` (single env).
        chunk_gamma: ``None`` (default): the outer transition's ``("next", "reward")``
            is the reward of the chunk's last executed step — 0 when a ``done``
            inside the chunk cut it short (``MultiAction(stack_rewards=False)``),
            enough for evaluation. A float: the chunk's discounted return
            ``sum_i chunk_gamma**i * r_i`` (:class:`ChunkReward`), what RL fine-tuning needs.

    ``("next", "step_count")`` counts inner steps.

    Examples (``model``: an :class:`MMaDAModel`; 10 decisions of 2 executed steps make 20 env steps):
        >>> penv = make_policy_env(EnvConfig("PickCube-v1"), MMaDAActor(model), execute_steps=2)  # doctest: +SKIP
        >>> rollout = penv.env.rollout(10, penv.policy)  # doctest: +SKIP
        >>> rollout["next", "step_count"][-1]  # doctest: +SKIP
        tensor([20])
    """
    chunk_size = actor.chunk_size
    if temporal_ensemble:
        if execute_steps not in (None, 1):
            raise ValueError(f"temporal_ensemble replans at every step: execute_steps must be 1 (or None), got {execute_steps!r}.")
        execute_steps = 1
    k = check_execute_steps(execute_steps, chunk_size)
    inner = make_env(env) if isinstance(env, EnvConfig) else env
    if inner.batch_size and inner.device is None:
        # a ParallelEnv without a device returns device-less instructions, except after the partial
        # step of a done inside a chunk (device cpu): rollouts then fail to stack (TorchRL 0.14.1)
        inner = inner.to("cpu")
    step_log = StepLog(log_keys) if log_keys else None
    chunker = MultiAction(stack_rewards=False) if chunk_gamma is None else ChunkReward(chunk_gamma)
    transforms = [chunker, InitTracker()]  # InitTracker after: once per decision
    if step_log is not None:
        transforms.insert(0, step_log)  # before MultiAction: called at every inner step
    # auto_unwrap=False: leave the given env intact (TorchRL would otherwise move its
    # transforms into this env's Compose, re-parenting them when an env is wrapped twice)
    outer = TransformedEnv(inner, Compose(*transforms), auto_unwrap=False)
    runner = actor if actor.execute_steps == k else actor.get_new_version(execute_steps=k)
    policy = TemporalEnsemble(runner, ensemble_decay) if temporal_ensemble else runner
    return PolicyEnv(outer, policy, runner, step_log)
