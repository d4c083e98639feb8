"""Collect the next batch in a process of its own while the updates run in this one.

:class:`~mmada_rl.training.CollectAhead` overlaps collection and updates with a
thread, but on these CPUs the learner and the collecting thread contend inside
one process (the actor decodes a chunk in many small ops, and TensorDict's
bookkeeping is Python), so the updates run ~1.5x slower beside it.
:class:`CollectAheadProcess` keeps :class:`CollectAhead`'s interface and its
one-batch-ahead schedule, but the collector (TorchRL's ``Collector``, its env
and a copy of the policy) lives in a process of its own
(started as :mod:`mmada_rl.envs.workers` starts simulator workers):

* :meth:`~CollectAheadProcess.start` sends the learner's current weights (a
  ``state_dict``) and the states of the collection's RNGs (named generators,
  e.g. the execution noise's and the sampled tokens'); the process loads them
  and collects one batch. Weights change only between batches, never during one.
* :meth:`~CollectAheadProcess.take` returns the batch, and the RNG states the
  collection left are written back into the caller's generators of the same
  names, so a checkpoint of them (after :meth:`~CollectAheadProcess.wait`) is
  the one a thread, or a sequential loop, would have saved: given the same
  factory, a run draws the same numbers in either, and a run resumed from a
  checkpoint continues the draws instead of starting them again.
* An error raised in the process (an env worker that failed) is raised by
  :meth:`~CollectAheadProcess.take` as :class:`CollectorProcessError`, with the
  original type and message; a process that dies raises it too.

Messages are pickled by hand (``pickle``, not torch's shared-memory reductions
that ``multiprocessing`` would use): a few tens of MB per iteration, copied, with no
file descriptor or shared-memory segment left behind per batch.

TorchRL's ``AsyncCollector`` runs a collector in another process too, but its
weight-sync schemes write the new weights into shared memory (or apply them in
a receiver thread) while a batch may be in progress, and it has no place for
the exploration RNGs' states; one request per batch keeps both exact.

Examples (``factory``: a picklable callable returning :class:`CollectorParts`, see the tests):
    >>> ahead = CollectAheadProcess(factory, weights=model.state_dict, generators={"noise": noise_rng})  # doctest: +SKIP
    >>> batch, seconds = ahead.take()    # doctest: +SKIP
    >>> ahead.start()                    # the next batch, while this one trains  # doctest: +SKIP
"""
from __future__ import annotations

import pickle
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch

from mmada_rl.data.collect_workers import error_reply
from mmada_rl.envs.workers import worker_context

__all__ = ["CollectAheadProcess", "CollectorParts", "CollectorProcessError"]


@dataclass
class CollectorParts:
    """What a factory builds in the collector's process.

    Attributes:
        batches: the batches, e.g. ``iter(collector)``.
        policy: the module whose ``load_state_dict`` takes the learner's weights before each batch.
        generators: the RNGs the collection draws from, by name (``torch.default_generator`` for the process's
            global one); each takes the state the caller's generator of that name sends with a request, and
            its state after the batch travels back.
        close: called when the process stops (e.g. ``collector.shutdown``), or ``None``.
    """

    batches: Iterator
    policy: torch.nn.Module
    generators: dict[str, torch.Generator] = field(default_factory=dict)
    close: Callable[[], None] | None = None


class CollectorProcessError(RuntimeError):
    """An error raised while collecting in the collector's process (or that process's end)."""


def _send(conn, message: Any) -> None:
    conn.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def _set_states(generators: dict[str, torch.Generator], states: dict[str, torch.Tensor]) -> None:
    """Set each of ``generators`` that ``states`` names to its state (the other side's generators of the same names)."""
    for name, state in states.items():
        if name in generators:
            generators[name].set_state(state)


def _serve(conn, factory: Callable[[], CollectorParts], num_threads: int) -> None:
    """The collector process: build the parts, then one batch per request until ``None`` or the pipe closes."""
    torch.set_num_threads(num_threads)
    try:
        parts = factory()
    except Exception as err:
        _send(conn, error_reply(err, "collector process"))
        return
    _send(conn, ("ready", None))
    try:
        while True:
            try:
                request = pickle.loads(conn.recv_bytes())
            except EOFError:  # the learner's process is gone
                break
            if request is None:
                break
            weights, rng_states = request
            try:
                parts.policy.load_state_dict(weights)
                _set_states(parts.generators, rng_states)
                start = time.perf_counter()
                batch = next(parts.batches)
                seconds = time.perf_counter() - start
                states = {name: g.get_state() for name, g in parts.generators.items()}
                _send(conn, ("batch", (batch, seconds, states)))
            except Exception as err:
                _send(conn, error_reply(err, "collector process"))
    finally:
        if parts.close is not None:
            parts.close()


