"""Tokenizers: actions, images and instructions to discrete ids and back.

- actions: :class:`VQActionTokenizer` (the paper's residual EMA codebook),
  :class:`UniformBinActionTokenizer` and :class:`FSQActionTokenizer` (baselines),
  all sharing :class:`ActionNormalizer`;
- images: :class:`VQImageTokenizer` (a small VQ-VAE);
- instructions: :class:`TextTokenizer` (word level);
- :func:`fit_action_tokenizer` / :func:`fit_image_tokenizer`, :func:`load_tokenizer`,
  and measurements in :mod:`mmada_rl.tokenizers.report`.
"""
from mmada_rl.tokenizers.action import ActionTokenizer, ActionTokenizerConfig, TokenizerLoss
from mmada_rl.tokenizers.action_bins import UniformBinActionTokenizer, UniformBinActionTokenizerConfig
from mmada_rl.tokenizers.action_fsq import FSQActionTokenizer, FSQActionTokenizerConfig
from mmada_rl.tokenizers.action_vq import VQActionTokenizer, VQActionTokenizerConfig
from mmada_rl.tokenizers.fit import FitResult, count_dead_code_restarts, fit_action_tokenizer, fit_image_tokenizer
from mmada_rl.tokenizers.image import ImageReconstruction, VQImageTokenizer, VQImageTokenizerConfig
from mmada_rl.tokenizers.io import load_tokenizer, save_tokenizer
from mmada_rl.tokenizers.bundle import Tokenizers
from mmada_rl.tokenizers.normalize import ActionNormalizer, ActionOutOfRangeWarning
from mmada_rl.tokenizers.text import PAD_ID, UNK_ID, TextEncoding, TextTokenizer, TextTokenizerConfig

__all__ = [
    "ActionNormalizer",
    "ActionOutOfRangeWarning",
    "ActionTokenizer",
    "ActionTokenizerConfig",
    "TokenizerLoss",
    "VQActionTokenizer",
    "VQActionTokenizerConfig",
    "UniformBinActionTokenizer",
    "UniformBinActionTokenizerConfig",
    "FSQActionTokenizer",
    "FSQActionTokenizerConfig",
    "VQImageTokenizer",
    "VQImageTokenizerConfig",
    "ImageReconstruction",
    "TextTokenizer",
    "TextTokenizerConfig",
    "TextEncoding",
    "PAD_ID",
    "UNK_ID",
    "FitResult",
    "fit_action_tokenizer",
    "fit_image_tokenizer",
    "count_dead_code_restarts",
    "Tokenizers",
    "load_tokenizer",
    "save_tokenizer",
]
