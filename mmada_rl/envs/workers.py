"""How the processes that run a simulator start: forked from a server that has the libraries imported.

Three things run ManiSkill in processes of their own: ``ParallelEnv``'s env workers
(:func:`~mmada_rl.envs.make_env` with ``num_workers > 1``), the demonstration
collection workers (:func:`~mmada_rl.data.collect_workers.parallel_attempts`) and
the fine-tuning collector's process
(:class:`~mmada_rl.training.collect_process.CollectAheadProcess`).

They cannot be forked from the process that asks for them: ``fork`` deadlocks
SAPIEN at the first reset once the parent has a simulator, and would copy the
learner's threads. A spawned process is safe but starts from nothing: it imports
torch, tensordict, TorchRL and ManiSkill again before it builds its env (a third
of a rendering worker's start-up CPU here, ~9 s: ``benchmarks/worker_start.py``).
:func:`worker_context` uses Python's ``forkserver`` start method instead: the
first worker starts one server process, fresh like a
spawned one, that imports :data:`PRELOAD` once; each worker is then forked from
that server, which has never built a simulator or run torch's thread pools, with
the imports done. Every later worker of the same parent process (the second
``ParallelEnv`` of a run, the evaluation env's workers, the next collection)
starts without importing them again.

What each worker does once it has started is unchanged: it builds its own
simulator from the picklable factory it was given, as a spawned one would.

The server keeps the standard output and error that its parent had when it
started, and so do the workers forked from it: a process that redirects its file
descriptors 1 and 2 later (the tests' batched recipe runs do, per run) stops the
server first (:func:`stop_server`) for the next workers to write to the new place.

``MMADA_RL_WORKER_START=spawn`` in the environment starts them spawned instead
(where ``forkserver`` is unavailable, or to compare: ``benchmarks/worker_start.py``).
"""
from __future__ import annotations

import multiprocessing as mp
import multiprocessing.forkserver
import os
from multiprocessing.context import BaseContext

__all__ = ["PRELOAD", "START_METHOD_VARIABLE", "stop_server", "worker_context"]

START_METHOD_VARIABLE = "MMADA_RL_WORKER_START"
START_METHODS = ("forkserver", "spawn")  # never "fork": see above
# what every worker imports to build its env; importing them builds no simulator and starts no thread
PRELOAD: tuple[str, ...] = ("torch", "tensordict", "torchrl.envs", "mani_skill.envs", "mmada_rl.envs.maniskill")


def worker_context() -> BaseContext:
    """The ``multiprocessing`` context to start simulator workers from: ``forkserver`` with :data:`PRELOAD`,
    or what :data:`START_METHOD_VARIABLE` names.

    The modules to preload are registered with the server before it starts (the first worker started starts
    it); a server already running keeps what it has. ``ParallelEnv`` takes the start method by name
    (``worker_context().get_start_method()``), and its workers then come from the same server.

    Raises:
        ValueError: :data:`START_METHOD_VARIABLE` names another start method.

    Examples:
        >>> worker_context().get_start_method()
        'forkserver'
    """
    method = os.environ.get(START_METHOD_VARIABLE) or START_METHODS[0]
    if method not in START_METHODS:
        raise ValueError(f"{START_METHOD_VARIABLE}={method!r}: simulator workers start by "
                         f"{' or '.join(START_METHODS)} (fork deadlocks SAPIEN).")
    ctx = mp.get_context(method)
    if method == "forkserver":
        ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def stop_server() -> None:
    """Stop this process's fork server, if one runs, and wait for it to exit (so its CPU, and that of the workers
    it reaped, counts as this process's children's); the next worker started starts a new one. Workers already
    started keep running."""
    multiprocessing.forkserver._forkserver._stop()  # CPython's own stop (private, used by its tests); no-op if none