class CollectAheadProcess:
    """Runs a collector one batch ahead of the caller, in a process of its own.

    Args:
        factory: a picklable callable that builds the :class:`CollectorParts` in the new process.
        weights: returns the learner's weights (a ``state_dict``) when a collection starts.
        generators: the caller's RNGs the collection draws from, by name (those of
            :attr:`CollectorParts.generators`): their states are sent with each request, and each is
            replaced by the state its namesake in the process left when the batch arrives.
        num_threads: torch threads in the collector's process.
        start_timeout: seconds to wait for ``factory`` to finish.

    Raises:
        CollectorProcessError: if ``factory`` raises (with its message) or the process does not start.
    """

    def __init__(self, factory: Callable[[], CollectorParts], weights: Callable[[], dict],
                 generators: dict[str, torch.Generator] | None = None, num_threads: int = 1,
                 start_timeout: float = 600.0) -> None:
        ctx = worker_context()  # not forked from here: fork deadlocks SAPIEN, and would copy the learner's threads
        self._conn, child = ctx.Pipe()
        self._weights, self._generators = weights, dict(generators or {})
        self._proc = ctx.Process(target=_serve, args=(child, factory, int(num_threads)), name="collect-ahead", daemon=False)
        self._proc.start()
        child.close()
        self._in_flight, self._result = False, None
        if not self._conn.poll(start_timeout):
            self._proc.terminate()
            raise CollectorProcessError(f"the collector process did not start within {start_timeout:.0f} s")
        kind, payload = self._receive()
        if kind == "error":
            self._proc.join()
            raise CollectorProcessError(f"building the collector failed: {payload}")

    @property
    def pid(self) -> int | None:
        """The collector process's id."""
        return self._proc.pid

    @property
    def in_flight(self) -> bool:
        """Whether a batch is being (or has been) collected and not yet taken."""
        return self._in_flight

    def _receive(self) -> tuple[str, Any]:
        try:
            return pickle.loads(self._conn.recv_bytes())
        except (EOFError, ConnectionError, OSError) as err:
            self._proc.join(timeout=10)
            raise CollectorProcessError(f"the collector process ended (exit code {self._proc.exitcode}) "
                                        f"without sending its batch: {type(err).__name__}") from err

    def start(self) -> None:
        """Send the learner's weights (and the RNG states); the process starts collecting the next batch."""
        if self._in_flight:
            raise RuntimeError("a batch is already being collected: take() it before starting another")
        _send(self._conn, (self._weights(), {name: g.get_state() for name, g in self._generators.items()}))
        self._in_flight = True

    def wait(self) -> None:
        """Block until the batch in flight (if any) has arrived; its result, or error, waits for :meth:`take`.
        The caller's generators then hold the states the collection left."""
        if self._in_flight and self._result is None:
            try:
                self._result = self._receive()
            except CollectorProcessError as err:
                self._result = ("lost", err)
            kind, payload = self._result
            if kind == "batch":  # (batch, seconds, RNG states by name)
                _set_states(self._generators, payload[2])

    def take(self) -> tuple[Any, float]:
        """The next batch and the seconds its collection took in the process (not the wait, which may be shorter).

        Starts a collection first if none is in flight (e.g. the first). Raises
        :class:`CollectorProcessError` if the collection failed. Call :meth:`start` afterwards for the next.
        """
        if not self._in_flight:
            self.start()
        self.wait()
        (kind, payload), self._result, self._in_flight = self._result, None, False
        if kind == "lost":
            raise payload
        if kind == "error":
            raise CollectorProcessError(payload)
        batch, seconds, _ = payload
        return batch, seconds

    def close(self, timeout: float = 60.0) -> None:
        """Finish the collection in flight (discarding its batch), stop the process and its env."""
        if self._proc.is_alive():
            self.wait()
            try:
                _send(self._conn, None)
            except (BrokenPipeError, OSError):
                pass
            self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join()
        self._in_flight, self._result = False, None
        self._conn.close()
