"""One object that turns observations into the unified token sequence and back.

:class:`MMaDAModel` owns the frozen tokenizers (text, image, action and — when
proprioception is on — a per-dimension bin tokenizer for the state), the
:class:`~mmada_rl.tokenizers.vocabulary.UnifiedVocabulary`, the
:class:`~mmada_rl.tokenizers.layout.SequenceLayout` and the trainable
:class:`~mmada_rl.diffusion.denoiser.MaskedDiffusionDenoiser`. It does three things:

* :meth:`sequence` — a training sample (instruction, image and state at ``t``,
  goal image ``o_{t+K}``, action chunk) → clean global ids ``[B, L]``;
* :meth:`prompt` — an observation → ids whose targets are ``[MASK]``;
* :meth:`act` — sample the targets with the parallel decoder and decode them
  into an action chunk (env units) and a predicted goal image.

It saves to / loads from one directory (tokenizers, vocabulary, layout and
denoiser configs, weights), so a checkpoint describes itself.
"""
from __future__ import annotations

import json
import warnings
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

import torch
from safetensors.torch import load_file, save_file
from tensordict import TensorDict, TensorDictBase
from torch import nn

from mmada_rl.data.windows import append_state_differences, check_state_differences, kept_state_dims, pad_state
from mmada_rl.diffusion.denoiser import DenoiserConfig, MaskedDiffusionDenoiser
from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY
from mmada_rl.diffusion.path import DecodingPath
from mmada_rl.diffusion.sampler import MaskedDiffusionSampler, SamplerConfig, is_greedy
from mmada_rl.envs.maniskill import EnvConfig, task_camera_fov
from mmada_rl.instructions import instruction_texts
from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_GRIPPER_ONLY_KEY,
    ACTION_IS_PAD_KEY,
    GOAL_IMAGE_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    SEQUENCE_KEY,
    STATE_KEY,
)
from mmada_rl.tokenizers.bundle import Tokenizers
from mmada_rl.tokenizers.normalize import ActionOutOfRangeWarning
from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig

MODEL_CONFIG = "model.json"
MODEL_WEIGHTS = "denoiser.safetensors"
TOKENIZERS_DIR = "tokenizers"


#: How a greedy chunk becomes actions (:attr:`MMaDAConfig.action_readout`).
ACTION_READOUTS = ("token", "mean")


def _check_action_readout(readout: str) -> None:
    if readout not in ACTION_READOUTS:
        raise ValueError(f"action_readout must be one of {ACTION_READOUTS}, got {readout!r}.")


