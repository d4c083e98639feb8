"""Actors and critics of the reinforcement-learning baselines (PPO, SAC/RLPD, IQL), built for TorchRL's losses.

Every network reads the observation of :func:`mmada_rl.envs.make_env` through one
:class:`ObservationTrunk`:

* ``obs_mode="state"``: ``("observation", "state")`` ``[*B, S]`` (ManiSkill's
  privileged state vector; the SAC/IQL references), standardised with data moments;
* ``obs_mode="rgb"``: ``("observation", "image")`` uint8 ``[*B, 3, H, W]`` +
  ``("observation", "state")`` (proprio), through the imitation baselines'
  :class:`~mmada_rl.baselines.encoders.ObservationEncoder` (what our policy sees).

On top of it:

* :func:`make_actor` — a TanhNormal ``ProbabilisticActor`` (bounded by the env's
  action spec) writing ``"action"`` ``[*B, A]`` and its log-probability;
* :func:`make_qvalue` — ``Q(s, a)`` → ``"state_action_value"``, LayerNorm MLP by
  default (RLPD); SAC/IQL losses turn it into an ensemble of ``num_qvalue_nets``;
* :func:`make_value` — ``V(s)`` → ``"state_value"`` (PPO's critic, IQL's value).

:class:`OneStepChunkActor` presents a trained actor as a chunk policy of length 1
so that :func:`mmada_rl.evaluation.evaluate` runs it on the fixed evaluation seeds;
:class:`RLAgent` saves and reloads a whole loss module (actor, critics, targets,
temperature) for checkpoints.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded, TensorSpec
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator

from mmada_rl.baselines.encoders import EncoderConfig, ObservationEncoder
from mmada_rl.baselines.normalization import StateStandardizer
from mmada_rl.envs.maniskill import OBS_MODES
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, IMAGE_KEY, STATE_KEY

__all__ = [
    "ACTOR_WEIGHTS",
    "AGENT_CONFIG",
    "AGENT_WEIGHTS",
    "OneStepChunkActor",
    "ObservationTrunk",
    "RLAgent",
    "RLNetworkConfig",
    "is_rl_agent_dir",
    "load_rl_actor",
    "make_actor",
    "make_qvalue",
    "make_value",
    "observation_keys",
]

#: Files of a saved :class:`RLAgent` (a checkpoint's ``model/`` directory): the config, the whole loss
#: module (what resuming needs) and the actor alone (what :func:`load_rl_actor` evaluates).
AGENT_CONFIG = "rl_agent.json"
AGENT_WEIGHTS = "rl_agent.pt"
ACTOR_WEIGHTS = "rl_actor.pt"

_ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "mish": nn.Mish, "gelu": nn.GELU}


@dataclass
class RLNetworkConfig:
    """Sizes of the baselines' actors and critics.

    Attributes:
        obs_mode: ``"state"`` (privileged state vector) or ``"rgb"`` (image + proprio).
        state_dim: ``S``, size of ``("observation", "state")``.
        action_dim: ``A``.
        image_size: side of the square image (``rgb`` only).
        hidden_sizes: widths of the MLP after the observation trunk.
        activation: ``relu`` | ``tanh`` | ``elu`` | ``mish`` | ``gelu``.
        encoder: the image encoder (``rgb`` only; each network owns one, trained end to end).
        critic_layer_norm: LayerNorm after every hidden layer of Q and V (RLPD's fix
            for value over-estimation with high update-to-data ratios).
        actor_layer_norm: the same for the actor MLP.
        state_dependent_scale: the actor predicts its standard deviation (SAC, IQL);
            False: one learned log-std per action dimension (PPO).
        init_scale: standard deviation of the pre-tanh Gaussian at initialisation.
        scale_lb: smallest standard deviation.
        camera_fov: field of view (degrees) of the camera (``rgb``; ``None``: the task's own).
    """

    obs_mode: str = "state"
    state_dim: int = 42
    action_dim: int = 7
    image_size: int = 64
    hidden_sizes: tuple[int, ...] = (256, 256)
    activation: str = "relu"
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    critic_layer_norm: bool = True
    actor_layer_norm: bool = False
    state_dependent_scale: bool = True
    init_scale: float = 1.0
    scale_lb: float = 0.1
    camera_fov: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.encoder, dict):
            self.encoder = EncoderConfig(**self.encoder)
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        if self.obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {self.obs_mode!r}.")
        if self.activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {self.activation!r}.")
        if not self.hidden_sizes or min(self.hidden_sizes) < 1:
            raise ValueError(f"hidden_sizes must be a non-empty list of positive widths, got {list(self.hidden_sizes)!r}.")
        for name in ("state_dim", "action_dim", "image_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if not self.init_scale > 0 or not 0 < self.scale_lb < self.init_scale:
            raise ValueError(f"need 0 < scale_lb < init_scale, got scale_lb={self.scale_lb!r}, init_scale={self.init_scale!r}.")

    def to_dict(self) -> dict:
        return asdict(self)


def observation_keys(obs_mode: str) -> list:
    """The observation entries a network reads: ``[state]`` or ``[image, state]``."""
    if obs_mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}.")
    return [IMAGE_KEY, STATE_KEY] if obs_mode == "rgb" else [STATE_KEY]


class ObservationTrunk(nn.Module):
    """Observation entries (any leading batch ``[*B]``) → features ``[*B, F]``.

    Args:
        config: the network config (``obs_mode``, sizes, encoder).
        state_mean, state_std: moments of ``("observation", "state")`` in the training data (default: identity).
    """

    def __init__(self, config: RLNetworkConfig, state_mean: torch.Tensor | None = None,
                 state_std: torch.Tensor | None = None) -> None:
        super().__init__()
        self.obs_mode = config.obs_mode
        if config.obs_mode == "rgb":
            self.encoder = ObservationEncoder(config.encoder, image_size=config.image_size, state_dim=config.state_dim,
                                              state_mean=state_mean, state_std=state_std)
            self.out_features = self.encoder.out_features
        else:
            self.standardize = StateStandardizer(config.state_dim, state_mean, state_std)
            self.out_features = config.state_dim

    def forward(self, *observation: torch.Tensor) -> torch.Tensor:
        if self.obs_mode == "state":
            return self.standardize(observation[0].float())  # (*B, S)
        image, state = observation
        batch = state.shape[:-1]
        features = self.encoder(image.reshape(-1, *image.shape[-3:]), state.reshape(-1, state.shape[-1]))  # (B, F)
        return features.reshape(*batch, -1)  # (*B, F)


def _mlp(in_features: int, sizes: tuple[int, ...], out_features: int, activation: str, layer_norm: bool) -> nn.Sequential:
    layers, width = [], in_features
    for size in sizes:
        layers += [nn.Linear(width, size), *([nn.LayerNorm(size)] if layer_norm else []), _ACTIVATIONS[activation]()]
        width = size
    return nn.Sequential(*layers, nn.Linear(width, out_features))


class _ActorNet(nn.Module):
    """Observation → ``(loc, scale)`` of the pre-tanh Gaussian, each ``[*B, A]``."""

    def __init__(self, config: RLNetworkConfig, stats: tuple | None) -> None:
        super().__init__()
        self.trunk = ObservationTrunk(config, *(stats or ()))
        A, self.state_dependent = config.action_dim, config.state_dependent_scale
        self.mlp = _mlp(self.trunk.out_features, config.hidden_sizes, 2 * A if self.state_dependent else A,
                        config.activation, config.actor_layer_norm)
        # scale = scale_lb + softplus(x + bias), with bias such that x = 0 gives init_scale
        self.scale_lb = config.scale_lb
        self.scale_bias = math.log(math.expm1(config.init_scale - config.scale_lb))
        if not self.state_dependent:
            self.scale_param = nn.Parameter(torch.zeros(A))

    def forward(self, *observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.mlp(self.trunk(*observation))
        if self.state_dependent:
            loc, raw = out.chunk(2, -1)
        else:
            loc, raw = out, self.scale_param.expand_as(out)
        return loc, self.scale_lb + nn.functional.softplus(raw + self.scale_bias)


class _CriticNet(nn.Module):
    """Observation (and action) → one value ``[*B, 1]``."""

    def __init__(self, config: RLNetworkConfig, stats: tuple | None, with_action: bool) -> None:
        super().__init__()
        self.trunk = ObservationTrunk(config, *(stats or ()))
        self.with_action = with_action
        extra = config.action_dim if with_action else 0
        self.mlp = _mlp(self.trunk.out_features + extra, config.hidden_sizes, 1, config.activation, config.critic_layer_norm)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if self.with_action:
            *observation, action = inputs
            return self.mlp(torch.cat([self.trunk(*observation), action], -1))
        return self.mlp(self.trunk(*inputs))


def make_actor(config: RLNetworkConfig, action_spec: TensorSpec, stats: tuple | None = None) -> ProbabilisticActor:
    """A TanhNormal actor over ``action_spec``'s box.

    Args:
        config: sizes (``state_dependent_scale=False`` for PPO's learned log-std).
        action_spec: the env's (unbatched) bounded action spec.
        stats: ``(state_mean, state_std)`` of the training data, or ``None``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> actor = make_actor(RLNetworkConfig(state_dim=42), Bounded(-1.0, 1.0, shape=(7,)))  # an env's action_spec
        >>> td = actor(TensorDict({("observation", "state"): torch.zeros(42)}))  # sampled; DETERMINISTIC: tanh(loc)
        >>> td["action"].shape, td["action_log_prob"].shape
        (torch.Size([7]), torch.Size([]))
    """
    if tuple(action_spec.shape[-1:]) != (config.action_dim,):
        raise ValueError(f"the env's actions are {tuple(action_spec.shape)} but action_dim={config.action_dim}.")
    module = TensorDictModule(_ActorNet(config, stats), in_keys=observation_keys(config.obs_mode), out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module, in_keys=["loc", "scale"], spec=action_spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False},
        return_log_prob=True, default_interaction_type=InteractionType.RANDOM,
    )  # fmt: skip


def make_qvalue(config: RLNetworkConfig, stats: tuple | None = None) -> ValueOperator:
    """``Q(s, a)`` reading the observation and ``"action"``, writing ``"state_action_value"`` ``[*B, 1]``."""
    return ValueOperator(_CriticNet(config, stats, with_action=True), in_keys=[*observation_keys(config.obs_mode), ACTION_KEY])


def make_value(config: RLNetworkConfig, stats: tuple | None = None) -> ValueOperator:
    """``V(s)`` reading the observation, writing ``"state_value"`` ``[*B, 1]``."""
    return ValueOperator(_CriticNet(config, stats, with_action=False), in_keys=observation_keys(config.obs_mode))


class OneStepChunkActor(TensorDictModuleBase):
    """A Markov actor seen as a chunk policy of length 1 (what :func:`mmada_rl.evaluation.evaluate` runs).

    Writes ``("vla_action", "chunk")`` and ``"action"``, both ``[*B, 1, A]``, from
    the wrapped actor's ``"action"`` ``[*B, A]``; greedy (``tanh(loc)``) under
    ``set_exploration_type(DETERMINISTIC)``, as evaluation sets it.

    Args:
        actor: the trained ``ProbabilisticActor`` (shared, not copied).
        obs_mode: ``"state"`` or ``"rgb"``; evaluation builds its env with it.
        image_size: the image side (``rgb``), checked against the evaluation env.
        camera_fov: the camera's field of view in degrees (``rgb``; ``None``: the task's own).

    Examples:
        >>> result = evaluate(OneStepChunkActor(actor, "state"), "PickCube-v1", episodes=20)  # doctest: +SKIP
    """

    chunk_size = 1
    execute_steps = 1
    num_denoise_steps = 0

    def __init__(self, actor: ProbabilisticActor, obs_mode: str, image_size: int | None = None,
                 camera_fov: float | None = None) -> None:
        super().__init__()
        self.actor = actor
        self.obs_mode = obs_mode
        self.image_size = image_size if obs_mode == "rgb" else None
        self.camera_fov = camera_fov if obs_mode == "rgb" else None
        self.action_dim = int(actor.spec[ACTION_KEY].shape[-1])
        self.in_keys = observation_keys(obs_mode)
        self.out_keys = [ACTION_CHUNK_KEY, ACTION_KEY]
        self.last_decode_seconds = float("nan")

    def get_new_version(self, **kwargs) -> OneStepChunkActor:
        """Itself: one action per call is its only setting (``execute_steps=1``)."""
        if kwargs.get("execute_steps", 1) != 1 or kwargs.get("num_denoise_steps") not in (None, 0):
            raise ValueError(f"a one-step actor executes one action per call; got {kwargs}.")
        return self

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        action = self.actor(tensordict.select(*self.in_keys)).get(ACTION_KEY)  # (*B, A)
        self.last_decode_seconds = time.perf_counter() - start
        tensordict.set(ACTION_CHUNK_KEY, action.unsqueeze(-2))  # (*B, 1, A)
        tensordict.set(ACTION_KEY, action.unsqueeze(-2))
        return tensordict


class RLAgent(nn.Module):
    """What a checkpoint's ``model/`` holds: the whole TorchRL loss module of one baseline, and its actor.

    The loss module owns the trained parameters (actor, the Q ensemble, V, target
    copies, SAC's temperature), so saving its state dict is what resuming needs.
    Rebuild the same loss from the config, then :meth:`load` into it. The actor is
    also saved alone, with its action bounds, so that :func:`load_rl_actor` (and
    ``mmada-rl eval --checkpoint``) can run it without the recipe that built the loss.

    Args:
        algo: ``"ppo"`` | ``"sac"`` | ``"iql"``.
        config: the networks' config.
        loss_module: the TorchRL loss (``ClipPPOLoss``, ``SACLoss``, ``IQLLoss``).
        actor: the actor the loss trains (the ``ProbabilisticActor`` of :func:`make_actor`,
            sharing its parameters); ``None`` saves the loss module only.
    """

    def __init__(self, algo: str, config: RLNetworkConfig, loss_module: nn.Module,
                 actor: ProbabilisticActor | None = None) -> None:
        super().__init__()
        self.algo, self.config, self.loss_module = algo, config, loss_module
        self.actor = actor

    def save(self, directory: str | Path) -> Path:
        """Write ``rl_agent.json`` (algo, network config, action bounds), ``rl_agent.pt`` (the loss
        module's state dict) and, with an actor, ``rl_actor.pt`` (its state dict)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        weights = {AGENT_WEIGHTS: self.loss_module}
        payload = {"algo": self.algo, "config": self.config.to_dict(),
                   "num_parameters": sum(p.numel() for p in self.loss_module.parameters())}
        if self.actor is not None:
            weights[ACTOR_WEIGHTS] = self.actor
            box = self.actor.spec[ACTION_KEY].space
            payload["action_low"], payload["action_high"] = box.low.tolist(), box.high.tolist()
        for name, module in weights.items():
            tmp = directory / f".{name}.tmp"
            torch.save({k: v.detach().cpu() for k, v in module.state_dict().items()}, tmp)
            tmp.replace(directory / name)
        tmp = directory / f".{AGENT_CONFIG}.tmp"
        tmp.write_text(json.dumps(payload, indent=2))
        tmp.replace(directory / AGENT_CONFIG)
        return directory

    def load(self, directory: str | Path) -> None:
        """Load the weights saved in ``directory`` (same algo and network config required)."""
        payload = _agent_payload(directory)
        if payload["algo"] != self.algo:
            raise ValueError(f"{directory} holds a {payload['algo']} agent but algo={self.algo}; resume with algo={payload['algo']}.")
        saved = RLNetworkConfig(**payload["config"])
        if saved != self.config:
            raise ValueError(f"{directory} was trained with network config {saved.to_dict()}, "
                             f"not {self.config.to_dict()}; resume with the run's own config.")
        self.loss_module.load_state_dict(torch.load(Path(directory) / AGENT_WEIGHTS, weights_only=True))


def is_rl_agent_dir(path: str | Path) -> bool:
    """Whether ``path`` holds a saved :class:`RLAgent` (``rl_agent.json``)."""
    return (Path(path) / AGENT_CONFIG).is_file()


def _agent_payload(directory: str | Path) -> dict:
    if not is_rl_agent_dir(directory):
        raise FileNotFoundError(f"{directory} holds no RL baseline ({AGENT_CONFIG} missing).")
    return json.loads((Path(directory) / AGENT_CONFIG).read_text())


def load_rl_actor(directory: str | Path, *, device: str | torch.device = "cpu") -> OneStepChunkActor:
    """The trained actor saved in ``directory`` by :meth:`RLAgent.save`, as the one-step chunk policy
    that :func:`mmada_rl.evaluation.evaluate` runs (greedy under its deterministic exploration type).

    Examples:
        >>> actor = load_rl_actor("runs/online_sac_PickCube-v1_s0/checkpoints/step_00050000/model")  # doctest: +SKIP
        >>> actor.obs_mode, actor.chunk_size  # doctest: +SKIP
        ('state', 1)
    """
    payload = _agent_payload(directory)
    if not (Path(directory) / ACTOR_WEIGHTS).is_file() or "action_low" not in payload:
        raise FileNotFoundError(f"{directory} holds a {payload['algo']} agent saved without its actor ({ACTOR_WEIGHTS}); "
                                "checkpoints written by recipes/baselines/online.py include it.")
    config = RLNetworkConfig(**payload["config"])
    low, high = (torch.tensor(payload[k], dtype=torch.float32) for k in ("action_low", "action_high"))
    actor = make_actor(config, Bounded(low, high, shape=low.shape))
    actor.load_state_dict(torch.load(Path(directory) / ACTOR_WEIGHTS, weights_only=True, map_location=device))
    return OneStepChunkActor(actor.to(device), config.obs_mode, config.image_size, config.camera_fov)
