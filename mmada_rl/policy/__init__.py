"""The MMaDA-VLA policy: tokenizers + unified sequence + denoiser + sampler, and its TorchRL actor."""
from mmada_rl.policy.model import MMaDAConfig, MMaDAModel, PolicyOutput, Tokenizers

__all__ = ["MMaDAConfig", "MMaDAModel", "PolicyOutput", "Tokenizers"]