@dataclass
class MMaDAConfig:
    """Architecture of the policy (everything but the tokenizers' own configs).

    Attributes:
        chunk_size: actions per chunk ``K``.
        predict_goal: generate the goal image ``o_{t+K}`` together with the chunk.
        use_proprio: put the proprioceptive state into the sequence as tokens.
        observation_tokens: put the observation image's codes into the sequence. ``False``:
            the image reaches the denoiser only through its own CNN features, by cross-attention
            (needs ``denoiser_overrides.visual_encoder_channels``): visual features instead of
            image tokens in the sequence; the image tokenizer then serves the goal image alone.
        proprio_drop_dims: state dimensions left out of the sequence (their tokens
            are dropped; the proprio tokenizer still covers every dimension, so a
            tokenizer directory serves runs with and without them). E.g.
            ``[9, ..., 17]``: the Panda's joint velocities, which let a policy copy
            its own motion from the demonstrations' pauses (the copycat problem).
        state_differences: pairs ``[a, b]`` of state dimensions whose difference
            ``state[a] - state[b]`` is appended to the state before it is tokenized, as
            dimensions ``D, D + 1, ...`` after the state's ``D`` (so ``proprio_drop_dims`` and
            state dropout can name them). The proprio tokenizer must be fitted on the state
            with them appended (``TokenizerFitConfig.state_differences``). E.g.
            ``[[26, 19], [27, 20], [28, 21]]``: PickCube-v1's goal relative to the gripper,
            which the policy otherwise has to work out from two separately binned tokens.
        interleave: interleave goal and action tokens.
        denoiser: a preset name (``tiny``, ``small``, ``base``) or a full config dict.
        denoiser_overrides: fields overriding the preset (e.g. ``{"attention": "block_causal"}``).
        sampler: parallel-decoding options.
        camera_fov: field of view (degrees) of the camera whose images the policy was
            trained on; ``None``: the task's own. Evaluation builds its env with it. A
            multi-task model may map each task to its own (``{"PushCube-v1": 60.0,
            "PickCube-v1": 45.0}``; see :meth:`camera_fov_for`).
        action_readout: how a greedily decoded chunk becomes actions: ``"token"`` (the
            committed bins' centres, the paper's) or ``"mean"`` (each dimension's expected
            value under the distribution its token was committed from; uniform-bin action
            tokens only). Sampled chunks always execute their tokens, so the log-probabilities
            fine-tuning records describe the executed actions.
    """

    chunk_size: int = 5
    predict_goal: bool = True
    use_proprio: bool = True
    observation_tokens: bool = True
    proprio_drop_dims: list[int] = field(default_factory=list)
    state_differences: list[list[int]] = field(default_factory=list)
    interleave: bool = False
    denoiser: str | dict = "small"
    denoiser_overrides: dict = field(default_factory=dict)
    sampler: dict = field(default_factory=dict)
    camera_fov: float | dict[str, float | None] | None = None
    action_readout: str = "token"

    def __post_init__(self) -> None:
        if not isinstance(self.chunk_size, int) or self.chunk_size < 1:
            raise ValueError(f"chunk_size must be a positive int, got {self.chunk_size!r}.")
        self.proprio_drop_dims = sorted({int(d) for d in self.proprio_drop_dims})
        if self.proprio_drop_dims and not self.use_proprio:
            raise ValueError(f"proprio_drop_dims={self.proprio_drop_dims} needs use_proprio=True.")
        self.state_differences = check_state_differences(self.state_differences)
        if self.state_differences and not self.use_proprio:
            raise ValueError(f"state_differences={self.state_differences} needs use_proprio=True.")
        _check_action_readout(self.action_readout)
        if isinstance(self.camera_fov, Mapping):
            self.camera_fov = {str(task): None if fov is None else float(fov) for task, fov in self.camera_fov.items()}
        for task in self.camera_fov if isinstance(self.camera_fov, dict) else [None]:
            EnvConfig(**({"task": task} if task else {}), camera_fov=self.camera_fov_for(task))  # validates
        denoiser = self.denoiser_config()  # validates
        if not self.observation_tokens and denoiser.visual_encoder_channels is None:
            raise ValueError("observation_tokens=false leaves the policy blind unless the denoiser encodes the "
                             "image itself: set denoiser_overrides.cross_attention_to_visual=true and "
                             "visual_encoder_channels (e.g. [32, 64, 128]).")
        self.sampler_config()

    def camera_fov_for(self, task: str | None) -> float | None:
        """The field of view (degrees) of ``task``'s camera in the training images (``None``: the task's own)."""
        return task_camera_fov(self.camera_fov, task)

    def denoiser_config(self) -> DenoiserConfig:
        if isinstance(self.denoiser, str):
            return DenoiserConfig.preset(self.denoiser, **self.denoiser_overrides)
        return DenoiserConfig(**{**self.denoiser, **self.denoiser_overrides})

    def sampler_config(self) -> SamplerConfig:
        return SamplerConfig(**self.sampler)


class PolicyOutput(NamedTuple):
    """What :meth:`MMaDAModel.act` returns."""

    chunk: torch.Tensor  # (B, K, A) env units
    action_tokens: torch.Tensor  # (B, K, d_tok) local codes
    goal_tokens: torch.Tensor | None  # (B, g, g) local codes
    goal_image: torch.Tensor | None  # (B, 3, H, W) uint8
    path: DecodingPath
    log_prob: torch.Tensor  # (B,) log-probability of the decoding path


def instructions_of(td: TensorDictBase) -> list[str]:
    """The instruction texts of a tensordict, one per batch element."""
    return instruction_texts(td.get(INSTRUCTION_KEY), td.batch_size)


