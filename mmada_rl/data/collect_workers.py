"""Episode attempts run side by side in worker processes, handed back in seed order.

:func:`~mmada_rl.data.collect.collect` tries one env seed after another and
keeps the episodes that pass. An attempt is set by its seed (the env
is reset with it; DART's noise is reseeded from it), so several processes, each
with its own simulator, can try the next seeds at once. :func:`parallel_attempts`
gives the attempts back in seed order, so the caller keeps and counts them as one
process would: the same seeds tried, the same ``next_seed`` to resume from.
Attempts of seeds beyond the last one taken are discarded when the caller stops.

Not bit for bit: a simulator carries a little state from one attempt to the
next, so an episode can differ in the last digits, growing after contacts, from
the one a simulator that had run other seeds before records (measured: of three
PickCube-v1 DART episodes, the second, tried by a fresh simulator, differed from
its 42nd step on, by at most 0.0013 in an action and 0.025 in the state). Each
worker takes a fixed share of the seeds (worker ``i`` of ``n``: every ``n``-th
from the ``i``-th), so one number of workers records the same buffer from run
to run.
"""
from __future__ import annotations

import multiprocessing as mp
import traceback
from multiprocessing.connection import Connection, wait
from typing import Callable, Iterator

from mmada_rl.data.sources import Attempt
from mmada_rl.envs.workers import worker_context


class CollectionWorkerError(RuntimeError):
    """A collection worker failed (its message) or ended without answering."""


def error_reply(err: BaseException, where: str) -> tuple[str, str]:
    """The ``("error", message)`` a worker process sends its parent for ``err``: its type, its text and the
    process's traceback (lost in the parent), headed by ``where`` it was raised. Called in the ``except`` block."""
    return "error", f"{type(err).__name__}: {err}\n--- in the {where} ---\n{traceback.format_exc()}"


def _serve(conn: Connection, make_source: Callable) -> None:
    """A worker: build the source, then answer each seed with its attempt until ``None``."""
    import torch

    torch.set_num_threads(1)  # one simulator per core: the workers are the parallelism
    source = None
    try:
        source = make_source()
        while True:
            seed = conn.recv()
            if seed is None:
                break
            try:
                conn.send(("attempt", source(seed)))
            except Exception as err:  # noqa: BLE001 - sent to the parent, which raises it with the seed
                conn.send(error_reply(err, "collection worker"))
    except (KeyboardInterrupt, EOFError, BrokenPipeError):  # interrupted with the parent, or the parent is gone
        pass
    except Exception as err:  # noqa: BLE001 - building the source failed
        conn.send(error_reply(err, "collection worker"))
    finally:
        if source is not None:
            source.close()


def parallel_attempts(make_source: Callable, workers: int, first_seed: int, limit: int,
                      start_timeout: float = 600.0) -> Iterator[tuple[int, Attempt]]:
    """Yield ``(seed, attempt)`` for seeds ``first_seed, first_seed + 1, ...`` (at most ``limit``), in that order,
    each attempted by one of ``workers`` processes (started by :func:`~mmada_rl.envs.workers.worker_context`).

    Args:
        make_source: a picklable callable that builds the episode source (``source(seed) -> Attempt``) in a worker.
        workers: processes, each with its own source (simulator); at most ``limit`` start.
        first_seed: the first env seed.
        limit: how many seeds may be attempted in all.
        start_timeout: seconds a worker may take to answer its first seed before it counts as lost
            (it builds its source first); later answers are waited for as long as they take.

    Raises:
        CollectionWorkerError: a worker's source raised (with the seed and its message) or a worker
            ended without answering (its exit code).

    Closing the generator (the caller stops taking attempts, or raises) stops the workers.
    """
    if workers < 1:
        raise ValueError(f"workers must be positive, got {workers}.")
    ctx = worker_context()  # not forked from here: fork deadlocks SAPIEN
    end, lookahead = first_seed + max(int(limit), 0), 2 * workers  # seeds in flight or waiting to be taken, at most
    procs: dict[Connection, mp.Process] = {}
    busy: dict[Connection, int] = {}  # worker -> the seed it is attempting
    try:
        for _ in range(min(workers, limit)):
            conn, child = ctx.Pipe()
            proc = ctx.Process(target=_serve, args=(child, make_source), name="collect-worker", daemon=True)
            proc.start()
            child.close()
            procs[conn] = proc
        idle, done = list(procs), {}
        # worker i attempts seeds first_seed + i, + i + n, ...: which env tried which seed after which does not
        # depend on timing, so the episodes (see the module's note) are the same from run to run
        upcoming = {conn: first_seed + i for i, conn in enumerate(procs)}
        started: set[Connection] = set()  # workers that have answered once (their source is built)
        for seed in range(first_seed, end):
            while seed not in done:
                for conn in [c for c in idle if upcoming[c] < min(end, seed + lookahead)]:
                    idle.remove(conn)
                    conn.send(upcoming[conn])
                    busy[conn] = upcoming[conn]
                    upcoming[conn] += len(procs)
                timeout = None if started >= set(busy) else start_timeout
                ready = wait(list(busy), timeout)
                if not ready:
                    raise CollectionWorkerError(f"no collection worker answered within {start_timeout:.0f} s of starting")
                for conn in ready:  # a failure is raised in its seed's turn, after the attempts before it
                    asked = busy.pop(conn)
                    try:
                        kind, payload = conn.recv()
                    except (EOFError, ConnectionError, OSError):
                        procs[conn].join(timeout=10)
                        done[asked] = CollectionWorkerError(f"a collection worker ended (exit code "
                                                            f"{procs[conn].exitcode}) while attempting seed {asked}")
                        continue
                    if kind == "error":
                        done[asked] = CollectionWorkerError(f"seed {asked}: {payload}")
                        continue
                    started.add(conn)
                    done[asked] = payload
                    idle.append(conn)
            attempt = done.pop(seed)
            if isinstance(attempt, CollectionWorkerError):
                raise attempt
            yield seed, attempt
    finally:
        for conn, proc in procs.items():
            if conn in busy:  # its attempt is past what the caller took: discarded
                proc.terminate()
                continue
            try:
                conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        for conn, proc in procs.items():
            proc.join(timeout=30)
            if proc.is_alive():
                proc.terminate()
                proc.join()
            conn.close()
