"""Demonstration and rollout buffers: collection, storage, import and chunk windows."""
from mmada_rl.data.buffer import BufferMismatchError, DemoBuffer
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.data.windows import ChunkWindowSampler, ChunkWindowTransform, make_window_buffer

__all__ = [
    "BufferMetadata",
    "BufferMismatchError",
    "ChunkWindowSampler",
    "ChunkWindowTransform",
    "DemoBuffer",
    "make_window_buffer",
]
