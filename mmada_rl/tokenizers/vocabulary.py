"""The unified discrete vocabulary shared by every modality.

Special tokens come first, then one contiguous id range per modality, in the
order ``text | image | action | proprio``. Each tokenizer keeps producing its
own *local* codes (``0 .. size-1``); this vocabulary maps them to *global* ids
and back, and tells which ids each modality may emit.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import torch

__all__ = [
    "DEFAULT_SPECIAL_TOKENS",
    "MODALITIES",
    "UnifiedVocabulary",
    "VocabularyConfig",
]

#: Special tokens, in id order. ``[PAD]`` is 0 and ``[MASK]`` is 1.
DEFAULT_SPECIAL_TOKENS: tuple[str, ...] = (
    "[PAD]",
    "[MASK]",
    "[BOS]",
    "[EOS]",
    "[SEP_LANG]",
    "[SEP_OBS]",
    "[SEP_PROPRIO]",
    "[SEP_GOAL]",
    "[SEP_ACT]",
)

#: Vocabulary modalities; the index of a name is its modality id (what
#: :attr:`SequenceLayout.modality_ids` holds). Goal images share ``"image"``.
MODALITIES: tuple[str, ...] = ("special", "text", "image", "action", "proprio")

_REQUIRED_SPECIALS = ("[PAD]", "[MASK]")


@dataclass
class VocabularyConfig:
    """Sizes of each modality's code book.

    Attributes:
        text_vocab_size: number of text-tokenizer ids (its own specials included).
        image_codebook_size: number of image (VQ) codes; observation and goal
            images share them.
        action_codebook_size: number of action codes.
        proprio_codebook_size: number of proprioception codes; ``0`` disables
            the proprio range.
        special_tokens: special token names, in id order; must start with
            ``[PAD]`` and ``[MASK]``.
    """

    text_vocab_size: int
    image_codebook_size: int
    action_codebook_size: int
    proprio_codebook_size: int = 0
    special_tokens: tuple[str, ...] = field(default=DEFAULT_SPECIAL_TOKENS)

    def __post_init__(self) -> None:
        self.special_tokens = tuple(self.special_tokens)
        for name in ("text_vocab_size", "image_codebook_size", "action_codebook_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if not isinstance(self.proprio_codebook_size, int) or self.proprio_codebook_size < 0:
            raise ValueError(
                "proprio_codebook_size must be an int >= 0 (0 disables proprio tokens), "
                f"got {self.proprio_codebook_size!r}."
            )
        if self.special_tokens[:2] != _REQUIRED_SPECIALS:
            raise ValueError(
                f"special_tokens must start with {_REQUIRED_SPECIALS}, got {self.special_tokens[:2]!r}."
            )
        if len(set(self.special_tokens)) != len(self.special_tokens):
            raise ValueError(f"special_tokens must be unique, got {self.special_tokens!r}.")


class UnifiedVocabulary:
    """One id space for special tokens, text, image, action and proprio codes.

    Args:
        config: the code-book sizes.

    Examples:
        >>> vocab = UnifiedVocabulary(VocabularyConfig(
        ...     text_vocab_size=100, image_codebook_size=512, action_codebook_size=256))
        >>> vocab.range_of("image")
        (109, 621)
        >>> ids = vocab.to_global("action", torch.tensor([0, 255]))
        >>> vocab.to_local("action", ids).tolist()
        [0, 255]
        >>> UnifiedVocabulary.from_dict(vocab.to_dict()).size == vocab.size
        True
    """

    def __init__(self, config: VocabularyConfig) -> None:
        self.config = config
        sizes = {
            "special": len(config.special_tokens),
            "text": config.text_vocab_size,
            "image": config.image_codebook_size,
            "action": config.action_codebook_size,
            "proprio": config.proprio_codebook_size,
        }
        self._ranges: dict[str, tuple[int, int]] = {}
        start = 0
        for name in MODALITIES:
            self._ranges[name] = (start, start + sizes[name])
            start += sizes[name]
        self._size = start
        self._special_ids = {tok: i for i, tok in enumerate(config.special_tokens)}

    # -- ids -----------------------------------------------------------------
    @property
    def size(self) -> int:
        """Total number of ids ``V``."""
        return self._size

    def __len__(self) -> int:
        return self._size

    @property
    def pad_id(self) -> int:
        return self._special_ids["[PAD]"]

    @property
    def mask_id(self) -> int:
        return self._special_ids["[MASK]"]

    @property
    def special_tokens(self) -> tuple[str, ...]:
        return self.config.special_tokens

    def token_id(self, token: str) -> int:
        """Global id of a special token such as ``"[SEP_ACT]"``."""
        if token not in self._special_ids:
            raise ValueError(f"Unknown special token {token!r}; known: {self.special_tokens}.")
        return self._special_ids[token]

    def has(self, modality: str) -> bool:
        """Whether ``modality`` owns at least one id (proprio may be disabled)."""
        start, stop = self.range_of(modality)
        return stop > start

    def range_of(self, modality: str) -> tuple[int, int]:
        """``(start, stop)`` of a modality's global ids (``stop`` excluded)."""
        if modality not in self._ranges:
            raise ValueError(f"Unknown modality {modality!r}; expected one of {MODALITIES}.")
        return self._ranges[modality]

    @staticmethod
    def modality_index(modality: str) -> int:
        """Integer id of a modality name (index in :data:`MODALITIES`)."""
        if modality not in MODALITIES:
            raise ValueError(f"Unknown modality {modality!r}; expected one of {MODALITIES}.")
        return MODALITIES.index(modality)

    # -- local <-> global ----------------------------------------------------
    def to_global(self, modality: str, local: torch.Tensor) -> torch.Tensor:
        """Map local codes ``0 .. size-1`` of ``modality`` to global ids."""
        start, stop = self.range_of(modality)
        local = torch.as_tensor(local)
        if local.numel() and (int(local.min()) < 0 or int(local.max()) >= stop - start):
            raise ValueError(
                f"{modality} codes must lie in [0, {stop - start}), got values in "
                f"[{int(local.min())}, {int(local.max())}]."
            )
        return local.long() + start

    def to_local(self, modality: str, ids: torch.Tensor) -> torch.Tensor:
        """Map global ids of ``modality`` back to its local codes."""
        start, stop = self.range_of(modality)
        ids = torch.as_tensor(ids)
        if ids.numel() and (int(ids.min()) < start or int(ids.max()) >= stop):
            raise ValueError(
                f"{modality} ids must lie in [{start}, {stop}), got values in "
                f"[{int(ids.min())}, {int(ids.max())}]."
            )
        return ids.long() - start

    def modality_of(self, ids: torch.Tensor) -> torch.Tensor:
        """Modality id (index in :data:`MODALITIES`) of every global id."""
        ids = torch.as_tensor(ids)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self._size):
            raise ValueError(f"ids must lie in [0, {self._size}), got [{int(ids.min())}, {int(ids.max())}].")
        stops = torch.tensor([self._ranges[m][1] for m in MODALITIES], device=ids.device)
        return torch.bucketize(ids, stops, right=True)

    # -- restriction ---------------------------------------------------------
    def bounds(self, modality_ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-position ``(low, high)`` id bounds for modality ids ``[...]``."""
        table = torch.tensor([self._ranges[m] for m in MODALITIES], dtype=torch.long)
        table = table.to(modality_ids.device)
        return table[modality_ids, 0], table[modality_ids, 1]

    def allowed_mask(self, modality_ids: torch.Tensor) -> torch.Tensor:
        """Bool ``[..., V]``: True where the id lies in the position's modality range."""
        low, high = self.bounds(modality_ids)
        ids = torch.arange(self._size, device=modality_ids.device)
        return (ids >= low.unsqueeze(-1)) & (ids < high.unsqueeze(-1))

    # -- serialisation -------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-serialisable description (sizes and special tokens)."""
        out = asdict(self.config)
        out["special_tokens"] = list(self.config.special_tokens)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "UnifiedVocabulary":
        return cls(VocabularyConfig(**data))

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> "UnifiedVocabulary":
        return cls.from_dict(json.loads(text))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, UnifiedVocabulary) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        ranges = ", ".join(f"{m}={self._ranges[m]}" for m in MODALITIES)
        return f"UnifiedVocabulary(size={self._size}, {ranges})"
