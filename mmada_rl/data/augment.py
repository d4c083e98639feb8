"""Augmentation of training windows.

:class:`RandomShift` is DrQ's random-shift augmentation (Kostrikov et al., 2020):
pad by ``pad`` pixels with the border, crop back at a random offset, the
small-image counterpart of Diffusion Policy's random crop. It is a replay-buffer
transform: it changes the training windows only, never what a policy sees in
the env. Given several image keys (the observation and the goal frame K steps
later), every key of one window is shifted by the same offset, as if the camera
had moved, so a goal image stays aligned with its observation.

:class:`StateDropout` is the regression baselines' counterpart of the MMaDA-VLA
loss's state dropout (``loss.proprio_drop_prob``): with probability ``p`` a
window's proprioceptive state is replaced by the demonstrations' mean state
(what the encoder's standardiser maps to zero), so those windows' chunks must be
predicted from the image. A policy that can read the arm's pose tends to
predict from it and ignore where the cube is seen; this makes it look.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from mmada_rl.data.windows import kept_state_dims
from mmada_rl.keys import IMAGE_KEY, STATE_KEY

__all__ = ["RandomShift", "StateDropout", "check_shift", "random_shift"]


def check_shift(pad, name: str = "pad") -> int:
    """``pad`` if it is a whole number of pixels ``>= 0`` (0: no shift), else a ``ValueError`` naming ``name``
    (the config key that set it)."""
    if not isinstance(pad, int) or isinstance(pad, bool) or pad < 0:
        raise ValueError(f"{name}={pad!r} must be a whole number of pixels >= 0 (0: off).")
    return pad


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Shift each image of ``[B, C, H, W]`` by up to ``pad`` pixels, filling with the border (same dtype)."""
    if pad == 0:
        return images
    B, C, H, W = images.shape
    padded = F.pad(images.float(), (pad, pad, pad, pad), mode="replicate")  # (B, C, H+2p, W+2p)
    dy, dx = torch.randint(0, 2 * pad + 1, (2, B), generator=generator).tolist()
    out = torch.empty_like(images)
    # one crop per image: a slice copy each, several times faster than one gather over four index tensors
    # (benchmarks/window_sampling.py)
    for i, (y, x) in enumerate(zip(dy, dx)):
        out[i] = padded[i, :, y:y + H, x:x + W]
    return out


class RandomShift(Transform):
    """Replay-buffer transform: :func:`random_shift` of the images under ``image_keys`` (uses torch's global RNG).

    Args:
        pad: largest shift in pixels (DrQ uses 4 at 84x84).
        image_keys: the images to shift, each ``[..., 3, H, W]`` with the same batch shape and size;
            one offset per window, shared by all of them.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmada_rl.keys import GOAL_IMAGE_KEY
        >>> image = torch.randint(0, 256, (8, 3, 64, 64), dtype=torch.uint8)
        >>> windows = TensorDict({IMAGE_KEY: image, GOAL_IMAGE_KEY: image.clone()}, batch_size=[8])
        >>> shift = RandomShift(4, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY])  # the observation and its goal frame
        >>> out = shift(windows)          # in training: make_window_buffer(...).append_transform(shift)
        >>> out[IMAGE_KEY].shape, out[IMAGE_KEY].dtype
        (torch.Size([8, 3, 64, 64]), torch.uint8)
        >>> torch.equal(out[IMAGE_KEY], out[GOAL_IMAGE_KEY])  # one offset per window, shared by both
        True
    """

    def __init__(self, pad: int = 4, image_keys: Sequence = (IMAGE_KEY,)) -> None:
        check_shift(pad)
        keys = list(image_keys)
        if not keys:
            raise ValueError("image_keys must name at least one image.")
        super().__init__(in_keys=keys, out_keys=keys)
        self.pad = pad

    def shift(self, images: torch.Tensor) -> torch.Tensor:
        """:func:`random_shift` of ``[B, C, H, W]`` images by up to ``pad`` pixels."""
        return random_shift(images, self.pad)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        images = [tensordict.get(key) for key in self.in_keys]
        shapes = {tuple(image.shape) for image in images}
        if len(shapes) != 1:
            raise ValueError(f"RandomShift shifts images of one shape together; {self.in_keys} have {sorted(shapes)}.")
        shape = images[0].shape
        # the keys stacked along channels: one random offset per window moves all of them alike
        flat = torch.cat([image.reshape(-1, *shape[-3:]) for image in images], dim=1)
        shifted = self.shift(flat).split(shape[-3], dim=1)
        for key, image in zip(self.out_keys, shifted):
            tensordict.set(key, image.reshape(shape))
        return tensordict


class StateDropout(Transform):
    """Replay-buffer transform: each window's state replaced by ``mean`` with probability ``p`` (torch's global RNG).

    Args:
        p: probability with which a window's state is dropped, in ``[0, 1]``.
        mean: the state written in its place, ``[S]`` (the demonstrations' mean state).
        keep_dims: state dimensions left as they are in a dropped window (e.g. PickCube-v1's goal position,
            ``26..28``, which no camera shows).
        state_key: the state's key, ``[B, S]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> windows = TensorDict({STATE_KEY: torch.ones(1000, 4)}, batch_size=[1000])
        >>> out = StateDropout(0.3, mean=torch.zeros(4), keep_dims=[3])(windows)
        >>> dropped = out[STATE_KEY][:, 0] == 0  # the windows whose state was dropped
        >>> 0.2 < dropped.float().mean().item() < 0.4
        True
        >>> bool((out[STATE_KEY][dropped, :3] == 0).all()), bool((out[STATE_KEY][:, 3] == 1).all())  # dim 3 kept
        (True, True)
    """

    def __init__(self, p: float, mean: torch.Tensor, keep_dims: Sequence[int] = (), state_key=STATE_KEY) -> None:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"state dropout probability must lie in [0, 1], got {p!r}.")
        mean = torch.as_tensor(mean, dtype=torch.float32)
        if mean.ndim != 1:
            raise ValueError(f"mean must be one state vector [S], got shape {tuple(mean.shape)}.")
        replaced = kept_state_dims(keep_dims, mean.numel(), "keep_dims")  # the complement of keep_dims, checked
        super().__init__(in_keys=[state_key], out_keys=[state_key])
        self.p = float(p)
        self.register_buffer("mean", mean)
        dropped = torch.zeros(mean.numel(), dtype=torch.bool)
        dropped[replaced] = True
        self.register_buffer("dropped_dims", dropped)  # (S,) True where a dropped window takes the mean

    def _apply_transform(self, state: torch.Tensor) -> torch.Tensor:
        if state.shape[-1] != self.mean.numel():
            raise ValueError(f"StateDropout was built for {self.mean.numel()}-d states, got {state.shape[-1]}-d.")
        drop = torch.rand(state.shape[:-1] + (1,), device=state.device) < self.p  # (B, 1): whole windows
        replace = drop & self.dropped_dims.to(state.device)  # (B, S)
        return torch.where(replace, self.mean.to(state), state)
