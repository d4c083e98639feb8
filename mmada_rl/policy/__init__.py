"""The MMaDA-VLA policy: tokenizers + unified sequence + denoiser + sampler, and its TorchRL actor."""
from mmada_rl.policy.actor import DECODING_PATH_KEY, PREDICTED_GOAL_IMAGE_KEY, MMaDAActor, check_execute_steps
from mmada_rl.policy.ensemble import MMaDAEnsemble
from mmada_rl.policy.execution import ExecutionNoise, PolicyEnv, StepLog, TemporalEnsemble, make_policy_env
from mmada_rl.policy.model import ACTION_READOUTS, MMaDAConfig, MMaDAModel, PolicyOutput, Tokenizers

__all__ = [
    "ACTION_READOUTS",
    "MMaDAConfig",
    "MMaDAModel",
    "PolicyOutput",
    "Tokenizers",
    "MMaDAActor",
    "MMaDAEnsemble",
    "DECODING_PATH_KEY",
    "PREDICTED_GOAL_IMAGE_KEY",
    "check_execute_steps",
    "ExecutionNoise",
    "PolicyEnv",
    "StepLog",
    "TemporalEnsemble",
    "make_policy_env",
]
