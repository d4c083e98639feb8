"""TensorDict keys of mmada_rl.

The canonical VLA keys come from TorchRL (``torchrl.data.vla.schema``) and are
re-exported here so that every module imports keys from one place. Keys that
TorchRL's schema does not define (goal image, trajectory bookkeeping, success)
are ours and live only in this module.
"""
from __future__ import annotations

from torchrl.data.vla.schema import (
    ACTION_CHUNK_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_KEY,
    ACTION_TOKENS_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    OBSERVATION_KEY,
    STATE_KEY,
    VLA_ACTION_KEY,
)

__all__ = [
    "ACTION_CHUNK_KEY",
    "ACTION_IS_PAD_KEY",
    "ACTION_KEY",
    "ACTION_TOKENS_KEY",
    "IMAGE_KEY",
    "INSTRUCTION_KEY",
    "OBSERVATION_KEY",
    "STATE_KEY",
    "VLA_ACTION_KEY",
    "PRIVILEGED_STATE_KEY",
    "GOAL_IMAGE_KEY",
    "GOAL_IS_CLIPPED_KEY",
    "ACTION_GRIPPER_ONLY_KEY",
    "TEACHER_CHUNK_KEY",
    "EPISODE_KEY",
    "STEP_KEY",
    "SUCCESS_KEY",
    "NEXT_SUCCESS_KEY",
    "INSTRUCTION_ID_KEY",
    "SEED_KEY",
    "TASK_INDEX_KEY",
    "IMAGE_TOKENS_KEY",
    "GOAL_TOKENS_KEY",
    "INSTRUCTION_TOKENS_KEY",
    "SEQUENCE_KEY",
    "NOISE_LEVEL_KEY",
    "ADVANTAGE_KEY",
    "VALUE_TARGET_KEY",
    "IS_DEMO_KEY",
    "GROUP_KEY",
]

#: ManiSkill's simulator state (every actor's pose and velocities, the robot's joints), float32 ``[*B, D]``:
#: what a critic may read in training and a policy never does (``EnvConfig.privileged_state``).
PRIVILEGED_STATE_KEY = ("observation", "privileged_state")
#: Future observation ``o_{t+K}`` that the policy predicts with the chunk, uint8 ``[*B, 3, H, W]``.
GOAL_IMAGE_KEY = ("goal", "image")
#: True where ``t+K`` ran past the episode's last frame and the goal was clipped to it.
GOAL_IS_CLIPPED_KEY = ("goal", "is_clipped")
#: True for a chunk window of which only the gripper's entries (the last of each action) are scored, bool ``[*B]``:
#: a window that starts in the hold after a grasp (``grasp_hold_gripper_only`` of ``make_window_buffer``).
ACTION_GRIPPER_ONLY_KEY = ("vla_action", "gripper_only")
#: The chunk a teacher policy predicted from a stored transition's observation, float32 ``[*B, K, A]``: what a buffer
#: relabelled by ``mmada-rl relabel`` stores beside the demonstrated action, and windows take with
#: ``teacher_labels`` (:func:`~mmada_rl.data.make_window_buffer`) as their chunk.
TEACHER_CHUNK_KEY = ("teacher", "chunk")
#: Trajectory id of every stored transition (what ``SliceSampler(traj_key=...)`` reads).
EPISODE_KEY = "episode"
#: Index of the transition inside its episode, starting at 0.
STEP_KEY = "step_count"
#: The task's own success flag for the state reached after the action.
SUCCESS_KEY = "success"
NEXT_SUCCESS_KEY = ("next", "success")
#: Index of the episode's instruction in the buffer metadata's ``instructions`` list.
INSTRUCTION_ID_KEY = "instruction_id"
#: Environment seed the episode was reset with.
SEED_KEY = "seed"
#: Which buffer (task) of a multi-task batch a window came from, int64 ``[*B]``.
TASK_INDEX_KEY = "task_index"

# -- tokens ------------------------------------------------------------------
#: Image-tokenizer codes of the current observation, long ``[*B, H', W']`` (local code ids).
IMAGE_TOKENS_KEY = ("observation", "image_tokens")
#: Image-tokenizer codes of the goal image ``o_{t+K}``, long ``[*B, H', W']``.
GOAL_TOKENS_KEY = ("goal", "tokens")
#: Text-tokenizer ids of the instruction, long ``[*B, L_text]`` (padded).
INSTRUCTION_TOKENS_KEY = "instruction_tokens"
#: Unified-vocabulary sequence ``[lang | obs | proprio | goal | actions]``, long ``[*B, L]``.
SEQUENCE_KEY = ("sequence", "ids")
#: Noise level (masking ratio) of each sample in the forward process, float ``[*B]``.
NOISE_LEVEL_KEY = ("sequence", "noise_level")
# -- reinforcement learning ---------------------------------------------------
#: Advantage of a decision (one executed chunk), float ``[*B]`` (TorchRL's default name).
ADVANTAGE_KEY = "advantage"
#: Return target of the value function for a decision, float ``[*B, 1]`` (TorchRL's default name).
VALUE_TARGET_KEY = "value_target"
#: True for demonstration samples in a mixed demo/online batch, bool ``[*B]``.
IS_DEMO_KEY = "is_demo"
#: Initial-state group of a decision (its episode's reset seed), int64 ``[*B, 1]``.
GROUP_KEY = ("next", "episode_seed")
