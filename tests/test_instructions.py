"""The instruction entry as it is written (env, buffer) and read (tokenizer, model)."""
import pytest
import torch
from tensordict import NonTensorStack, TensorDict

from mmada_rl.envs.instruction import InstructionTransform
from mmada_rl.instructions import instruction_entry, instruction_texts
from mmada_rl.keys import INSTRUCTION_KEY

TEXTS = ["pick up the cube", "push the cube", "stack the cubes"]


def test_what_is_written_is_read_back_per_element():
    ids = [2, 0, 0, 1, 2, 1]
    td = TensorDict({}, [2, 3], device="cpu")
    td.set(INSTRUCTION_KEY, instruction_entry(TEXTS, ids, td.batch_size, td.device))
    value = td.get(INSTRUCTION_KEY)
    assert isinstance(value, NonTensorStack) and value.batch_size == (2, 3)
    assert instruction_texts(value, td.batch_size) == [TEXTS[i] for i in ids]
    assert td[1, 0][INSTRUCTION_KEY] == TEXTS[1]
    assert td[0, 2][INSTRUCTION_KEY] == TEXTS[0]


def test_one_text_is_shared_by_the_batch_and_a_scalar_is_the_text():
    assert instruction_texts("push the cube", torch.Size([4])) == ["push the cube"] * 4
    scalar = TensorDict({}, [])
    scalar.set(INSTRUCTION_KEY, instruction_entry(TEXTS, [1], scalar.batch_size))
    assert scalar[INSTRUCTION_KEY] == "push the cube"
    assert instruction_texts(scalar.get(INSTRUCTION_KEY), scalar.batch_size) == ["push the cube"]


def test_counts_that_do_not_match_the_batch_fail_clearly():
    with pytest.raises(ValueError, match="3 instruction ids for a batch of shape \\(2,\\)"):
        instruction_entry(TEXTS, [0, 1, 2], torch.Size([2]))
    with pytest.raises(ValueError, match="got 2 instructions for a tensordict of batch size \\(3,\\)"):
        instruction_texts(["a", "b"], torch.Size([3]))


def test_the_env_transform_writes_its_text_for_every_env():
    transform = InstructionTransform("pick up the cube")
    td = transform._call(TensorDict({}, [3], device="cpu"))
    assert instruction_texts(td.get(INSTRUCTION_KEY), td.batch_size) == ["pick up the cube"] * 3
    assert transform._call(TensorDict({}, []))[INSTRUCTION_KEY] == "pick up the cube"
