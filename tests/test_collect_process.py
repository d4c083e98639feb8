"""CollectAheadProcess: the next batch collected in a process of its own, one iteration behind the learner."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
import torch

from mmada_rl.training import CollectAheadProcess, CollectorParts, CollectorProcessError


class _Batches:
    """Each batch: the weight it was collected with, one number drawn from the collection's own RNG and one from the
    process's global torch RNG (where a policy samples its tokens). Batch ``i > 0``
    is only collected once ``marker(i)`` exists, which the caller creates while it updates on batch ``i - 1``."""

    def __init__(self, policy: torch.nn.Module, generator: torch.Generator, markers: Path | None, fail_at: int | None):
        self.policy, self.generator, self.markers, self.fail_at, self.i = policy, generator, markers, fail_at, 0

    def __iter__(self):
        return self

    def __next__(self):
        i, self.i = self.i, self.i + 1
        if i == self.fail_at:
            raise RuntimeError("the simulator died")
        if self.markers is not None and i:
            deadline = time.monotonic() + 30
            while not (self.markers / f"updating_{i}").exists():  # sequentially, this would never be created
                if time.monotonic() > deadline:
                    raise AssertionError(f"batch {i} was not collected beside the update")
                time.sleep(0.01)
        return {"weight": float(self.policy.weight), "draw": torch.rand(1, generator=self.generator),
                "global_draw": torch.rand(1), "pid": os.getpid()}


class _Factory:
    """Picklable: builds the parts in the collector's process."""

    def __init__(self, markers: Path | None = None, fail_at: int | None = None, fail_to_build: bool = False):
        self.markers, self.fail_at, self.fail_to_build = markers, fail_at, fail_to_build

    def __call__(self) -> CollectorParts:
        if self.fail_to_build:
            raise ValueError("no such task")
        policy = torch.nn.Linear(1, 1, bias=False).requires_grad_(False)
        generator = torch.Generator().manual_seed(12345)  # replaced by the caller's state before each batch
        return CollectorParts(_Batches(policy, generator, self.markers, self.fail_at), policy,
                              {"noise": generator, "sampling": torch.default_generator})


def _draws(seed: int, n: int) -> list[float]:
    expected = torch.Generator().manual_seed(seed)
    return [float(torch.rand(1, generator=expected)) for _ in range(n)]


def test_the_next_batch_is_collected_in_another_process_during_the_updates_by_the_weights_from_before_them(tmp_path):
    learner = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        learner.weight.fill_(0.0)
    generator, sampling = torch.Generator().manual_seed(0), torch.Generator().manual_seed(1)
    ahead = CollectAheadProcess(_Factory(markers=tmp_path), weights=learner.state_dict,
                                generators={"noise": generator, "sampling": sampling})
    collected = []
    for i in range(3):
        batch, seconds = ahead.take()
        collected.append(batch)
        assert seconds >= 0 and not ahead.in_flight
        if i < 2:
            ahead.start()
            assert ahead.in_flight
            (tmp_path / f"updating_{i + 1}").touch()  # the update on batch i runs while batch i + 1 is collected
        with torch.no_grad():
            learner.weight += 1.0  # the update's new weights
    ahead.close()
    assert {b["pid"] for b in collected} != {os.getpid()}
    # a sequential loop collects batch i by the weights after i updates; here batch i + 1 comes from those after i - 1
    assert [b["weight"] for b in collected] == [0.0, 0.0, 1.0]
    # the draws continue the caller's RNG streams (its own generator's, and the process's global one's from the
    # caller's "sampling"), and the caller's generators hold the states after them
    assert [float(b["draw"]) for b in collected] == _draws(0, 3)
    assert [float(b["global_draw"]) for b in collected] == _draws(1, 3)
    expected = torch.Generator().manual_seed(1)
    for _ in range(3):
        torch.rand(1, generator=expected)
    assert torch.equal(sampling.get_state(), expected.get_state())


def test_a_new_process_continues_the_draws_from_the_states_the_caller_saved():
    """What a checkpoint saves of the caller's generators and a resumed run restores: a new collector process
    draws the numbers the first would have drawn next, in its own generator and in its global RNG alike."""
    weights = torch.nn.Linear(1, 1, bias=False).state_dict
    generators = {"noise": torch.Generator().manual_seed(0), "sampling": torch.Generator().manual_seed(1)}
    first = CollectAheadProcess(_Factory(), weights=weights, generators=generators)
    before = [first.take()[0] for _ in range(2)]
    first.close()
    saved = {name: g.get_state() for name, g in generators.items()}
    restored = {name: torch.Generator() for name in saved}
    for name, g in restored.items():
        g.set_state(saved[name])
    second = CollectAheadProcess(_Factory(), weights=weights, generators=restored)
    after = second.take()[0]
    second.close()
    assert [float(b["draw"]) for b in [*before, after]] == _draws(0, 3)
    assert [float(b["global_draw"]) for b in [*before, after]] == _draws(1, 3)


def test_wait_brings_the_rng_state_of_the_batch_in_flight_before_it_is_taken(tmp_path):
    generator = torch.Generator().manual_seed(3)
    ahead = CollectAheadProcess(_Factory(), weights=torch.nn.Linear(1, 1, bias=False).state_dict,
                                generators={"noise": generator})
    ahead.start()
    ahead.wait()  # e.g. before a checkpoint saves the generator
    expected = torch.Generator().manual_seed(3)
    torch.rand(1, generator=expected)
    assert torch.equal(generator.get_state(), expected.get_state()) and ahead.in_flight
    assert ahead.take()[0]["draw"].shape == (1,)
    ahead.close()


def test_a_collection_error_is_raised_by_take_with_its_message_and_the_process_stops_on_close():
    ahead = CollectAheadProcess(_Factory(fail_at=1), weights=torch.nn.Linear(1, 1, bias=False).state_dict)
    assert ahead.take()[0]["weight"] is not None
    ahead.start()
    ahead.wait()  # finished (with an error) but not raised here
    with pytest.raises(CollectorProcessError, match="RuntimeError: the simulator died") as failure:
        ahead.take()
    # the process's own traceback comes with the message: where in the collector it was raised
    assert "--- in the collector process ---" in str(failure.value) and "the simulator died" in str(failure.value)
    assert 'raise RuntimeError("the simulator died")' in str(failure.value)
    pid = ahead.pid
    ahead.close()
    assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text()


def test_a_factory_error_is_raised_when_the_process_starts():
    with pytest.raises(CollectorProcessError, match="building the collector failed: ValueError: no such task"):
        CollectAheadProcess(_Factory(fail_to_build=True), weights=dict)


def test_a_collector_process_that_dies_is_reported_with_its_exit_code(tmp_path):
    ahead = CollectAheadProcess(_Factory(markers=tmp_path), weights=torch.nn.Linear(1, 1, bias=False).state_dict)
    ahead.take()
    ahead.start()  # batch 1 waits for its marker, which never comes: kill the process meanwhile
    os.kill(ahead.pid, signal.SIGKILL)
    with pytest.raises(CollectorProcessError, match=r"ended \(exit code -9\)"):
        ahead.take()
    ahead.close()


def test_starting_a_second_collection_before_taking_the_first_is_refused():
    ahead = CollectAheadProcess(_Factory(), weights=torch.nn.Linear(1, 1, bias=False).state_dict)
    ahead.start()
    with pytest.raises(RuntimeError, match="take"):
        ahead.start()
    assert ahead.take()[0]["weight"] is not None
    ahead.close()
