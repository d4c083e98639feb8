"""The MMaDA-VLA policy as a TorchRL actor.

:class:`MMaDAActor` subclasses TorchRL's :class:`~torchrl.modules.vla.VLAWrapperBase`
with the ``"tokens"`` action head. It reads the canonical VLA observation keys and
writes, under ``"vla_action"``::

    ("vla_action", "chunk")       float [*B, K, A]     the decoded chunk, env units
    ("vla_action", "tokens")      long  [*B, K, d_tok] its action tokens (local codes)
    ("vla_action", "log_probs")   float [*B]           log-probability of the decoding path
    ("vla_action", "goal_image")  uint8 [*B, 3, H, W]  predicted goal o_{t+K} (when the model predicts it)
    ("vla_action", "path")        DecodingPath [*B]    what ``path_log_prob`` needs to rescore it
    "action"                      float [*B, k, A]     the first ``execute_steps`` actions

The two keys the base class does not define (``goal_image``, ``path``) are
defined here only: :data:`PREDICTED_GOAL_IMAGE_KEY` and :data:`DECODING_PATH_KEY`.
``mmada_rl.keys.GOAL_IMAGE_KEY`` (``("goal", "image")``) is the *recorded* future
frame of the data; a prediction gets its own key so it never overwrites it.

The base class samples one categorical per action token; a masked-diffusion
policy instead decodes all targets jointly in ``N`` refinement steps, so
:meth:`MMaDAActor.forward` and :meth:`MMaDAActor.log_prob` are overridden and
``get_dist`` is not available.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import InteractionType
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torchrl.modules.vla import VLAWrapperBase

from mmada_rl.diffusion.path import path_log_prob
from mmada_rl.keys import IMAGE_KEY, INSTRUCTION_KEY, STATE_KEY, VLA_ACTION_KEY
from mmada_rl.policy.model import MMaDAModel

__all__ = ["ChunkExecutionMixin", "DECODING_PATH_KEY", "MMaDAActor", "PREDICTED_GOAL_IMAGE_KEY", "check_execute_steps"]

#: The goal image ``o_{t+K}`` the policy predicts with its chunk, uint8 ``[*B, 3, H, W]``.
PREDICTED_GOAL_IMAGE_KEY = (VLA_ACTION_KEY, "goal_image")
#: The :class:`~mmada_rl.diffusion.path.DecodingPath` of the sampled chunk, batch ``[*B]``.
DECODING_PATH_KEY = (VLA_ACTION_KEY, "path")


def check_execute_steps(execute_steps: int | None, chunk_size: int) -> int:
    """``execute_steps`` (``None`` → ``chunk_size``), checked to lie in ``[1, chunk_size]``."""
    if execute_steps is None:
        return chunk_size
    if isinstance(execute_steps, bool) or not isinstance(execute_steps, int) or not 1 <= execute_steps <= chunk_size:
        raise ValueError(
            f"execute_steps must be an int in [1, chunk_size={chunk_size}] (actions executed per chunk "
            f"before replanning), got {execute_steps!r}."
        )
    return execute_steps


class ChunkExecutionMixin:
    """What every chunk policy shares on top of ``VLAWrapperBase``: the interaction-type
    readout and copies with other runtime settings (``execute_steps`` checked)."""

    def get_new_version(self, **kwargs):
        """A shallow copy sharing the weights, with other runtime settings (e.g. ``execute_steps=1``)."""
        if "execute_steps" in kwargs:
            kwargs["execute_steps"] = check_execute_steps(kwargs["execute_steps"], self.chunk_size)
        return super().get_new_version(**kwargs)

    def is_greedy(self) -> bool:
        """Whether the current interaction type (or the default one) asks for deterministic inference."""
        current = interaction_type()
        if current is None:
            current = self.default_interaction_type
        return current != InteractionType.RANDOM


class MMaDAActor(ChunkExecutionMixin, VLAWrapperBase):
    """TorchRL actor around an :class:`~mmada_rl.policy.model.MMaDAModel`.

    Decoding is greedy under ``set_exploration_type(ExplorationType.DETERMINISTIC)``
    (also ``MODE``/``MEAN``) and sampled under ``RANDOM``; with no exploration
    context, ``default_interaction_type`` decides (deterministic by default).
    Works on unbatched tensordicts (batch ``[]``, one env's output) and on any
    batch ``[*B]`` (e.g. a ``ParallelEnv``'s ``[N]``).

    Args:
        model: the policy (tokenizers, layout, denoiser, sampler).

    Keyword Args:
        execute_steps: actions of each chunk written to ``"action"`` for the env
            to execute before replanning, ``1 <= k <= K``; ``None`` (default): the
            whole chunk (open loop, the authors' choice).
        generator: RNG for sampled decoding (``None``: torch's global RNG). A
            ``generator=`` keyword of a call overrides it for that call.
        return_vla_action_container: write a ``VLAAction`` tensorclass at
            ``"vla_action"`` instead of a plain TensorDict (the keys are the same).
            Off by default: plain TensorDicts stack and persist in replay
            buffers without ``None`` fields.
        **kwargs: other :class:`~torchrl.modules.vla.VLAWrapperBase` keywords
            (key names, ``default_interaction_type``, ``inplace``...).

    Attributes:
        last_decode_seconds: wall time of the last ``model.act`` call.

    Examples (``model``: an :class:`MMaDAModel` with ``chunk_size=5``; ``env``: one ManiSkill env, batch ``[]``):
        >>> import torch
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> actor = MMaDAActor(model, execute_steps=2)  # doctest: +SKIP
        >>> td = env.reset()  # doctest: +SKIP
        >>> td = actor(td)  # doctest: +SKIP
        >>> td["vla_action", "chunk"].shape, td["action"].shape  # doctest: +SKIP
        (torch.Size([5, 7]), torch.Size([2, 7]))
        >>> td["vla_action", "log_probs"].shape  # doctest: +SKIP
        torch.Size([])
        >>> with set_exploration_type(ExplorationType.RANDOM):  # doctest: +SKIP
        ...     sampled = actor(env.reset(), generator=torch.Generator().manual_seed(0))
    """

    @dataclass
    class _AcceptedKeys(VLAWrapperBase._AcceptedKeys):
        """The base class's keys plus the predicted goal image and the decoding path."""

        goal_image: NestedKey = PREDICTED_GOAL_IMAGE_KEY
        decoding_path: NestedKey = DECODING_PATH_KEY

    def __init__(
        self,
        model: MMaDAModel,
        *,
        execute_steps: int | None = None,
        generator: torch.Generator | None = None,
        return_vla_action_container: bool = False,
        **kwargs,
    ) -> None:
        if kwargs.get("log_probs_mode", "sequence") != "sequence":
            raise ValueError(
                f"log_probs_mode must be 'sequence' (one log-probability per decoding path), got {kwargs['log_probs_mode']!r}."
            )
        for name in ("action_head", "output_mode", "vocab_size", "action_dim", "chunk_size", "action_tokenizer"):
            if name in kwargs:
                raise ValueError(f"{name} is fixed by the model; do not pass {name}={kwargs[name]!r}.")
        self.predict_goal = bool(model.config.predict_goal)
        super().__init__(
            model,
            action_head="tokens",
            output_mode="both",
            action_dim=model.action_tokenizer.action_dim,
            chunk_size=model.config.chunk_size,
            vocab_size=model.action_tokenizer.vocab_size,
            action_tokenizer=model.action_tokenizer,
            use_state=model.proprio_tokenizer is not None,
            return_vla_action_container=return_vla_action_container,
            **kwargs,
        )
        self.execute_steps = check_execute_steps(execute_steps, self.chunk_size)
        self.generator = generator
        self.last_decode_seconds = float("nan")

    # -- keys ---------------------------------------------------------------
    def _update_keys(self) -> None:
        super()._update_keys()
        keys = self._tensor_keys
        extra = [keys.decoding_path, keys.action]
        if self.predict_goal:
            extra.insert(0, keys.goal_image)
        self.out_keys = [*self.out_keys, *extra]

    #: our fields under the ``vla_action`` root: (accepted-key name, field name)
    _OWN_FIELDS = (("goal_image", "goal_image"), ("decoding_path", "path"))

    def set_keys(self, **kwargs) -> MMaDAActor:
        """Set key names; renaming ``vla_action`` also moves ``goal_image`` and ``decoding_path`` under it."""
        old_root = self._tensor_keys.vla_action
        defaults = {name: self._vla_field_key(old_root, field) for name, field in self._OWN_FIELDS}
        super().set_keys(**kwargs)
        if "vla_action" in kwargs:
            for name, field in self._OWN_FIELDS:
                if name not in kwargs and getattr(self._tensor_keys, name) == defaults[name]:
                    setattr(self._tensor_keys, name, self._vla_field_key(self._tensor_keys.vla_action, field))
            self._update_keys()
        return self

    # -- decoding -------------------------------------------------------------
    def _observation(self, tensordict: TensorDictBase) -> TensorDict:
        """The inputs under the canonical keys ``model.act`` reads, batch ``[B]``, on the model's device."""
        device = next(self.model.denoiser.parameters()).device
        obs = TensorDict({IMAGE_KEY: self._get_image(tensordict)}, batch_size=tensordict.batch_size)
        obs.set(INSTRUCTION_KEY, self._get_instruction(tensordict))
        if self.use_state and self._tensor_keys.state is not None:
            obs.set(STATE_KEY, self._get_state(tensordict))
        return obs.reshape(-1).to(device)  # (B,)

    def forward(
        self,
        tensordict: TensorDictBase,
        *,
        tensordict_out: TensorDictBase | None = None,
        generator: torch.Generator | None = None,
        **kwargs,
    ) -> TensorDictBase:
        """Decode one chunk per observation of ``tensordict`` (batch ``[*B]``)."""
        if kwargs.get("logits_only"):
            raise ValueError("logits_only=True is not supported: a masked-diffusion policy has no single-step logits.")
        batch = tensordict.batch_size
        obs = self._observation(tensordict)  # (B,)
        start = time.perf_counter()
        result = self.model.act(obs, greedy=self.is_greedy(), generator=generator or self.generator)
        self.last_decode_seconds = time.perf_counter() - start
        flat = TensorDict(
            {
                "chunk": result.chunk,  # (B, K, A)
                "tokens": result.action_tokens,  # (B, K, d_tok)
                "log_probs": result.log_prob,  # (B,)
                "path": result.path,  # DecodingPath (B,)
            },
            batch_size=obs.batch_size,
        )
        if self.predict_goal:
            flat.set("goal_image", result.goal_image)  # (B, 3, H, W) uint8
        home = tensordict.device or self._get_image(tensordict).device  # where the env reads the action
        flat = flat.reshape(batch).to(home)  # (*B,): [] for an unbatched env
        out = TensorDict({}, batch_size=batch, device=tensordict.device)
        self._set_action(out, chunk=flat["chunk"], tokens=flat["tokens"], log_probs=flat["log_probs"])
        keys = self._tensor_keys
        if self.predict_goal:
            out.set(keys.goal_image, flat["goal_image"])
        out.set(keys.decoding_path, flat.get("path"))
        out.set(keys.action, flat["chunk"][..., : self.execute_steps, :])  # (*B, k, A)
        return self._output_tensordict(tensordict, out, tensordict_out)

    # -- log-probabilities for RL -------------------------------------------------
    def log_prob(self, tensordict: TensorDictBase, *, log_probs_key: NestedKey | None = None, **kwargs) -> TensorDictBase:
        """Rescore the stored decoding paths under the current parameters; writes ``[*B]`` log-probs.

        Gradients flow to the denoiser (call it inside ``torch.no_grad()`` when
        none are needed). Put the model in ``eval()`` to match the sampler.
        """
        path = tensordict.get(self._tensor_keys.decoding_path)
        batch = tensordict.batch_size
        flat = path.reshape(-1).to(next(self.model.denoiser.parameters()).device)  # (B,)
        visual = self.model.visual_input(tensordict)  # the observation images, with cross-attention
        if visual is not None:
            visual = visual.to(flat.inputs.device)
        log_probs = path_log_prob(self.model.denoiser, flat, visual).reshape(batch)  # (*B,)
        tensordict.set(self._tensor_keys.log_probs if log_probs_key is None else log_probs_key, log_probs)
        return tensordict

    def get_dist(self, *args, **kwargs):
        raise NotImplementedError(
            "MMaDAActor has no per-token distribution: chunks come from N joint refinement steps. "
            "Use actor.log_prob(td) (or mmada_rl.diffusion.path.path_log_prob) on the stored decoding path."
        )
