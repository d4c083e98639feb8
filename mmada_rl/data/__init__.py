"""Demonstration and rollout buffers: collection, storage, import and chunk windows."""
from mmada_rl.data.augment import RandomShift, StateDropout, check_shift, random_shift
from mmada_rl.data.buffer import BufferMismatchError, DemoBuffer, merge_buffers
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.data.relabel import relabel_buffer
from mmada_rl.data.windows import (
    WINDOW_SKIPS,
    ChunkWindowSampler,
    ChunkWindowTransform,
    MultiTaskWindows,
    kept_state_dims,
    make_window_buffer,
    pad_state,
    window_generators,
    every_window,
    window_skips,
)

__all__ = [
    "WINDOW_SKIPS",
    "BufferMetadata",
    "BufferMismatchError",
    "ChunkWindowSampler",
    "ChunkWindowTransform",
    "DemoBuffer",
    "MultiTaskWindows",
    "RandomShift",
    "StateDropout",
    "check_shift",
    "every_window",
    "kept_state_dims",
    "make_window_buffer",
    "merge_buffers",
    "pad_state",
    "random_shift",
    "relabel_buffer",
    "window_generators",
    "window_skips",
]
