"""Chunk-level value function of the fine-tuning recipes: ``V(o_t)`` from the image and the proprio state,
or, as an asymmetric critic, from the simulator's privileged state.

A separate small network (the baselines' :class:`~mmada_rl.baselines.encoders.ObservationEncoder`
and an MLP head, or an MLP over ``("observation", "privileged_state")``), so that fitting values
never moves the policy's denoiser. Wrapped as TorchRL's :class:`~torchrl.modules.ValueOperator`
reading the network's ``in_keys``, it plugs into :class:`~torchrl.objectives.value.GAE`.
"""
from __future__ import annotations

import torch
from torch import nn
from tensordict import TensorDictBase
from torchrl.modules import ValueOperator

from mmada_rl.baselines.encoders import EncoderConfig, ObservationEncoder
from mmada_rl.keys import IMAGE_KEY, PRIVILEGED_STATE_KEY, STATE_KEY

__all__ = ["PrivilegedValueNetwork", "StandardizedValue", "ValueNetwork", "make_value_operator", "value_step"]


@torch.no_grad()
def merge_moments(count: torch.Tensor, mean: torch.Tensor, sum_sq: torch.Tensor, x: torch.Tensor) -> None:
    """Merge the rows of ``x`` ``[N, *mean.shape]`` into running moments, in place (Chan et al.'s parallel update):
    ``count`` rows seen, their ``mean`` and summed squared deviations ``sum_sq``."""
    n = float(x.shape[0])
    if n == 0:
        return
    x = x.to(mean.dtype)
    batch_mean = x.mean(0)
    delta, total = batch_mean - mean, count + n
    sum_sq += ((x - batch_mean) ** 2).sum(0) + delta**2 * count * n / total
    mean += delta * n / total
    count.copy_(total)


class ValueNetwork(nn.Module):
    """``V(image, state) -> [B, 1]``.

    Args:
        encoder: sizes of the observation encoder.
        image_size: side of the square image.
        state_dim: size of the proprio state.
        hidden: width of the MLP head.
        state_mean, state_std: state moments (e.g. of the demonstrations).
    """

    in_keys = [IMAGE_KEY, STATE_KEY]

    def __init__(self, encoder: EncoderConfig, *, image_size: int, state_dim: int, hidden: int = 256,
                 state_mean: torch.Tensor | None = None, state_std: torch.Tensor | None = None) -> None:
        super().__init__()
        self.encoder = ObservationEncoder(encoder, image_size=image_size, state_dim=state_dim,
                                          state_mean=state_mean, state_std=state_std)
        self.head = nn.Sequential(nn.Linear(self.encoder.out_features, hidden), nn.Mish(), nn.Linear(hidden, 1))

    def forward(self, image: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        batch = image.shape[:-3]
        out = self.head(self.encoder(image.reshape(-1, *image.shape[-3:]), state.reshape(-1, state.shape[-1])))
        return out.reshape(*batch, 1)


class PrivilegedValueNetwork(nn.Module):
    """``V(privileged_state) -> [B, 1]``: an MLP with LayerNorm over the simulator's state.

    The state mixes metres, quaternions, joint angles and velocities: on PickCube-v1 the cube's
    angular velocity reaches 27 rad/s while positions move by centimetres. With ``normalize``
    each dimension is standardised by running moments of the states the critic has been fitted
    on (:meth:`observe`, which the recipe's value step calls) and clipped to ``[-clip, clip]``, as
    running observation normalisers in RL do; the moments are buffers, so they are saved and
    resumed with the weights.

    Args:
        state_dim: size of the privileged state (:attr:`mmada_rl.envs.EnvConfig.privileged_state`).
        hidden: width of the two hidden layers.
        normalize: standardise the input by running moments (``False``: the raw state).
        clip: bound of the standardised input (``math.inf``: unclipped).

    Examples:
        >>> import torch
        >>> net = PrivilegedValueNetwork(70, hidden=32)
        >>> net(torch.zeros(4, 70)).shape
        torch.Size([4, 1])
        >>> net.observe(torch.stack([torch.zeros(70), torch.full((70,), 10.0)]))  # mean 5, std 7.07
        >>> net.normalized(torch.tensor([[5.0, 5.0 + 50 ** 0.5, 1000.0] + [5.0] * 67]))[0, :3]
        tensor([0., 1., 5.])
        >>> make_value_operator(net).in_keys
        [('observation', 'privileged_state')]
    """

    in_keys = [PRIVILEGED_STATE_KEY]

    def __init__(self, state_dim: int, hidden: int = 256, normalize: bool = True, clip: float = 5.0) -> None:
        super().__init__()
        if state_dim < 1 or hidden < 1:
            raise ValueError(f"state_dim and hidden must be positive, got {state_dim!r} and {hidden!r}.")
        if not clip > 0:
            raise ValueError(f"clip must be positive, got {clip!r}.")
        self.normalize, self.clip = bool(normalize), float(clip)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(state_dim, dtype=torch.float64))
        self.register_buffer("sum_sq", torch.zeros(state_dim, dtype=torch.float64))  # summed squared deviations
        self.mlp = nn.Sequential(nn.Linear(state_dim, hidden), nn.LayerNorm(hidden), nn.Mish(),
                                 nn.Linear(hidden, hidden), nn.LayerNorm(hidden), nn.Mish(), nn.Linear(hidden, 1))

    def observe(self, states: torch.Tensor) -> None:
        """Merge the moments of ``states`` ``[..., D]`` into the running ones."""
        merge_moments(self.count, self.mean, self.sum_sq, states.reshape(-1, self.mean.shape[0]))

    def normalized(self, privileged_state: torch.Tensor) -> torch.Tensor:
        """The input as the MLP reads it: standardised and clipped (unchanged before any :meth:`observe`,
        or without ``normalize``)."""
        if not self.normalize or self.count < 2:
            return privileged_state
        std = (self.sum_sq / (self.count - 1)).sqrt().clamp_min(1e-3)
        standard = (privileged_state - self.mean.to(privileged_state.dtype)) / std.to(privileged_state.dtype)
        return standard.clamp(-self.clip, self.clip)

    def forward(self, privileged_state: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.normalized(privileged_state))


