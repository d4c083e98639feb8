"""mmada_rl: unified discrete-diffusion vision-language-action policies on ManiSkill3, built on TorchRL."""

__version__ = "0.1.0"
