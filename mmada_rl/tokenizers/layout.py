"""Where each modality sits in the unified sequence.

A :class:`SequenceLayout` is computed once from segment lengths and then
asked by every module (tokenizer glue, forward process, denoiser, loss,
sampler): positions, masks and restrictions are never re-derived by hand.

The sequence is ``[BOS] [SEP_LANG] lang [SEP_OBS] obs [SEP_PROPRIO] proprio
[SEP_GOAL] goal [SEP_ACT] actions`` (empty segments and their tags are left
out). With ``interleave=True`` the goal and action tokens form one block
``[SEP_GOAL] g_0 a_0 g_1 a_1 ... g_{K-1} a_{K-1}``, where the goal tokens are
split into ``K`` near-equal groups and ``a_k`` are the ``d_tok`` tokens of
action ``k``. Goal and action positions are the *targets*; every other
position (separators included) is *conditioning*.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary

__all__ = ["LayoutConfig", "SEGMENTS", "SequenceLayout"]

#: Segment roles; the index of a name is its segment id (:attr:`SequenceLayout.segment_ids`).
SEGMENTS: tuple[str, ...] = ("special", "lang", "obs", "proprio", "goal", "action")

_SEGMENT_MODALITY = {
    "special": "special",
    "lang": "text",
    "obs": "image",
    "proprio": "proprio",
    "goal": "image",
    "action": "action",
}
_SEGMENT_TAG = {
    "lang": "[SEP_LANG]",
    "obs": "[SEP_OBS]",
    "proprio": "[SEP_PROPRIO]",
    "goal": "[SEP_GOAL]",
    "action": "[SEP_ACT]",
}


@dataclass
class LayoutConfig:
    """Segment lengths of the unified sequence.

    Attributes:
        text_tokens: instruction tokens ``L_t`` (padded length).
        obs_tokens: observation image tokens ``L_o`` (0 when the denoiser
            cross-attends to visual features instead).
        goal_tokens: goal image tokens ``L_g``; 0 disables goal prediction.
        chunk_size: actions per chunk ``K``.
        tokens_per_action: tokens per action ``d_tok``.
        proprio_tokens: proprioception tokens ``L_p``; 0 disables them.
        interleave: interleave goal and action tokens instead of ``[goal | actions]``.
        image_grid: ``(h, w)`` of the image-token grid; when set, :meth:`SequenceLayout.split`
            returns obs/goal codes shaped ``[B, h, w]`` (else flat ``[B, L]``).
    """

    text_tokens: int
    obs_tokens: int
    goal_tokens: int
    chunk_size: int
    tokens_per_action: int
    proprio_tokens: int = 0
    interleave: bool = False
    image_grid: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        for name in ("text_tokens", "obs_tokens", "goal_tokens", "proprio_tokens"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an int >= 0, got {value!r}.")
        for name in ("chunk_size", "tokens_per_action"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if self.image_grid is not None:
            self.image_grid = tuple(int(v) for v in self.image_grid)
            if len(self.image_grid) != 2 or min(self.image_grid) < 1:
                raise ValueError(f"image_grid must be (h, w) with h, w >= 1, got {self.image_grid!r}.")
            cells = self.image_grid[0] * self.image_grid[1]
            for name in ("obs_tokens", "goal_tokens"):
                value = getattr(self, name)
                if value not in (0, cells):
                    raise ValueError(
                        f"{name}={value} does not match image_grid {self.image_grid} ({cells} tokens)."
                    )


class SequenceLayout:
    """Positions, masks and (dis)assembly of ``[lang | obs | proprio | goal | actions]``.

    Args:
        config: the segment lengths.
        vocab: the unified vocabulary the sequence's ids live in.

    Attributes:
        length: total sequence length ``L``.
        spans: ``{segment: slice}`` of every contiguous segment present
            (``"goal"``/``"action"`` are missing when interleaved).
        segment_ids: long ``[L]``, index in :data:`SEGMENTS` of each position.
        modality_ids: long ``[L]``, index in ``vocabulary.MODALITIES``.
        is_target / is_condition: bool ``[L]``.
        goal_positions: long ``[L_g]``; action_positions: long ``[K * d_tok]``
            in chunk order (action-major, then token); target_positions: long
            ``[L_g + K * d_tok]``, ascending.

    Examples:
        >>> from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig
        >>> vocab = UnifiedVocabulary(VocabularyConfig(32, 16, 8))
        >>> layout = SequenceLayout(LayoutConfig(text_tokens=4, obs_tokens=4, goal_tokens=4,
        ...                                      chunk_size=2, tokens_per_action=3), vocab)
        >>> layout.length  # [BOS] + 4 tags + 4 + 4 + 4 + 6
        23
        >>> ids = layout.assemble(torch.zeros(1, 4, dtype=torch.long), torch.zeros(1, 2, 2, dtype=torch.long),
        ...                       torch.ones(1, 4, dtype=torch.long), torch.full((1, 2, 3), 7))
        >>> layout.split(ids)["action"].shape
        torch.Size([1, 2, 3])
    """

    def __init__(self, config: LayoutConfig, vocab: UnifiedVocabulary) -> None:
        self.config = config
        self.vocab = vocab
        if config.proprio_tokens and not vocab.has("proprio"):
            raise ValueError(
                f"proprio_tokens={config.proprio_tokens} but the vocabulary has no proprio range; "
                "set VocabularyConfig.proprio_codebook_size > 0 or proprio_tokens=0."
            )
        self._build()

    # -- construction --------------------------------------------------------
    def _build(self) -> None:
        cfg, vocab = self.config, self.vocab
        segments: list[str] = []  # segment name of each position
        tokens: list[int] = []  # fixed separator id, -1 for content
        spans: dict[str, slice] = {}

        def add_tag(tag: str) -> None:
            segments.append("special")
            tokens.append(vocab.token_id(tag))

        def add_content(name: str, n: int) -> None:
            spans[name] = slice(len(segments), len(segments) + n)
            segments.extend([name] * n)
            tokens.extend([-1] * n)

        add_tag("[BOS]")
        for name, n in (("lang", cfg.text_tokens), ("obs", cfg.obs_tokens), ("proprio", cfg.proprio_tokens)):
            if n:
                add_tag(_SEGMENT_TAG[name])
                add_content(name, n)

        num_actions = cfg.chunk_size * cfg.tokens_per_action
        if cfg.interleave and cfg.goal_tokens:
            add_tag("[SEP_GOAL]")
            groups = torch.arange(cfg.goal_tokens).tensor_split(cfg.chunk_size)
            for k in range(cfg.chunk_size):
                add_content("goal", len(groups[k]))
                add_content("action", cfg.tokens_per_action)
            spans.pop("goal")  # not contiguous
            spans.pop("action")
        else:
            if cfg.goal_tokens:
                add_tag("[SEP_GOAL]")
                add_content("goal", cfg.goal_tokens)
            add_tag("[SEP_ACT]")
            add_content("action", num_actions)
        self.spans = spans
        self.length = len(segments)

        self.segment_ids = torch.tensor([SEGMENTS.index(s) for s in segments], dtype=torch.long)
        self.modality_ids = torch.tensor(
            [vocab.modality_index(_SEGMENT_MODALITY[s]) for s in segments], dtype=torch.long
        )
        self._fixed_tokens = torch.tensor(tokens, dtype=torch.long)  # (L,) -1 = content
        self.goal_positions = self._where("goal")  # (L_g,) in goal order
        self.action_positions = self._where("action")  # (K * d_tok,) in chunk order
        self.is_target = torch.zeros(self.length, dtype=torch.bool)
        self.is_target[self.goal_positions] = True
        self.is_target[self.action_positions] = True
        self.is_condition = ~self.is_target
        self.is_separator = self._fixed_tokens >= 0
        #: Long ``[L_g + K * d_tok]``: every target position, ascending.
        self.target_positions = self.is_target.nonzero().squeeze(-1)
        #: Long ``[K * d_tok]``: where each action position (chunk order) sits among the targets.
        self.action_target_index = torch.searchsorted(self.target_positions, self.action_positions)

    def _where(self, segment: str) -> torch.Tensor:
        return (self.segment_ids == SEGMENTS.index(segment)).nonzero().squeeze(-1)

    # -- sizes ---------------------------------------------------------------
    @property
    def num_targets(self) -> int:
        """Number of target positions ``L_g + K * d_tok``."""
        return int(self.target_positions.numel())

    @property
    def has_goal(self) -> bool:
        return self.config.goal_tokens > 0

    def positions(self, segment: str) -> torch.Tensor:
        """Long index tensor of a segment's positions, in its own order.

        ``segment`` is one of :data:`SEGMENTS` or ``"target"`` (all targets, ascending).
        """
        if segment == "goal":
            return self.goal_positions
        if segment == "action":
            return self.action_positions
        if segment == "target":
            return self.target_positions
        if segment not in SEGMENTS:
            raise ValueError(f"Unknown segment {segment!r}; expected one of {SEGMENTS} or 'target'.")
        return self._where(segment)

    # -- masks ---------------------------------------------------------------
    def logit_bounds(self, restrict_condition: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-position allowed id range ``(low, high)``, long ``[L]`` each.

        Target positions are always restricted to their modality's range;
        conditioning positions too unless ``restrict_condition=False`` (then
        ``[0, V)``).
        """
        low, high = self.vocab.bounds(self.modality_ids)
        if not restrict_condition:
            low = torch.where(self.is_target, low, torch.zeros_like(low))
            high = torch.where(self.is_target, high, torch.full_like(high, self.vocab.size))
        return low, high

    def allowed_logit_mask(
        self, vocab: UnifiedVocabulary | None = None, restrict_condition: bool = True
    ) -> torch.Tensor:
        """Bool ``[L, V]``: True where position ``i`` may emit id ``v``."""
        vocab = self._check_vocab(vocab)
        low, high = self.logit_bounds(restrict_condition)
        ids = torch.arange(vocab.size)
        return (ids >= low[:, None]) & (ids < high[:, None])  # (L, V)

    def attention_mask(self, kind: str = "block_causal") -> torch.Tensor | None:
        """Bool ``[L, L]`` (True = query row may attend to key column), or None.

        ``"block_causal"``: conditioning positions attend only to conditioning
        positions; targets attend to everything. ``"bidirectional"``: None
        (everything attends to everything).
        """
        if kind == "bidirectional":
            return None
        if kind != "block_causal":
            raise ValueError(f"attention kind must be 'bidirectional' or 'block_causal', got {kind!r}.")
        return self.is_target[:, None] | self.is_condition[None, :]  # (L, L)

    # -- assembly ------------------------------------------------------------
    def assemble(
        self,
        text_ids: torch.Tensor | None,
        obs_ids: torch.Tensor | None,
        goal_ids: torch.Tensor | None = None,
        action_ids: torch.Tensor | None = None,
        proprio_ids: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Build global sequence ids ``[B, L]`` from LOCAL codes per modality.

        Args:
            text_ids: ``[B, L_t]`` text-tokenizer ids (None only if ``L_t == 0``).
            obs_ids: ``[B, L_o]`` or ``[B, h, w]`` image codes (None only if ``L_o == 0``).
            goal_ids: like ``obs_ids`` with ``L_g`` tokens; None fills goal positions with ``[MASK]``.
            action_ids: ``[B, K, d_tok]`` (or ``[B, K * d_tok]``) action codes;
                None fills action positions with ``[MASK]`` (the sampler's start).
            proprio_ids: ``[B, L_p]`` proprio codes (None only if ``L_p == 0``).
        """
        cfg = self.config
        given = {"text_ids": text_ids, "obs_ids": obs_ids, "goal_ids": goal_ids,
                 "action_ids": action_ids, "proprio_ids": proprio_ids}
        batch = next((t.shape[0] for t in given.values() if t is not None), None)
        if batch is None:
            raise ValueError("assemble needs at least one input tensor to know the batch size.")
        device = next(t.device for t in given.values() if t is not None)
        ids = self._fixed_tokens.to(device).expand(batch, -1).clone()  # (B, L)
        ids[:, self.is_target.to(device)] = self.vocab.mask_id
        pieces = (
            ("lang", "text_ids", text_ids, cfg.text_tokens, False),
            ("obs", "obs_ids", obs_ids, cfg.obs_tokens, False),
            ("proprio", "proprio_ids", proprio_ids, cfg.proprio_tokens, False),
            ("goal", "goal_ids", goal_ids, cfg.goal_tokens, True),
            ("action", "action_ids", action_ids, cfg.chunk_size * cfg.tokens_per_action, True),
        )
        for segment, name, local, n, optional in pieces:
            if local is None:
                if n and not optional:
                    raise ValueError(f"{name}: expected a tensor with {n} tokens per sample, got None.")
                continue
            flat = self._flatten(name, local, batch, n, segment)
            if n:
                modality = _SEGMENT_MODALITY[segment]
                ids[:, self.positions(segment).to(device)] = self.vocab.to_global(modality, flat)
        return ids

    def _flatten(self, name: str, local: torch.Tensor, batch: int, n: int, segment: str) -> torch.Tensor:
        shape = tuple(local.shape)
        expected = self._expected_shapes(segment, batch, n)
        if shape not in expected:
            raise ValueError(
                f"{name}: expected shape {' or '.join(str(list(s)) for s in expected)}, got {list(shape)}."
            )
        return local.reshape(batch, n)

    def _expected_shapes(self, segment: str, batch: int, n: int) -> list[tuple[int, ...]]:
        shapes = [(batch, n)]
        if segment == "action":
            shapes.insert(0, (batch, self.config.chunk_size, self.config.tokens_per_action))
        elif segment in ("obs", "goal") and n:
            grid = self.config.image_grid
            if grid is not None:
                shapes.append((batch, *grid))
            else:  # accept any (h, w) grid with h * w == n
                root = int(round(n**0.5))
                if root * root == n:
                    shapes.append((batch, root, root))
        return shapes

    def split(self, ids: torch.Tensor) -> dict[str, torch.Tensor]:
        """Inverse of :meth:`assemble`: local codes of every segment present.

        Returns ``{"text": [B, L_t], "obs": [B, L_o] or [B, h, w], "proprio": [B, L_p],
        "goal": [B, L_g] or [B, h, w], "action": [B, K, d_tok]}``; segments of
        length 0 are left out. Raises ValueError if a position holds an id
        outside its modality (e.g. a ``[MASK]`` left in the targets).
        """
        if ids.ndim != 2 or ids.shape[1] != self.length:
            raise ValueError(f"ids: expected shape [B, {self.length}], got {list(ids.shape)}.")
        batch = ids.shape[0]
        cfg = self.config
        out: dict[str, torch.Tensor] = {}
        for segment, key in (("lang", "text"), ("obs", "obs"), ("proprio", "proprio"),
                             ("goal", "goal"), ("action", "action")):
            pos = self.positions(segment).to(ids.device)
            if pos.numel() == 0:
                continue
            local = self.vocab.to_local(_SEGMENT_MODALITY[segment], ids[:, pos])
            if segment == "action":
                local = local.reshape(batch, cfg.chunk_size, cfg.tokens_per_action)
            elif segment in ("obs", "goal") and cfg.image_grid is not None:
                local = local.reshape(batch, *cfg.image_grid)
            out[key] = local
        return out

    def split_targets(self, target_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        """Local goal/action codes from target ids ``[B, L_target]`` (ordered as :attr:`target_positions`)."""
        if target_ids.ndim != 2 or target_ids.shape[1] != self.num_targets:
            raise ValueError(
                f"target_ids: expected shape [B, {self.num_targets}], got {list(target_ids.shape)}."
            )
        full = torch.full((target_ids.shape[0], self.length), -1, dtype=torch.long, device=target_ids.device)
        full[:, self.target_positions.to(full.device)] = target_ids
        cfg = self.config
        out = {"action": self.vocab.to_local("action", full[:, self.action_positions.to(full.device)])
               .reshape(-1, cfg.chunk_size, cfg.tokens_per_action)}
        if self.has_goal:
            goal = self.vocab.to_local("image", full[:, self.goal_positions.to(full.device)])
            out["goal"] = goal.reshape(-1, *cfg.image_grid) if cfg.image_grid is not None else goal
        return out

    # -- misc ----------------------------------------------------------------
    def _check_vocab(self, vocab: UnifiedVocabulary | None) -> UnifiedVocabulary:
        if vocab is None:
            return self.vocab
        if vocab.to_dict() != self.vocab.to_dict():
            raise ValueError(f"vocab {vocab!r} differs from the layout's vocabulary {self.vocab!r}.")
        return vocab

    def describe(self) -> str:
        """One line per segment: ``name [start, stop)`` (or its count when interleaved)."""
        lines = [f"length={self.length} targets={self.num_targets} interleave={self.config.interleave}"]
        for name in ("lang", "obs", "proprio", "goal", "action"):
            pos = self.positions(name)
            if pos.numel():
                span = self.spans.get(name)
                where = f"[{span.start}, {span.stop})" if span is not None else f"{pos.numel()} interleaved"
                lines.append(f"  {name:<8}{where}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"layout": asdict(self.config), "vocabulary": self.vocab.to_dict()}

    @classmethod
    def from_dict(cls, data: dict) -> "SequenceLayout":
        return cls(LayoutConfig(**data["layout"]), UnifiedVocabulary.from_dict(data["vocabulary"]))

    def __repr__(self) -> str:
        return f"SequenceLayout({self.describe()})"
