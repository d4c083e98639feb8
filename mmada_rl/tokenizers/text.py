"""Word-level instruction tokenizer built from the instructions it is fitted on.

Why words and not bytes: the denoiser attends over the whole sequence
``[lang | obs | goal | actions]`` at every refinement step, so its cost grows
with the square of the sequence length, and on these CPUs the sequence length is
the compute budget. ManiSkill task instructions come from a few templates
("pick up the red cube and move it to the green goal"): 12 words but 50 bytes.
A byte-level tokenizer would need no vocabulary and never meet an unknown
symbol, but would spend 4x the positions on the least informative modality.
A word vocabulary fitted on the instructions (lower-cased, punctuation split
off) is a few dozen entries, needs no download, and keeps the language span at
``max_len`` (default 16) positions; the price is that words unseen at fit time
become ``[UNK]``, so fit it on every task's instructions you will evaluate on.
Ids: ``[PAD] = 0``, ``[UNK] = 1``, then the words in sorted order.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Iterable, NamedTuple, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from mmada_rl.instructions import instruction_texts
from mmada_rl.keys import INSTRUCTION_KEY, INSTRUCTION_TOKENS_KEY
from mmada_rl.tokenizers.io import TokenizerIOMixin

__all__ = ["TextTokenizerConfig", "TextTokenizer", "TextEncoding", "PAD_ID", "UNK_ID", "split_words"]

PAD_TOKEN, UNK_TOKEN = "[PAD]", "[UNK]"
PAD_ID, UNK_ID = 0, 1
_WORD = re.compile(r"\w+|[^\w\s]")


def split_words(text: str) -> list[str]:
    """Lower-cases ``text`` and splits it into words and punctuation marks."""
    return _WORD.findall(text.lower())


@dataclass
class TextTokenizerConfig:
    """Config of :class:`TextTokenizer`.

    Attributes:
        max_len: fixed number of ids per instruction (padded with ``[PAD]``).
        words: the fitted vocabulary without the special tokens (set by ``fit``).
    """

    max_len: int = 16
    words: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        self.words = tuple(self.words)
        if self.max_len < 1:
            raise ValueError(f"max_len must be >= 1, got {self.max_len}.")
        if len(set(self.words)) != len(self.words):
            raise ValueError("words must be unique.")
        if {PAD_TOKEN, UNK_TOKEN} & set(self.words):
            raise ValueError(f"words must not contain the special tokens {PAD_TOKEN} / {UNK_TOKEN}.")


class TextEncoding(NamedTuple):
    """Output of :meth:`TextTokenizer.encode`."""

    ids: torch.Tensor  # long (B, max_len)
    attention_mask: torch.Tensor  # bool (B, max_len), True on words


class TextTokenizer(TokenizerIOMixin, TensorDictModuleBase):
    """Word-level tokenizer: ``list[str]`` <-> ``long [B, max_len]``.

    Args:
        config: a :class:`TextTokenizerConfig` (its ``words`` may be empty until :meth:`fit`).
        in_keys / out_keys: keys of ``forward`` (default ``"language_instruction"`` ->
            ``"instruction_tokens"``).

    Examples:
        >>> from mmada_rl.tokenizers import TextTokenizer
        >>> tok = TextTokenizer().fit(["Pick up the red cube.", "push the cube to the goal"])
        >>> enc = tok.encode(["pick up the blue cube"])
        >>> enc.ids[0, :6].tolist(), int(enc.attention_mask.sum())
        ([5, 10, 8, 1, 3, 0], 5)
        >>> tok.decode(enc.ids)
        ['pick up the [UNK] cube']
    """

    def __init__(
        self,
        config: TextTokenizerConfig | None = None,
        *,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
    ) -> None:
        super().__init__()
        self.config = config if config is not None else TextTokenizerConfig()
        self.in_keys = list(in_keys) if in_keys is not None else [INSTRUCTION_KEY]
        self.out_keys = list(out_keys) if out_keys is not None else [INSTRUCTION_TOKENS_KEY]
        self._index = {w: i for i, w in enumerate(self.vocabulary)}

    @property
    def vocabulary(self) -> tuple[str, ...]:
        """Every token by id: ``[PAD]``, ``[UNK]``, then the words."""
        return (PAD_TOKEN, UNK_TOKEN, *self.config.words)

    @property
    def vocab_size(self) -> int:
        return len(self.vocabulary)

    @property
    def max_len(self) -> int:
        return self.config.max_len

    def _words(self, text: str) -> list[str]:
        if not isinstance(text, str):
            raise ValueError(f"instructions must be strings, got {type(text).__name__}.")
        words = split_words(text)
        if not words:
            raise ValueError(f"empty instruction {text!r}: every instruction needs at least one word.")
        if len(words) > self.max_len:
            raise ValueError(
                f"instruction {text!r} has {len(words)} tokens, more than max_len={self.max_len}; raise max_len."
            )
        return words

    def fit(self, instructions: Iterable[str]) -> TextTokenizer:
        """Builds the vocabulary from ``instructions``; returns ``self``."""
        instructions = [instructions] if isinstance(instructions, str) else list(instructions)
        if not instructions:
            raise ValueError("fit needs at least one instruction.")
        words = sorted({w for text in instructions for w in self._words(text)})
        self.config = TextTokenizerConfig(max_len=self.max_len, words=tuple(words))
        self._index = {w: i for i, w in enumerate(self.vocabulary)}
        return self

    def encode(self, instructions: Sequence[str] | str) -> TextEncoding:
        """Instructions -> ids ``long [B, max_len]`` and attention mask ``bool [B, max_len]``."""
        if isinstance(instructions, str):
            instructions = [instructions]
        if not self.config.words:
            raise RuntimeError("the text tokenizer has no vocabulary; call fit(instructions) first.")
        ids = torch.full((len(instructions), self.max_len), PAD_ID, dtype=torch.long)  # (B, L)
        for row, text in enumerate(instructions):
            words = self._words(text)
            ids[row, : len(words)] = torch.tensor([self._index.get(w, UNK_ID) for w in words])
        return TextEncoding(ids=ids, attention_mask=ids != PAD_ID)

    def decode(self, ids: torch.Tensor) -> list[str]:
        """Ids ``[B, L]`` (or ``[L]``) -> instructions; padding dropped, punctuation re-attached."""
        ids = torch.as_tensor(ids)
        if ids.is_floating_point():
            raise ValueError(f"ids must be an integer tensor, got {ids.dtype}.")
        if ids.numel() and (ids.min() < 0 or ids.max() >= self.vocab_size):
            raise ValueError(f"ids must lie in [0, {self.vocab_size}), got [{int(ids.min())}, {int(ids.max())}].")
        rows = ids.reshape(-1, ids.shape[-1]) if ids.ndim else ids.reshape(1, 1)
        texts = []
        for row in rows.tolist():
            text = ""
            for i in row:
                if i == PAD_ID:
                    continue
                word = self.vocabulary[i]
                glue = not text or (len(word) == 1 and not word.isalnum() and word not in "([")
                text += word if glue else " " + word
            texts.append(text)
        return texts

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the ids of ``td[in_key]`` (str or stack of str) to ``td[out_key]``, ``[*B, max_len]``."""
        batch = tensordict.batch_size
        texts = instruction_texts(tensordict.get(self.in_keys[0]), batch)
        ids = self.encode(texts).ids.reshape(*batch, self.max_len)
        tensordict.set(self.out_keys[0], ids)
        return tensordict

