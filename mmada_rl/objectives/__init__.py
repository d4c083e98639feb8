"""TorchRL losses of mmada_rl."""
from mmada_rl.objectives.masked_diffusion import MaskedDiffusionLoss

__all__ = ["MaskedDiffusionLoss"]
