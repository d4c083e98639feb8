"""The set of tokenizers a policy uses, saved to and loaded from one directory."""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from mmada_rl.tokenizers.action import ActionTokenizer
from mmada_rl.tokenizers.image import VQImageTokenizer
from mmada_rl.tokenizers.io import load_tokenizer
from mmada_rl.tokenizers.text import TextTokenizer

_REQUIRED = ("text", "image", "action")


class Tokenizers(NamedTuple):
    """Text, image, action and (optional) proprioception tokenizers; ``DIR/{name}/`` each on disk."""

    text: TextTokenizer
    image: VQImageTokenizer
    action: ActionTokenizer
    proprio: ActionTokenizer | None = None

    def save(self, directory: str | Path) -> Path:
        directory = Path(directory)
        for name, tok in self._asdict().items():
            if tok is not None:
                tok.save(directory / name)
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> Tokenizers:
        directory = Path(directory)
        missing = [n for n in _REQUIRED if not (directory / n).exists()]
        if missing:
            raise FileNotFoundError(f"{directory} holds no fitted tokenizers ({', '.join(missing)} missing); "
                                    "run `mmada-rl fit-tokenizers --data DIR --out DIR`.")
        proprio = directory / "proprio"
        return cls(*(load_tokenizer(directory / n) for n in _REQUIRED),
                   proprio=load_tokenizer(proprio) if proprio.exists() else None)
