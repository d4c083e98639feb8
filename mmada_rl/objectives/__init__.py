"""TorchRL losses of mmada_rl: pretraining (masked diffusion) and fine-tuning (reward-weighted, path PPO)."""
from mmada_rl.objectives.masked_diffusion import MaskedDiffusionLoss, ScoredPositions
from mmada_rl.objectives.path_ppo import PathPPOLoss
from mmada_rl.objectives.reward_weighted import RewardWeightedDiffusionLoss, advantage_weights

__all__ = ["MaskedDiffusionLoss", "PathPPOLoss", "RewardWeightedDiffusionLoss", "ScoredPositions", "advantage_weights"]
