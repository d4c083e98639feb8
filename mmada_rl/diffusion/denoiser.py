"""The masked-diffusion denoiser ``D_θ(x̃, ρ)`` over the unified sequence.

A pre-norm transformer: token + learned position + segment (modality role)
embeddings (and, as an option, an embedding of each proprioception bin's
value, so the state's tokens are read as ordered numbers), plus an embedding
of the noise level added to every position (to the targets only under
block-causal attention); self-attention bidirectional or
block-causal (per the layout); an optional
cross-attention sublayer per block to visual features ``[B, N, d_vis]`` — given
as such, or computed from the observation image by a CNN the denoiser owns and
trains (``visual_encoder_channels``). The
output head covers the whole vocabulary (tied to the token embeddings by
default) and every position's logits are set to ``-inf`` outside the id range
the layout allows there, so targets can only emit ids of their own modality.

With block-causal attention the conditioning never reads the targets or the
noise level, so its keys and values at every layer are the same at every
decoding step: :meth:`MaskedDiffusionDenoiser.cache_condition` computes them
once per prompt and ``forward(..., cache=...)`` then runs the target positions
alone, attending to the cached conditioning (the same logits, fewer rows).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from mmada_rl.diffusion.keys import LOGITS_KEY, VISUAL_FEATURES_KEY
from mmada_rl.diffusion.pretrained import load_pretrained_text_embeddings
from mmada_rl.diffusion.transformer import ScalarEmbedding, TransformerBlock
from mmada_rl.diffusion.visual import ConvPatchEncoder
from mmada_rl.keys import NOISE_LEVEL_KEY, SEQUENCE_KEY
from mmada_rl.tokenizers.layout import SEGMENTS, SequenceLayout

__all__ = [
    "ConditionCache",
    "DenoiserConfig",
    "MaskedDiffusionDenoiser",
    "make_denoiser_module",
]

_PRESETS = {
    "tiny": dict(d_model=64, num_layers=2, num_heads=2),
    "small": dict(d_model=256, num_layers=4, num_heads=4),
    "base": dict(d_model=512, num_layers=8, num_heads=8),
}


@dataclass
class DenoiserConfig:
    """Size and options of :class:`MaskedDiffusionDenoiser`.

    Attributes:
        d_model: width of the residual stream.
        num_layers: transformer blocks.
        num_heads: attention heads (must divide ``d_model``).
        mlp_ratio: MLP hidden width over ``d_model``.
        dropout: dropout in attention and residual branches.
        attention: ``"bidirectional"`` (the paper) or ``"block_causal"``
            (conditioning attends only to conditioning; targets to everything).
            Under block-causal attention the noise level is added to the target
            positions only, so the conditioning's hidden states depend on the
            conditioning alone and a sampler can compute them once per chunk
            (:meth:`MaskedDiffusionDenoiser.cache_condition`).
        cross_attention_to_visual: add a cross-attention sublayer per block over
            visual features given to ``forward(visual=...)``.
        visual_dim: width ``d_vis`` of those features (defaults to ``d_model``).
        visual_encoder_channels: widths of a :class:`~mmada_rl.diffusion.visual.ConvPatchEncoder`
            owned by the denoiser (needs ``cross_attention_to_visual``): ``visual``
            is then the uint8 observation image ``[B, 3, H, W]``, and its CNN
            features (one per cell of the last feature map) are what the
            sequence attends to. ``None``: ``visual`` holds the features already.
        visual_keypoints: with ``visual_encoder_channels``, pool the CNN's last feature
            map into this many spatial-softmax keypoints (the BC baseline's pooling) and
            let the sequence attend to one token per keypoint (its expected position,
            embedded) instead of to every cell: the image narrowed to positions.
            ``None``: the cells.
        proprio_value_embedding: add to each proprioception token a sinusoidal
            embedding of its bin's value (bin index over the number of bins, in
            ``[0, 1]``), whose features lie further apart the further apart
            the values are, so differences of state values are easy to read.
            Without it a state token is an unordered learned embedding shared
            by every dimension. Needs proprio tokens whose codes are ordered bins.
        action_value_embedding: give every action id a sinusoidal embedding of
            its bin's value (bin index over the number of bins, in ``[0, 1]``)
            through an MLP, added to its learned embedding — in the input and,
            through the tied head, in the output. Neighbouring bins then start
            with nearly the same embedding, so the logits over the bins are a
            smooth function of the value learned from every example, instead of
            256 unrelated classes each learned from its own few (what a
            regression head shares for free). Needs action tokens whose codes
            are ordered bins (the uniform-bin tokenizer).
        tie_embeddings: share the output head with the token embeddings.
        pretrained_path: local HuggingFace checkpoint whose input embeddings
            initialise the text rows (needs ``transformers``; never downloads).

    Use :meth:`preset` for the ``"tiny"`` (tests), ``"small"`` (CPU benchmarks)
    and ``"base"`` (GPU) sizes.
    """

    d_model: int = 64
    num_layers: int = 2
    num_heads: int = 2
    mlp_ratio: float = 4.0
    dropout: float = 0.0
    attention: str = "bidirectional"
    cross_attention_to_visual: bool = False
    visual_dim: int | None = None
    visual_encoder_channels: list[int] | None = None
    visual_keypoints: int | None = None
    proprio_value_embedding: bool = False
    action_value_embedding: bool = False
    tie_embeddings: bool = True
    pretrained_path: str | None = None

    def __post_init__(self) -> None:
        for name in ("d_model", "num_layers", "num_heads"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if self.d_model % self.num_heads:
            raise ValueError(f"d_model={self.d_model} must be divisible by num_heads={self.num_heads}.")
        if self.mlp_ratio <= 0:
            raise ValueError(f"mlp_ratio must be > 0, got {self.mlp_ratio!r}.")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must lie in [0, 1), got {self.dropout!r}.")
        if self.attention not in ("bidirectional", "block_causal"):
            raise ValueError(f"attention must be 'bidirectional' or 'block_causal', got {self.attention!r}.")
        if self.visual_dim is not None and (not isinstance(self.visual_dim, int) or self.visual_dim < 1):
            raise ValueError(f"visual_dim must be a positive int or None, got {self.visual_dim!r}.")
        if self.visual_keypoints is not None and self.visual_encoder_channels is None:
            raise ValueError("visual_keypoints pools the denoiser's own CNN: it needs visual_encoder_channels "
                             "(e.g. [32, 64, 128]).")
        if self.visual_encoder_channels is not None:
            self.visual_encoder_channels = [int(c) for c in self.visual_encoder_channels]
            if not self.cross_attention_to_visual:
                raise ValueError("visual_encoder_channels needs cross_attention_to_visual=true "
                                 "(the encoder's features are read by the cross-attention).")
            if self.visual_keypoints is not None and (not isinstance(self.visual_keypoints, int) or self.visual_keypoints < 1):
                raise ValueError(f"visual_keypoints must be a positive int or None, got {self.visual_keypoints!r}.")
            if self.visual_dim is not None and self.visual_dim != self.visual_encoder_channels[-1]:
                raise ValueError(f"visual_dim={self.visual_dim} differs from the encoder's last width "
                                 f"{self.visual_encoder_channels[-1]}; leave visual_dim unset.")

    @property
    def encodes_images(self) -> bool:
        """Whether ``visual`` is the raw observation image (the denoiser owns the CNN)."""
        return self.visual_encoder_channels is not None

    @classmethod
    def preset(cls, name: str, **overrides) -> "DenoiserConfig":
        """``"tiny"`` (d=64, 2 layers), ``"small"`` (d=256, 4 layers), ``"base"`` (d=512, 8 layers, 8 heads)."""
        if name not in _PRESETS:
            raise ValueError(f"preset must be one of {sorted(_PRESETS)}, got {name!r}.")
        unknown = set(overrides) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown DenoiserConfig fields {sorted(unknown)}.")
        return cls(**{**_PRESETS[name], **overrides})


@dataclass
class ConditionCache:
    """The conditioning of a batch of prompts as a block-causal denoiser's targets read it.

    Built by :meth:`MaskedDiffusionDenoiser.cache_condition`; valid for any
    targets and noise level of those prompts.

    Attributes:
        keys / values: one ``[B, H, C, Dh]`` tensor per block: the self-attention
            keys and values of the ``C`` conditioning positions.
        visual: ``[B, N, D]`` projected visual features for the cross-attention
            (the CNN's, when the denoiser encodes the image), or None.
    """

    keys: list[torch.Tensor]
    values: list[torch.Tensor]
    visual: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.keys[0].shape[0]

    def repeat_interleave(self, repeats: int) -> "ConditionCache":
        """Each prompt's cache repeated ``repeats`` times in a row (batch ``B * repeats``)."""
        def rep(x):
            return None if x is None else x.repeat_interleave(repeats, dim=0)
        return ConditionCache([rep(k) for k in self.keys], [rep(v) for v in self.values], rep(self.visual))


class MaskedDiffusionDenoiser(nn.Module):
    """Transformer denoiser: ``forward(ids [B, L], noise_level [B]) -> logits [B, L, V]``.

    Args:
        config: sizes and options.
        layout: the sequence layout (fixes ``L``, the vocabulary, the segments
            and the allowed id range of each position).

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> net = MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny"), layout)
        >>> ids = torch.full((2, layout.length), layout.vocab.mask_id)
        >>> net(ids, torch.ones(2)).shape
        torch.Size([2, 23, 65])
    """

    def __init__(self, config: DenoiserConfig, layout: SequenceLayout) -> None:
        super().__init__()
        self.config = config
        self.layout = layout
        vocab_size, length, dim = layout.vocab.size, layout.length, config.d_model
        self.token_embedding = nn.Embedding(vocab_size, dim)
        self.position_embedding = nn.Parameter(torch.zeros(length, dim))
        self.segment_embedding = nn.Embedding(len(SEGMENTS), dim)
        self.noise_embedding = ScalarEmbedding(dim)
        self.proprio_value_embedding = None
        if config.proprio_value_embedding:
            if not layout.config.proprio_tokens:
                raise ValueError("proprio_value_embedding=True needs proprio tokens in the layout (proprio_tokens > 0).")
            self.proprio_value_embedding = ScalarEmbedding(dim, scale=10.0)
        self.action_value_embedding = None
        if config.action_value_embedding:
            if not layout.vocab.has("action"):
                raise ValueError("action_value_embedding=True needs action ids in the vocabulary.")
            # Frequencies from ~1 to 200 radians over [0, 1]: the slow ones make neighbouring bins alike,
            # the fast ones (a period of ~8 of 256 bins) still let a distribution peak within a few bins.
            self.action_value_embedding = ScalarEmbedding(dim, scale=200.0, max_period=200.0)
        self.visual_proj = self.visual_encoder = None
        if config.encodes_images:
            self.visual_encoder = ConvPatchEncoder(config.visual_encoder_channels, keypoints=config.visual_keypoints or 0)
        if config.cross_attention_to_visual:
            visual_dim = self.visual_encoder.out_features if self.visual_encoder else config.visual_dim or dim
            self.visual_proj = nn.Sequential(nn.Linear(visual_dim, dim), nn.LayerNorm(dim))
        self.blocks = nn.ModuleList(
            TransformerBlock(dim, config.num_heads, config.mlp_ratio, config.dropout, config.cross_attention_to_visual)
            for _ in range(config.num_layers)
        )
        self.final_norm = nn.LayerNorm(dim)
        self.head = None if config.tie_embeddings else nn.Linear(dim, vocab_size, bias=False)
        self.head_bias = nn.Parameter(torch.zeros(vocab_size))

        low, high = layout.logit_bounds(restrict_condition=True)
        self.register_buffer("segment_ids", layout.segment_ids.clone(), persistent=False)  # (L,)
        self.register_buffer("logit_low", low, persistent=False)  # (L,)
        self.register_buffer("logit_high", high, persistent=False)  # (L,)
        mask = layout.attention_mask(config.attention)
        self.register_buffer("attn_mask", mask, persistent=False)  # (L, L) or None
        noised = layout.is_target if config.attention == "block_causal" else torch.ones(layout.length, dtype=torch.bool)
        self.register_buffer("noised_positions", noised[:, None].float(), persistent=False)  # (L, 1)
        self.register_buffer("condition_positions", layout.is_condition.nonzero().squeeze(-1), persistent=False)
        self.register_buffer("target_positions", layout.target_positions.clone(), persistent=False)
        self._init_weights()
        if config.pretrained_path is not None:
            load_pretrained_text_embeddings(
                self.token_embedding, layout.vocab.range_of("text"), config.pretrained_path
            )

    def _init_weights(self) -> None:
        for module in self.modules():
            if isinstance(module, (nn.Linear, nn.Embedding)):
                nn.init.normal_(module.weight, std=0.02)
                if getattr(module, "bias", None) is not None:
                    nn.init.zeros_(module.bias)
        nn.init.normal_(self.position_embedding, std=0.02)
        for block in self.blocks:  # GPT-2 scaling of the residual projections
            for layer in (block.attn.out, block.mlp[-1]) + ((block.cross.out,) if block.cross else ()):
                nn.init.normal_(layer.weight, std=0.02 / (2 * self.config.num_layers) ** 0.5)

    @property
    def visual_ndim(self) -> int:
        """Dimensions of one sample's ``visual`` input plus the batch: 4 for images, 3 for features."""
        return 4 if self.visual_encoder is not None else 3

    def flat_visual(self, visual: torch.Tensor, batch: int = -1) -> torch.Tensor:
        """``visual`` with its batch dimensions flattened to ``batch`` (features or images alike)."""
        return visual.reshape(batch, *visual.shape[-(self.visual_ndim - 1):])

    @property
    def vocab_size(self) -> int:
        return self.layout.vocab.size

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    @property
    def supports_condition_cache(self) -> bool:
        """Whether :meth:`cache_condition` applies (block-causal attention)."""
        return self.config.attention == "block_causal"

    # -- forward -------------------------------------------------------------
    def _check_ids(self, ids: torch.Tensor) -> None:
        length = self.layout.length
        if ids.ndim != 2 or ids.shape[1] != length:
            raise ValueError(f"ids: expected shape [B, {length}], got {list(ids.shape)}.")

    def _noise(self, noise_level: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        """Noise-level embedding ``[B, D]`` (a scalar level applies to the whole batch)."""
        noise_level = torch.as_tensor(noise_level, device=ids.device)
        if noise_level.ndim == 0:
            noise_level = noise_level.expand(ids.shape[0])
        if noise_level.shape != ids.shape[:1]:
            raise ValueError(f"noise_level: expected shape [{ids.shape[0]}], got {list(noise_level.shape)}.")
        return self.noise_embedding(noise_level)

    def _embed(self, ids: torch.Tensor, positions: torch.Tensor | None = None) -> torch.Tensor:
        """Token + position + segment (+ proprio value) embeddings of sequences ``ids [B, L]``:
        ``[B, L, D]``, or ``[B, P, D]`` at ``positions [P]``."""
        if positions is None:
            position, segments = self.position_embedding, self.segment_ids
        else:
            ids, position, segments = ids[:, positions], self.position_embedding[positions], self.segment_ids[positions]
        x = nn.functional.embedding(ids, self._token_weight()) + position + self.segment_embedding(segments)
        if self.proprio_value_embedding is not None:
            at_proprio = segments == SEGMENTS.index("proprio")  # (P,); none among the targets alone
            if bool(at_proprio.any()):
                x[:, at_proprio] = x[:, at_proprio] + self._proprio_values(ids[:, at_proprio])
        return x

    def _token_weight(self, weight: torch.Tensor | None = None) -> torch.Tensor:
        """The id embeddings ``[V, D]`` (the token embeddings, or ``weight``), the action rows plus
        their bins' value embeddings when ``action_value_embedding`` is on."""
        weight = self.token_embedding.weight if weight is None else weight
        if self.action_value_embedding is None:
            return weight
        start, stop = self.layout.vocab.range_of("action")
        values = torch.arange(stop - start, device=weight.device, dtype=torch.float32) / max(stop - start - 1, 1)
        return torch.cat([weight[:start], weight[start:stop] + self.action_value_embedding(values), weight[stop:]])

    def _proprio_values(self, ids: torch.Tensor) -> torch.Tensor:
        """Value embeddings ``[B, P_p, D]`` of proprio-position ids ``[B, P_p]`` (zero at masked ones)."""
        start, stop = self.layout.vocab.range_of("proprio")
        codes = ids - start
        is_bin = (codes >= 0) & (codes < stop - start)  # a masked proprio token has no value
        value = codes.clamp(0, stop - start - 1).float() / max(stop - start - 1, 1)
        return self.proprio_value_embedding(value) * is_bin[..., None]

    def _visual_context(self, visual: torch.Tensor | None, batch: int) -> torch.Tensor | None:
        """What the cross-attention reads, ``[B, N, D]`` (None without cross-attention)."""
        if self.visual_proj is None and visual is not None:
            raise ValueError("visual features given but cross_attention_to_visual=False.")
        if self.visual_proj is None:
            return None
        expected = f"[{batch}, 3, H, W] uint8 images" if self.visual_encoder else f"[{batch}, N, d_vis]"
        if visual is None or visual.ndim != self.visual_ndim or visual.shape[0] != batch:
            got = None if visual is None else list(visual.shape)
            raise ValueError(f"visual: expected shape {expected}, got {got}.")
        if self.visual_encoder is not None:
            visual = self.visual_encoder(visual)  # (B, N, C)
        return self.visual_proj(visual)  # (B, N, D)

    def encode(
        self, ids: torch.Tensor, noise_level: torch.Tensor, visual: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Final hidden states ``[B, L, D]`` of sequences ``ids [B, L]`` at noise levels ``[B]``."""
        self._check_ids(ids)
        noise = self._noise(noise_level, ids)  # (B, D)
        visual = self._visual_context(visual, ids.shape[0])
        x = self._embed(ids)
        x = x + noise[:, None, :] * self.noised_positions  # (B, L, D)
        for block in self.blocks:
            x = block(x, attn_mask=self.attn_mask, visual=visual)
        return self.final_norm(x)  # (B, L, D)

    def cache_condition(self, ids: torch.Tensor, visual: torch.Tensor | None = None) -> ConditionCache:
        """Keys and values of the conditioning positions of ``ids [B, L]`` at every block.

        Only with block-causal attention, where the conditioning attends to
        itself alone and carries no noise level: then ``forward(ids', ρ,
        cache=cache)`` for any ``ids'`` with the same conditioning gives the
        target logits of ``forward(ids', ρ, visual)``. The target positions of
        ``ids`` are ignored.
        """
        if not self.supports_condition_cache:
            raise ValueError(
                f"cache_condition needs attention='block_causal' (this denoiser's is {self.config.attention!r}): "
                "with bidirectional attention the conditioning reads the targets, so it changes at every step."
            )
        self._check_ids(ids)
        if visual is not None:
            visual = self.flat_visual(visual)
        visual = self._visual_context(visual, ids.shape[0])
        x = self._embed(ids, self.condition_positions)  # (B, C, D)
        keys, values = [], []
        for block in self.blocks:  # the conditioning rows of the block-causal mask: all-to-all among themselves
            x, (k, v) = block(x, visual=visual, return_kv=True)
            keys.append(k)
            values.append(v)
        return ConditionCache(keys, values, visual)

    def encode_targets(self, ids: torch.Tensor, noise_level: torch.Tensor, cache: ConditionCache) -> torch.Tensor:
        """Final hidden states ``[B, T, D]`` of the target positions, the conditioning read from ``cache``."""
        self._check_ids(ids)
        if cache.batch_size != ids.shape[0]:
            raise ValueError(f"cache: built for a batch of {cache.batch_size}, ids have {ids.shape[0]}.")
        noise = self._noise(noise_level, ids)  # (B, D)
        x = self._embed(ids, self.target_positions) + noise[:, None, :]  # (B, T, D)
        for block, k, v in zip(self.blocks, cache.keys, cache.values):
            x = block(x, visual=cache.visual, prefix=(k, v))
        return self.final_norm(x)

    def project(self, hidden: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """Restricted logits ``[..., V]`` of hidden states ``[..., D]`` at sequence ``positions [...]``."""
        weight = self._token_weight(None if self.head is None else self.head.weight)  # (V, D)
        logits = hidden @ weight.t() + self.head_bias  # (..., V)
        ids = torch.arange(self.vocab_size, device=hidden.device)
        allowed = (ids >= self.logit_low[positions][..., None]) & (ids < self.logit_high[positions][..., None])
        return logits.masked_fill(~allowed, float("-inf"))

    def forward(
        self,
        ids: torch.Tensor,
        noise_level: torch.Tensor,
        visual: torch.Tensor | None = None,
        positions: torch.Tensor | None = None,
        cache: ConditionCache | None = None,
    ) -> torch.Tensor:
        """Logits ``[*B, P, V]`` at ``positions`` (long ``[P]``; all ``L`` positions by default).

        Args:
            ids: global ids ``[*B, L]``.
            noise_level: masking ratio per sample ``[*B]`` (or a scalar).
            visual: visual features ``[*B, N, d_vis]``, or images ``[*B, 3, H, W]``
                when the denoiser has its own encoder (only with cross-attention).
            positions: which positions to score; asking only for the targets
                saves the head's ``L × V`` product on the conditioning.
            cache: the conditioning of these prompts (:meth:`cache_condition`,
                batch ``prod(*B)``): only the target positions are computed, so
                ``positions`` must be None or the targets, and ``visual`` is
                read from the cache. Returns the target logits ``[*B, T, V]``.
        """
        batch_shape = ids.shape[:-1]
        flat_ids = ids.reshape(-1, ids.shape[-1])
        noise_level = torch.as_tensor(noise_level, device=ids.device)
        if noise_level.ndim:
            noise_level = noise_level.reshape(-1)
        if cache is not None:
            targets = self.target_positions
            if positions is not None and not torch.equal(positions.to(targets.device), targets):
                raise ValueError("with a conditioning cache only the target positions are computed; pass positions=None.")
            if visual is not None:
                raise ValueError("with a conditioning cache the visual input is read from the cache; pass visual=None.")
            logits = self.project(self.encode_targets(flat_ids, noise_level, cache), targets)  # (B, T, V)
            return logits.reshape(*batch_shape, *logits.shape[1:])
        if visual is not None:
            visual = self.flat_visual(visual)
        hidden = self.encode(flat_ids, noise_level, visual)  # (B, L, D)
        if positions is None:
            positions = torch.arange(self.layout.length, device=ids.device)
        logits = self.project(hidden[:, positions], positions)  # (B, P, V)
        return logits.reshape(*batch_shape, *logits.shape[1:])


def make_denoiser_module(
    denoiser: MaskedDiffusionDenoiser,
    *,
    sequence_key=SEQUENCE_KEY,
    noise_level_key=NOISE_LEVEL_KEY,
    visual_key=VISUAL_FEATURES_KEY,
    logits_key=LOGITS_KEY,
) -> TensorDictModule:
    """Wrap a denoiser as a ``TensorDictModule`` reading ids and noise level, writing logits.

    ``in_keys = [sequence_key, noise_level_key]`` (+ ``visual_key`` with
    cross-attention), ``out_keys = [logits_key]`` (:data:`LOGITS_KEY`).

    Examples:
        >>> from tensordict import TensorDict
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> from mmada_rl.tokenizers.layout import LayoutConfig, SequenceLayout
        >>> layout = SequenceLayout(LayoutConfig(4, 4, 4, 2, 3), UnifiedVocabulary(VocabularyConfig(32, 16, 8)))
        >>> module = make_denoiser_module(MaskedDiffusionDenoiser(DenoiserConfig(), layout))
        >>> td = TensorDict({SEQUENCE_KEY: torch.ones(2, layout.length, dtype=torch.long),
        ...                  NOISE_LEVEL_KEY: torch.ones(2)}, batch_size=[2])
        >>> module(td)[LOGITS_KEY].shape
        torch.Size([2, 23, 65])
    """
    in_keys = [sequence_key, noise_level_key]
    if denoiser.config.cross_attention_to_visual:
        in_keys.append(visual_key)
    return TensorDictModule(denoiser, in_keys=in_keys, out_keys=[logits_key])
