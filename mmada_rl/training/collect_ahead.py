"""Collect the next batch in a background thread while the updates run on this one.

An on-line recipe alternates two phases that each keep one core busy on these
2-core machines: collection (the simulator's worker process and the actor's
decoding) and the gradient updates. :class:`CollectAhead` overlaps them, as
asynchronous actor-learner loops do (IMPALA, Ape-X, TorchRL's asynchronous
collectors), but one batch ahead only: when the loop takes batch ``t`` it
starts collecting batch ``t + 1`` in a background thread, after copying the
learner's weights into the acting policy (``sync``); the updates on batch ``t``
run meanwhile. Batch ``t + 1`` is therefore collected by the weights of
one iteration earlier than a sequential loop would use (a lag of one
iteration, which off-policy updates such as reward-weighted regression absorb).

The acting policy must be a copy that nothing else touches while a batch is
collected; :func:`acting_copy` makes one. Torch ops release the GIL, so the
two threads run in parallel. Anything that must not run beside a collection
(an evaluation that sets the process-wide exploration type, a checkpoint of an
RNG the collection draws from) calls :meth:`CollectAhead.wait` first. An env in
the process resets in the collection thread, and ManiSkill's reset seeds torch's
process-wide RNG and puts it back: the updates draw from that RNG under
:data:`~mmada_rl.envs.maniskill.TORCH_RNG_LOCK`, which every reset holds, so that
no reset falls between two of their draws. An error
raised while collecting is raised again by :meth:`CollectAhead.take`.
:class:`~mmada_rl.training.CollectAheadProcess` keeps this interface with the
collector in a process of its own, where the learner and the actor do not
contend for one interpreter.

Examples:
    >>> synced = []
    >>> ahead = CollectAhead(iter(range(3)), sync=lambda: synced.append(len(synced)))
    >>> first, seconds = ahead.take()  # nothing in flight: synced and collected now
    >>> ahead.start()                  # synced, and batch 1 collected in the background...
    >>> second, _ = ahead.take()       # ...while the caller trains on batch 0
    >>> (first, second, synced, ahead.in_flight)
    (0, 1, [0, 1], False)
    >>> ahead.close()
"""
from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import torch

__all__ = ["CollectAhead", "acting_copy"]


def _timed_next(batches: Iterator) -> tuple[Any, float]:
    start = time.perf_counter()
    return next(batches), time.perf_counter() - start


class CollectAhead:
    """Runs ``next(batches)`` one batch ahead of the caller in a background thread.

    Args:
        batches: the iterator of batches (e.g. ``iter(collector)``); only the background
            thread advances it once the first batch has been taken.
        sync: called by :meth:`take` before each collection starts (copy the learner's weights
            into the acting policy here); the thread is idle while it runs.
    """

    def __init__(self, batches: Iterator, sync: Callable[[], None] | None = None) -> None:
        self._batches, self._sync = batches, sync
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="collect-ahead")
        self._future: Future | None = None

    @property
    def in_flight(self) -> bool:
        """Whether a batch is being (or has been) collected and not yet taken."""
        return self._future is not None

    def start(self) -> None:
        """Call ``sync``, then start collecting the next batch in the background thread."""
        if self._future is not None:
            raise RuntimeError("a batch is already being collected: take() it before starting another")
        if self._sync is not None:
            self._sync()
        self._future = self._pool.submit(_timed_next, self._batches)

    def take(self) -> tuple[Any, float]:
        """The next batch and the seconds its collection took (not the wait, which may be shorter).

        Waits for the batch in flight, or (none in flight, e.g. the first) syncs and collects one now.
        Raises what the collection raised. Call :meth:`start` afterwards to collect the following one.
        """
        if self._future is None:
            self.start()
        future, self._future = self._future, None
        return future.result()

    def wait(self) -> None:
        """Block until the batch in flight (if any) is collected; its result, or error, waits for :meth:`take`."""
        if self._future is not None:
            self._future.exception()

    def close(self) -> None:
        """Finish the collection in flight (discarding its batch) and stop the thread."""
        self._future = None
        self._pool.shutdown(wait=True)  # waits for the collection in flight


def acting_copy(model: torch.nn.Module) -> torch.nn.Module:
    """A frozen copy of ``model`` in eval mode to act in the collector while ``model`` trains;
    refresh it with ``copy.load_state_dict(model.state_dict())`` between collections."""
    acting = copy.deepcopy(model).eval()
    return acting.requires_grad_(False)