class StandardizedValue(nn.Module):
    """A value network that learns standardised returns (MAPPO's value normalisation).

    The fine-tuning recipes' value targets span two orders of magnitude (on PickCube-v1, 0 to 100 with the
    success absorbing) while a fresh network outputs about 0: regressed on them directly it spends much of a
    run's few critic steps climbing to their scale. Here ``network`` predicts the target standardised by running
    moments of the targets it has been fitted on (:meth:`observe_targets`, which the recipe's value step calls),
    and :meth:`forward` returns it in the targets' units, ``network(x) * std + mean``, as GAE reads it. The
    regression's loss is the squared error over :meth:`target_variance`, the standardised error. Before any
    target is observed the output is the network's own (mean 0, std 1). The moments are buffers, saved and
    resumed with the weights. :meth:`observe` passes the inputs on to ``network``'s own input moments.

    Examples:
        >>> import torch
        >>> value = StandardizedValue(PrivilegedValueNetwork(4, hidden=8))
        >>> value.observe_targets(torch.tensor([10.0, 30.0]))  # mean 20, std 14.1
        >>> raw = value.network(torch.zeros(1, 4))
        >>> torch.allclose(value(torch.zeros(1, 4)), raw * 200 ** 0.5 + 20)
        True
        >>> value.in_keys
        [('observation', 'privileged_state')]
    """

    def __init__(self, network: ValueNetwork | PrivilegedValueNetwork) -> None:
        super().__init__()
        self.network = network
        self.in_keys = list(network.in_keys)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("sum_sq", torch.zeros((), dtype=torch.float64))

    def observe(self, *inputs: torch.Tensor) -> None:
        """The network's running input moments take in ``inputs`` (a no-op for a network without them)."""
        observe = getattr(self.network, "observe", None)
        if observe is not None:
            observe(*inputs)

    def observe_targets(self, targets: torch.Tensor) -> None:
        """Merge the value targets ``targets`` (any shape) into the running moments."""
        merge_moments(self.count, self.mean, self.sum_sq, targets.reshape(-1))

    def target_variance(self) -> torch.Tensor:
        """The targets' running variance (1 before two are observed; floored at 1e-6), a float scalar."""
        if self.count < 2:
            return torch.ones(())
        return (self.sum_sq / (self.count - 1)).clamp_min(1e-6).float()

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        out = self.network(*inputs)
        if self.count < 2:
            return out
        return out * self.target_variance().sqrt().to(out.dtype) + self.mean.to(out.dtype)


def make_value_operator(network: ValueNetwork | PrivilegedValueNetwork | StandardizedValue) -> ValueOperator:
    """The network as a TorchRL ``ValueOperator`` reading its ``in_keys``, writing ``"state_value"``."""
    return ValueOperator(network, in_keys=list(network.in_keys))


def value_step(value_op, value_optim, observations: TensorDictBase, targets: torch.Tensor) -> float:
    """One gradient step of the mean squared error of ``V(o)`` (the entries of ``observations`` the critic
    reads) against ``targets``; returns the loss. The fine-tuning recipe's online regression and warm start take
    it. A critic with running input moments (:meth:`PrivilegedValueNetwork.observe`) first takes in these inputs;
    a :class:`StandardizedValue` also these targets, and steps on the error over their running variance (the
    standardised error; the loss returned stays in the targets' units)."""
    inputs = observations.select(*value_op.in_keys).clone()
    module = value_op.module
    observe = getattr(module, "observe", None)
    if observe is not None:
        observe(*(inputs.get(key) for key in value_op.in_keys))
    standardized = isinstance(module, StandardizedValue)
    if standardized:
        module.observe_targets(targets)
    pred = value_op(inputs).get("state_value")
    loss = torch.nn.functional.mse_loss(pred, targets.reshape(pred.shape).to(pred.dtype))
    value_optim.zero_grad(set_to_none=True)
    (loss / module.target_variance() if standardized else loss).backward()
    value_optim.step()
    return float(loss.detach())
