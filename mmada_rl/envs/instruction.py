"""A transform that writes the task's instruction into every reset and step."""
from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.data import Composite, NonTensor
from torchrl.envs.transforms import Transform

from mmada_rl.instructions import instruction_entry
from mmada_rl.keys import INSTRUCTION_KEY


class InstructionTransform(Transform):
    """Adds a constant natural-language instruction under ``language_instruction``.

    TorchRL's VLA schema keeps the instruction at the root of the tensordict;
    ManiSkill envs do not emit one, and TorchRL 0.14 has no transform that adds a
    constant string entry (``ToyVLAEnv`` builds it in), hence this one.

    Args:
        instruction: the instruction text, e.g. ``"pick up the red cube ..."``.
    """

    def __init__(self, instruction: str):
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"instruction must be a non-empty string, got {instruction!r}.")
        super().__init__(in_keys=[], out_keys=[INSTRUCTION_KEY])
        self.instruction = instruction

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        shape = next_tensordict.batch_size
        value = instruction_entry([self.instruction], [0] * shape.numel(), shape, next_tensordict.device)
        next_tensordict.set(INSTRUCTION_KEY, value)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[INSTRUCTION_KEY] = NonTensor(
            shape=observation_spec.shape,
            example_data=self.instruction,
            device=observation_spec.device,
        )
        return observation_spec