class MMaDAModel(nn.Module):
    """Tokenizers, vocabulary, layout and denoiser of the MMaDA-VLA policy.

    Args:
        config: architecture options.
        tokenizers: fitted tokenizers (kept frozen).
        state_dim: size of the proprioceptive state (needed when ``use_proprio``).

    Examples (``tokenizers`` fitted on demonstrations; ``sequence`` is the clean ``(B, L)`` training sequence,
    ``act`` returns a :class:`PolicyOutput` with ``chunk`` of shape ``(B, 5, 7)``):
        >>> model = MMaDAModel(MMaDAConfig(chunk_size=5, denoiser="tiny"), tokenizers)  # doctest: +SKIP
        >>> ids = model.sequence(batch)  # doctest: +SKIP
        >>> out = model.act(observation_td)  # doctest: +SKIP
    """

    def __init__(self, config: MMaDAConfig, tokenizers: Tokenizers):
        super().__init__()
        self.config = config
        if config.use_proprio and tokenizers.proprio is None:
            raise ValueError("use_proprio=True needs a proprio tokenizer (Tokenizers.proprio).")
        self.text_tokenizer = tokenizers.text
        self.image_tokenizer = tokenizers.image
        self.action_tokenizer = tokenizers.action
        self.proprio_tokenizer = tokenizers.proprio if config.use_proprio else None
        for tok in self.tokenizers():
            tok.requires_grad_(False).eval()
        self._check_state_differences()
        self.register_buffer("proprio_index", self._proprio_index(), persistent=False)
        grid = self.image_tokenizer.config.grid_size
        self.vocab = UnifiedVocabulary(
            VocabularyConfig(
                text_vocab_size=self.text_tokenizer.vocab_size,
                image_codebook_size=self.image_tokenizer.vocab_size,
                action_codebook_size=self.action_tokenizer.vocab_size,
                proprio_codebook_size=self.proprio_tokenizer.vocab_size if self.proprio_tokenizer else 0,
            )
        )
        self.layout = SequenceLayout(
            LayoutConfig(
                text_tokens=self.text_tokenizer.max_len,
                obs_tokens=self.image_tokenizer.tokens_per_image if config.observation_tokens else 0,
                goal_tokens=self.image_tokenizer.tokens_per_image if config.predict_goal else 0,
                chunk_size=config.chunk_size,
                tokens_per_action=self.action_tokenizer.tokens_per_action,
                proprio_tokens=len(self.proprio_index) if self.proprio_tokenizer else 0,
                interleave=config.interleave,
                image_grid=(grid, grid),
            ),
            self.vocab,
        )
        denoiser_config = config.denoiser_config()
        if denoiser_config.proprio_value_embedding and not (
            self.proprio_tokenizer is not None and self.proprio_tokenizer.has_ordered_bins
        ):
            raise ValueError("denoiser_overrides.proprio_value_embedding=true needs proprio tokens that are ordered "
                             "bins (use_proprio=true and a bin proprio tokenizer).")
        if denoiser_config.action_value_embedding:
            self.action_tokenizer.require_ordered_bins("denoiser_overrides.action_value_embedding=true embeds the value "
                                                       "of each action token's bin")
        self.denoiser = MaskedDiffusionDenoiser(denoiser_config, self.layout)
        if self.denoiser.config.cross_attention_to_visual and self.denoiser.visual_encoder is None:
            raise ValueError("the policy's cross-attention needs the denoiser to encode the observation image: "
                             "set denoiser_overrides.visual_encoder_channels (e.g. [32, 64, 128]).")
        self.sampler = MaskedDiffusionSampler(config.sampler_config())
        self.set_action_readout(config.action_readout)

    def set_action_readout(self, readout: str) -> None:
        """How greedy chunks become actions from now on (:attr:`MMaDAConfig.action_readout`;
        evaluation switches it for one run)."""
        _check_action_readout(readout)
        if readout == "mean":
            self.action_tokenizer.require_ordered_bins("action_readout='mean' reads each action token's expected bin")
        self.action_readout = readout

    @contextmanager
    def decoding(self, *, num_steps: int | None = None, temperature: float | None = None,
                 readout: str | None = None) -> Iterator[MMaDAModel]:
        """Decode with ``num_steps`` (N), sampling ``temperature`` and action ``readout`` inside the block
        (None keeps the policy's own); the sampler and read-out are restored on exit, also on error.

            >>> with model.decoding(num_steps=1, readout="mean"):  # doctest: +SKIP
            ...     chunk = model.act(td, greedy=True).chunk
        """
        saved_sampler, saved_readout = self.sampler, self.action_readout
        try:
            if readout is not None:
                self.set_action_readout(readout)
            overrides = {k: v for k, v in {"num_steps": num_steps, "temperature": temperature}.items() if v is not None}
            if overrides:
                self.sampler = MaskedDiffusionSampler(SamplerConfig(**{**asdict(saved_sampler.config), **overrides}))
            yield self
        finally:
            self.sampler, self.action_readout = saved_sampler, saved_readout

    @property
    def state_dim(self) -> int | None:
        """Size of the (zero-padded) state the policy reads, before ``state_differences`` are appended."""
        if self.proprio_tokenizer is None:
            return None
        return self.proprio_tokenizer.config.action_dim - len(self.config.state_differences)

    def _check_state_differences(self) -> None:
        pairs = self.config.state_differences
        if not pairs or self.proprio_tokenizer is None:
            return
        self._check_one_token_per_state_dim("state_differences")
        if max(max(pair) for pair in pairs) >= self.state_dim:
            covers = self.proprio_tokenizer.config.action_dim
            raise ValueError(f"state_differences={pairs} need a proprio tokenizer fitted with them: this one covers "
                             f"{covers} dimensions, so with {len(pairs)} differences appended the state has only "
                             f"{self.state_dim}, fewer than the pairs name. Fit it on the state with them appended "
                             "(TokenizerFitConfig.state_differences, `mmada-rl fit-tokenizers --state-differences`).")

    def _proprio_index(self) -> torch.Tensor:
        """Which of the proprio tokenizer's tokens enter the sequence (all but ``proprio_drop_dims``)."""
        tok = self.proprio_tokenizer
        if tok is None:
            return torch.zeros(0, dtype=torch.long)
        drop, dims = self.config.proprio_drop_dims, tok.config.action_dim
        if not drop:
            return torch.arange(tok.tokens_per_action)  # every token, whatever the tokenizer
        self._check_one_token_per_state_dim("proprio_drop_dims")
        return torch.tensor(kept_state_dims(drop, dims, "proprio_drop_dims"), dtype=torch.long)

    def _check_one_token_per_state_dim(self, what: str) -> None:
        """Raise unless the proprio tokenizer writes one token per state dimension (``what`` maps dims onto tokens)."""
        tok = self.proprio_tokenizer
        if tok is None:
            raise ValueError(f"{what} needs proprio tokens in the sequence (model.use_proprio=True).")
        if tok.tokens_per_action != tok.config.action_dim:
            raise ValueError(f"{what} needs one proprio token per state dimension, but the proprio "
                             f"tokenizer writes {tok.tokens_per_action} tokens for {tok.config.action_dim} dimensions.")

    def proprio_segment_index(self, dims) -> torch.Tensor:
        """Where the state dimensions ``dims`` sit in the sequence's proprio segment (one token each).

        Raises:
            ValueError: without one proprio token per state dimension, or if a
                dimension is outside the state or left out (``proprio_drop_dims``).
        """
        self._check_one_token_per_state_dim("mapping state dimensions onto proprio tokens")
        read = self.proprio_index.tolist()
        missing = [int(d) for d in dims if int(d) not in read]
        if missing:
            raise ValueError(f"state dimensions {missing} are not in the sequence: it reads {read} (of "
                             f"0..{self.proprio_tokenizer.config.action_dim - 1}, "
                             f"proprio_drop_dims={self.config.proprio_drop_dims}).")
        return torch.tensor([read.index(int(d)) for d in dims], dtype=torch.long)

    def proprio_drop_index(self, keep_dims, name: str = "proprio_drop_keep_dims") -> list[int] | None:
        """The proprio tokens state dropout masks when it leaves the state dimensions ``keep_dims`` readable:
        every other token of the segment (None when ``keep_dims`` is empty: state dropout masks them all).
        ``name``: what the error calls ``keep_dims`` (a recipe's config key).

        Raises:
            ValueError: as :meth:`proprio_segment_index`, or if ``keep_dims`` keeps every token (nothing to mask).
        """
        keep = [int(d) for d in keep_dims or []]
        if not keep:
            return None
        keep_at = set(self.proprio_segment_index(keep).tolist())
        dropped = [i for i in range(len(self.proprio_index)) if i not in keep_at]
        if not dropped:
            raise ValueError(f"{name}={keep} keeps every state dimension in the sequence: "
                             "state dropout would mask nothing.")
        return dropped

    def tokenizers(self) -> list[nn.Module]:
        return [t for t in (self.text_tokenizer, self.image_tokenizer, self.action_tokenizer, self.proprio_tokenizer) if t is not None]

    def train(self, mode: bool = True):
        super().train(mode)
        for tok in self.tokenizers():  # frozen: batch statistics and EMA codebooks never move
            tok.eval()
        return self

    @property
    def image_size(self) -> int:
        return self.image_tokenizer.config.image_size

    @property
    def device(self) -> torch.device:
        """Where the denoiser's weights are; the sequence methods move their inputs there."""
        return next(self.denoiser.parameters()).device

    # -- sequence construction ------------------------------------------------
    @torch.no_grad()
    def _condition(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        batch = td.batch_size
        image = td.get(IMAGE_KEY)
        if image.shape[-1] != self.image_size or image.shape[-2] != self.image_size:
            raise ValueError(
                f"observation images are {tuple(image.shape[-2:])} but the image tokenizer was fitted on "
                f"{self.image_size}x{self.image_size}; use env image_size={self.image_size}."
            )
        text = self.text_tokenizer.encode(instructions_of(td)).ids.to(image.device)  # (B, L_t)
        obs_tokens = self.layout.config.obs_tokens  # 0: the image reaches the denoiser through its CNN alone
        out = {
            "text_ids": text.reshape(-1, text.shape[-1]),
            "obs_ids": self.image_tokenizer.encode(image).reshape(-1, obs_tokens) if obs_tokens else None,
        }
        if self.proprio_tokenizer is not None:
            # a multi-task model's tokenizer spans the largest state; smaller task states are zero-padded
            state = td.get(STATE_KEY)
            if state.shape[-1] > self.state_dim and self.config.state_differences:
                raise ValueError(f"the state has {state.shape[-1]} dimensions but the proprio tokenizer covers "
                                 f"{self.state_dim} before the {len(self.config.state_differences)} state_differences: "
                                 "fit it with the model's state_differences on these tasks' states.")
            state = append_state_differences(pad_state(state, self.state_dim), self.config.state_differences)
            with warnings.catch_warnings():
                # states beyond the demonstrations' range are clipped to the edge bins at every step
                # of a rollout; the normaliser still counts them (proprio_tokenizer.normalizer.num_out_of_range)
                warnings.simplefilter("ignore", ActionOutOfRangeWarning)
                proprio = self.proprio_tokenizer.encode(state)
            out["proprio_ids"] = proprio.reshape(-1, proprio.shape[-1])[:, self.proprio_index.to(proprio.device)]
        if batch and out["text_ids"].shape[0] != batch.numel():
            raise ValueError(f"{out['text_ids'].shape[0]} instructions for a batch of {tuple(batch)}.")
        return out

    def visual_input(self, td: TensorDictBase) -> torch.Tensor | None:
        """The denoiser's visual input for observations ``td``: the images ``[B, 3, H, W]``
        when it cross-attends to its own CNN features of them, else ``None``."""
        if self.denoiser.visual_encoder is None:
            return None
        image = td.get(IMAGE_KEY)
        return image.reshape(-1, *image.shape[-3:]).to(self.device)

    @torch.no_grad()
    def sequence(self, td: TensorDictBase, action_tokens: torch.Tensor | None = None) -> torch.Tensor:
        """Clean global ids ``[B, L]`` of training windows (needs the chunk and, if predicted, the goal image).

        ``action_tokens`` (local codes ``[B, K, d_tok]``, e.g. the ones a rollout
        sampled) are used as they are instead of re-encoding the chunk.
        """
        td = td.to(self.device)  # windows sampled from a CPU buffer for a model on an accelerator
        cond = self._condition(td)
        if action_tokens is None:
            chunk = td.get(ACTION_CHUNK_KEY)  # (B, K, A)
            if chunk.shape[-2] != self.config.chunk_size:
                raise ValueError(f"action chunks hold {chunk.shape[-2]} actions but the model's chunk_size is {self.config.chunk_size}.")
            with warnings.catch_warnings():
                # demonstrations beyond the 1st/99th percentiles are clipped by design (counted, not warned per batch)
                warnings.simplefilter("ignore", ActionOutOfRangeWarning)
                actions = self.action_tokenizer.encode(chunk)  # (B, K, d_tok)
        else:
            actions = action_tokens.reshape(-1, *action_tokens.shape[-2:]).to(self.device)
            if actions.shape[-2] != self.config.chunk_size:
                raise ValueError(f"action_tokens hold {actions.shape[-2]} actions but the model's chunk_size is {self.config.chunk_size}.")
        goal = self.image_tokenizer.encode(td.get(GOAL_IMAGE_KEY)) if self.config.predict_goal else None
        return self.layout.assemble(goal_ids=goal, action_ids=actions, **cond)

    def loss_inputs(self, windows: TensorDictBase) -> TensorDict:
        """What a masked-diffusion loss reads from a batch of chunk windows: the clean
        sequence ``[B, L]``, the chunk's padding flags ``[B, K]`` (and its gripper-only flags ``[B]``
        where the windows carry them) and, with
        cross-attention, the visual input (:meth:`visual_input`)."""
        windows = windows.to(self.device)
        ids = self.sequence(windows)
        rows = TensorDict({SEQUENCE_KEY: ids, ACTION_IS_PAD_KEY: windows.get(ACTION_IS_PAD_KEY)},
                          batch_size=[ids.shape[0]], device=ids.device)
        gripper_only = windows.get(ACTION_GRIPPER_ONLY_KEY, None)
        if gripper_only is not None:
            rows.set(ACTION_GRIPPER_ONLY_KEY, gripper_only)
        visual = self.visual_input(windows)
        if visual is not None:
            rows.set(VISUAL_FEATURES_KEY, visual)
        return rows

    @torch.no_grad()
    def prompt(self, td: TensorDictBase) -> torch.Tensor:
        """Ids ``[B, L]`` of an observation with every target position masked."""
        return self.layout.assemble(**self._condition(td.to(self.device)))

    @torch.no_grad()
    def act(self, td: TensorDictBase, *, greedy: bool | None = None, generator: torch.Generator | None = None,
            decode_goal: bool = True) -> PolicyOutput:
        """Sample a chunk (and goal image) for a batch of observations ``td`` (batch ``[B]``)."""
        was_training = self.denoiser.training
        self.denoiser.eval()
        mean = self.action_readout == "mean" and is_greedy(greedy)
        try:
            result = self.sampler.sample(self.denoiser, self.prompt(td), visual=self.visual_input(td),
                                         greedy=greedy, generator=generator, action_probs=mean)
        finally:
            self.denoiser.train(was_training)
        if mean:
            chunk = self.action_tokenizer.decode_mean(result.action_probs)  # (B, K, A)
        else:
            chunk = self.action_tokenizer.decode(result.action_tokens)  # (B, K, A)
        goal_image = None
        if result.goal_tokens is not None and decode_goal:
            grid = self.image_tokenizer.config.grid_size
            goal_image = self.image_tokenizer.decode(result.goal_tokens.reshape(-1, grid, grid))
        return PolicyOutput(chunk, result.action_tokens, result.goal_tokens, goal_image, result.path, result.path.log_prob)

    # -- persistence -------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write the whole policy into ``directory``: tokenizers, configs, denoiser weights."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        Tokenizers(self.text_tokenizer, self.image_tokenizer, self.action_tokenizer, self.proprio_tokenizer).save(
            directory / TOKENIZERS_DIR
        )
        payload = {
            "config": {**asdict(self.config), "action_readout": self.action_readout},  # as switched last
            "vocabulary": self.vocab.to_dict(),
            "layout": self.layout.to_dict(),
            "num_parameters": sum(p.numel() for p in self.denoiser.parameters()),
        }
        tmp = directory / f".{MODEL_CONFIG}.tmp"
        tmp.write_text(json.dumps(payload, indent=2))
        tmp.replace(directory / MODEL_CONFIG)
        tmp = directory / f".{MODEL_WEIGHTS}.tmp"
        save_file({k: v.contiguous() for k, v in self.denoiser.state_dict().items()}, str(tmp))
        tmp.replace(directory / MODEL_WEIGHTS)
        return directory

    @classmethod
    def load(cls, directory: str | Path, *, device: str | torch.device = "cpu") -> MMaDAModel:
        directory = Path(directory)
        if not (directory / MODEL_CONFIG).exists():
            raise FileNotFoundError(f"{directory} holds no MMaDA policy ({MODEL_CONFIG} missing).")
        payload = json.loads((directory / MODEL_CONFIG).read_text())
        config = MMaDAConfig(**payload["config"])
        model = cls(config, Tokenizers.load(directory / TOKENIZERS_DIR))
        model.denoiser.load_state_dict(load_file(str(directory / MODEL_WEIGHTS)))
        return model.to(device)
