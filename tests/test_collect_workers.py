"""parallel_attempts: episode attempts in worker processes, handed back in seed order; collect(workers=...)."""
from __future__ import annotations

import os
import time

import pytest
import torch
from tensordict import TensorDict

from mmada_rl.data import DemoBuffer
from mmada_rl.data.collect import collect
from mmada_rl.data.collect_workers import CollectionWorkerError, parallel_attempts
from mmada_rl.data.sources import Attempt
from mmada_rl.envs import EnvConfig


class _ToySource:
    """An attempt per seed: a one-step episode naming its seed and the process that tried it. Even seeds take
    longer, so attempts finish out of seed order."""

    def __init__(self, fail_seed: int | None, exit_seed: int | None):
        self.fail_seed, self.exit_seed = fail_seed, exit_seed

    def __call__(self, seed: int) -> Attempt:
        if seed == self.fail_seed:
            raise RuntimeError("the planner found no path")
        if seed == self.exit_seed:
            os._exit(7)
        time.sleep(0.3 if seed % 2 == 0 else 0.0)
        episode = TensorDict({"seed": torch.tensor([seed]), "pid": torch.tensor([os.getpid()])}, batch_size=[1])
        return Attempt(episode, success=seed % 3 != 0)

    def close(self) -> None:
        pass


class _MakeToy:
    """Picklable: builds the source in the worker."""

    def __init__(self, fail_seed: int | None = None, exit_seed: int | None = None, fail_to_build: bool = False):
        self.fail_seed, self.exit_seed, self.fail_to_build = fail_seed, exit_seed, fail_to_build

    def __call__(self) -> _ToySource:
        if self.fail_to_build:
            raise ValueError("unknown task 'NoSuchTask-v1'")
        return _ToySource(self.fail_seed, self.exit_seed)


def _gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # a finished child of this process lingers as a zombie until reaped
            if os.waitpid(pid, os.WNOHANG)[0] == pid:
                return True
        except ChildProcessError:
            return True
        time.sleep(0.05)
    return False


def test_attempts_come_back_in_seed_order_each_worker_taking_a_fixed_share():
    got = list(parallel_attempts(_MakeToy(), workers=2, first_seed=5, limit=7))
    assert [seed for seed, _ in got] == list(range(5, 12))
    assert [int(a.episode["seed"][0]) for _, a in got] == list(range(5, 12))
    assert [a.success for _, a in got] == [s % 3 != 0 for s in range(5, 12)]
    pids = [int(a.episode["pid"][0]) for _, a in got]
    # worker i tries every second seed from the i-th, whichever finishes first: the same split on every run
    assert len(set(pids[0::2])) == 1 and len(set(pids[1::2])) == 1 and pids[0] != pids[1] and os.getpid() not in pids
    assert all(_gone(pid) for pid in set(pids))


def test_stopping_early_stops_the_workers_and_a_limit_bounds_the_seeds():
    attempts = parallel_attempts(_MakeToy(), workers=2, first_seed=0, limit=100)
    taken = [next(attempts) for _ in range(3)]
    attempts.close()  # what collect does once the buffer is full
    assert [s for s, _ in taken] == [0, 1, 2]
    assert all(_gone(int(a.episode["pid"][0])) for _, a in taken)
    assert [s for s, _ in parallel_attempts(_MakeToy(), workers=3, first_seed=0, limit=2)] == [0, 1]  # 2 workers start
    with pytest.raises(ValueError, match="workers must be positive"):
        next(parallel_attempts(_MakeToy(), workers=0, first_seed=0, limit=1))


@pytest.mark.parametrize("make, message, before, raised_at", [
    (_MakeToy(fail_seed=3), "seed 3: RuntimeError: the planner found no path", [0, 1, 2],
     'raise RuntimeError("the planner found no path")'),
    (_MakeToy(exit_seed=2), r"a collection worker ended \(exit code 7\) while attempting seed 2", [0, 1], None),
    (_MakeToy(fail_to_build=True), "ValueError: unknown task 'NoSuchTask-v1'", [],
     """raise ValueError("unknown task 'NoSuchTask-v1'")"""),
])
def test_a_failing_worker_ends_the_attempts_with_its_seed_and_message(make, message, before, raised_at):
    seen = []
    with pytest.raises(CollectionWorkerError, match=message) as failure:
        for seed, _ in parallel_attempts(make, workers=2, first_seed=0, limit=6):
            seen.append(seed)
    assert seen == before  # every attempt before the failing seed was handed back
    if raised_at is not None:  # the worker's traceback travels with its message, down to the line that raised
        assert "--- in the collection worker ---" in str(failure.value) and raised_at in str(failure.value)


@pytest.mark.slow
def test_collect_with_two_workers_records_the_seeds_in_order_and_resumes(tmp_path):
    """Real ManiSkill envs in two worker processes: random-policy episodes (every one kept) in seed order, the
    metadata one process would write, and a resumed run continuing from its ``next_seed``. State observations:
    a process's first rendered frame costs ~12 s of CPU here (tests/recipe_runs.py), and what is tested is the
    workers' order and resumption."""
    cfg = EnvConfig(task="PickCube-v1", obs_mode="state", max_episode_steps=3)
    out = tmp_path / "buf"
    result = collect(out, cfg, episodes=5, policy="random", workers=2, max_attempts=3, progress=False)
    assert (result.new_episodes, result.attempts) == (3, 3)
    buf = DemoBuffer.open(out)
    assert (buf.metadata.num_episodes, buf.metadata.next_seed, buf.metadata.attempts) == (3, 3, 3)
    assert buf.storage[: len(buf)]["seed"].unique_consecutive().tolist() == [0, 1, 2]
    result = collect(out, cfg, episodes=5, policy="random", workers=2, progress=False)
    buf = DemoBuffer.open(out)
    assert result.new_episodes == 2 and buf.storage[: len(buf)]["seed"].unique_consecutive().tolist() == [0, 1, 2, 3, 4]
    assert len(buf) == 5 * 3
    with pytest.raises(ValueError, match="workers must be a positive number"):
        collect(tmp_path / "other", cfg, episodes=1, torchrl_policy=torch.nn.Identity(), workers=2)


def test_the_collect_command_refuses_a_bad_number_of_workers(tmp_path, capsys):
    from mmada_rl.cli import main

    assert main(["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", str(tmp_path / "b"), "--workers", "0"]) == 2
    assert "mmada-rl collect: error: workers must be a positive number of processes" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # refused before anything is created
