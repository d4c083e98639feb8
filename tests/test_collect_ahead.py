"""CollectAhead: the next batch collected in a background thread, one iteration behind the learner."""
from __future__ import annotations

import threading

import pytest
import torch

from mmada_rl.training import CollectAhead, acting_copy


def test_the_next_batch_is_collected_during_the_updates_by_the_weights_from_before_them():
    learner, acting = {"weights": 0}, {"weights": None}
    updating = [threading.Event() for _ in range(3)]  # set by the caller once its update on batch i - 1 has begun

    def batches():
        for i in range(3):
            # batches after the first are collected while the caller updates: sequentially this would time out
            if i and not updating[i].wait(timeout=30):
                raise AssertionError(f"batch {i} was not collected beside the update")
            yield acting["weights"]

    ahead = CollectAhead(batches(), sync=lambda: acting.update(weights=learner["weights"]))
    collected_by = []
    for i in range(3):
        weights, seconds = ahead.take()
        collected_by.append(weights)
        assert seconds >= 0 and not ahead.in_flight
        if i < 2:
            ahead.start()
            assert ahead.in_flight
            updating[i + 1].set()   # the update on batch i runs while batch i + 1 is collected
        learner["weights"] += 1     # the update's new weights
    ahead.close()
    # a sequential loop collects batch i by the weights after i updates; here batch i + 1 comes from those after i - 1
    assert collected_by == [0, 0, 1]


def test_a_collection_error_is_raised_by_take_and_wait_does_not_raise():
    def batches():
        yield "first"
        raise RuntimeError("the simulator died")

    ahead = CollectAhead(batches())
    assert ahead.take()[0] == "first"
    ahead.start()
    ahead.wait()  # finished (with an error) but not raised here
    with pytest.raises(RuntimeError, match="the simulator died"):
        ahead.take()
    ahead.close()


def test_starting_a_second_collection_before_taking_the_first_is_refused():
    ahead = CollectAhead(iter(range(5)))
    ahead.start()
    with pytest.raises(RuntimeError, match="take"):
        ahead.start()
    assert ahead.take()[0] == 0
    ahead.close()


def test_the_acting_copy_is_frozen_and_follows_the_learner_only_when_synced():
    torch.manual_seed(0)
    learner = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Dropout(0.5), torch.nn.Linear(4, 1)).train()
    acting = acting_copy(learner)
    assert not acting.training and learner.training
    assert all(not p.requires_grad for p in acting.parameters())
    before = [p.detach().clone() for p in acting.parameters()]
    optimizer = torch.optim.SGD(learner.parameters(), lr=0.1)
    learner(torch.ones(8, 3)).pow(2).sum().backward()
    optimizer.step()
    assert all(torch.equal(a, b) for a, b in zip(acting.parameters(), before))  # no storage shared
    acting.load_state_dict(learner.state_dict())
    assert all(torch.equal(a, p) for a, p in zip(acting.parameters(), learner.parameters()))
    assert not acting.training  # loading weights keeps eval mode
