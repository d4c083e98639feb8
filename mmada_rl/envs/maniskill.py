"""ManiSkill3 tasks (SAPIEN, CPU physics, CPU Vulkan rendering) as TorchRL environments.

``make_env`` returns a :class:`~torchrl.envs.TransformedEnv` whose tensordicts follow
TorchRL's canonical VLA schema::

    observation: {image: uint8 [3, H, W], state: float32 [S]}
    language_instruction: str
    action: float32 [A]
    next: {observation, reward, done, terminated, truncated, success, ...}
    step_count: int64 [1]
"""
from __future__ import annotations

import threading
import warnings
from dataclasses import asdict, dataclass
from collections.abc import Mapping
from typing import Callable, Literal

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import Binary, Unbounded
from torchrl.envs import Compose, GymWrapper, ParallelEnv, RenameTransform, StepCounter, Transform, TransformedEnv
from torchrl.envs.gym_like import default_info_dict_reader

from mmada_rl.envs.brdf_lut import install as install_brdf_lut
from mmada_rl.envs.instruction import InstructionTransform
from mmada_rl.envs.tasks import task_option, task_spec
from mmada_rl.keys import GROUP_KEY, IMAGE_KEY, PRIVILEGED_STATE_KEY, STATE_KEY
from mmada_rl.envs.vulkan import VulkanUnavailableError, is_render_device_error
from mmada_rl.envs.workers import worker_context

ObsMode = Literal["rgb", "state"]
RewardMode = Literal["dense", "sparse"]

#: Our reward names mapped to ManiSkill's reward modes.
_REWARD_MODES = {"dense": "normalized_dense", "sparse": "sparse"}
#: Observation modes: camera image + proprioception, or ManiSkill's privileged state vector.
OBS_MODES = ("rgb", "state")
#: Seeds of ``ParallelEnv`` worker ``w`` start at ``train_seed + w * WORKER_SEED_STRIDE``.
WORKER_SEED_STRIDE = 100_000
#: Info entry with the seed an episode was reset with (``mmada_rl.keys.GROUP_KEY`` in transitions).
EPISODE_SEED_KEY = GROUP_KEY[-1]


@dataclass
class EnvConfig:
    """How to build a ManiSkill3 task as a TorchRL env.

    Attributes:
        task: ManiSkill task id (see :mod:`mmada_rl.envs.tasks`).
        obs_mode: ``"rgb"``: a camera image plus proprioception (and the goal
            position where the task defines one); ``"state"``: ManiSkill's full
            privileged state vector, no image.
        image_size: side of the square camera image, pixels.
        camera_fov: vertical field of view of the task's camera (``base_camera``), degrees;
            ``None`` keeps the task's own (90° for the tabletop tasks). A narrower view
            puts more pixels on the objects: PickCube-v1's 4 cm cube covers ~6 pixels of
            a 64x64 image at 90° and ~35 at 45° (same camera position, the whole spawn
            area still in view).
        control_mode: ManiSkill controller, e.g. ``"pd_ee_delta_pose"``,
            ``"pd_joint_delta_pos"``, ``"pd_joint_pos"``.
        reward: ``"dense"`` (ManiSkill's normalised dense reward, in [0, 1]) or ``"sparse"``.
        max_episode_steps: episode length; ``None`` takes the task registry's value.
        ignore_terminations: keep stepping after success until truncation
            (ManiSkill's protocol for ``success_at_end``).
        num_workers: ``ParallelEnv`` workers; 1 builds a single env.
        train_seed: ``None`` (default): resets without a seed continue the env's
            RNG. An int: episode ``e`` of worker ``w`` starts from seed
            ``train_seed + w * WORKER_SEED_STRIDE + e // group_size``, and the
            seed is reported as ``("next", "episode_seed")`` (a ``reset(seed=...)``
            still uses the seed it is given).
        group_size: consecutive episodes of a worker sharing one initial state
            (group-relative advantages compare them).
        stage_flags: also read the task's progress flags (``TaskSpec.stages``,
            e.g. PickCube-v1's ``is_grasped`` and ``is_obj_placed``) into every
            step, beside ``success`` (evaluation does; off by default, so
            demonstration buffers keep their layout).
        privileged_state: with ``obs_mode="rgb"``, also give the simulator's
            state as ``("observation", "privileged_state")``: ManiSkill's
            ``get_state()``, every actor's pose and velocities and the robot's
            joints (70 numbers on PickCube-v1, the cube's pose among them), for
            a critic trained beside a pixel policy (asymmetric actor-critic,
            Pinto et al., 2018). Off by default: policies never read it.
    """

    task: str = "PickCube-v1"
    obs_mode: ObsMode = "rgb"
    image_size: int = 64
    camera_fov: float | None = None
    control_mode: str = "pd_ee_delta_pose"
    reward: RewardMode = "dense"
    max_episode_steps: int | None = None
    ignore_terminations: bool = False
    num_workers: int = 1
    train_seed: int | None = None
    group_size: int = 1
    stage_flags: bool = False
    privileged_state: bool = False

    def __post_init__(self) -> None:
        if self.obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {self.obs_mode!r}.")
        if self.privileged_state and self.obs_mode != "rgb":
            raise ValueError(f"privileged_state=True adds the simulator state beside the image; obs_mode={self.obs_mode!r} "
                             "already is ManiSkill's privileged state: use obs_mode='rgb' or privileged_state=False.")
        if self.reward not in _REWARD_MODES:
            raise ValueError(f"reward must be 'dense' or 'sparse', got {self.reward!r}.")
        if not isinstance(self.image_size, int) or not 16 <= self.image_size <= 512:
            raise ValueError(f"image_size must be an int in [16, 512] pixels, got {self.image_size!r}.")
        if self.camera_fov is not None:
            if not (isinstance(self.camera_fov, (int, float)) and 1 <= self.camera_fov < 180):
                raise ValueError(f"camera_fov must be a field of view in degrees in [1, 180) or None, got {self.camera_fov!r}.")
            self.camera_fov = float(self.camera_fov)
        if self.max_episode_steps is not None and self.max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be positive, got {self.max_episode_steps!r}.")
        if self.num_workers < 1:
            raise ValueError(f"num_workers must be >= 1, got {self.num_workers!r}.")
        if self.group_size < 1:
            raise ValueError(f"group_size must be >= 1, got {self.group_size!r}.")
        if self.train_seed is not None and self.train_seed < 0:
            raise ValueError(f"train_seed must be >= 0, got {self.train_seed!r}.")
        task_spec(self.task)  # unknown task ids fail here, with the list of supported ones

    @property
    def episode_steps(self) -> int | None:
        """The episode length actually used."""
        return self.max_episode_steps or task_spec(self.task).max_episode_steps

    def to_dict(self) -> dict:
        return asdict(self)


def task_camera_fov(camera_fov: float | Mapping[str, float | None] | None, task: str) -> float | None:
    """The camera field of view (degrees) of ``task`` under ``camera_fov``: one value for every task
    (``None``: each task's own camera), or a mapping ``{task: degrees}`` for a multi-task model whose
    tasks' demonstrations came through different cameras (e.g. ``{"PushCube-v1": 60, "PickCube-v1": 45}``).

    Raises:
        ValueError: ``camera_fov`` is a mapping without ``task``.
    """
    return task_option(camera_fov, task, "camera_fov", "cameras", "<degrees> (null: the task's own camera)")


class CanonicalObservation(gym.Wrapper):
    """Unbatched ManiSkill observations → ``{"camera": CHW uint8, "proprio": float32}``
    (and ``"privileged"``: the simulator state, float32, with ``privileged=True``).

    (:func:`make_env` then renames them to the canonical ``("observation", "image")``
    and ``("observation", "state")``; TorchRL's ``GymWrapper`` would rename a
    ``"state"`` entry to ``"observation"`` itself, hence the neutral names.)

    Applied after ManiSkill's ``CPUGymWrapper`` (numpy, unbatched). Also turns the
    ``success`` info entry (and the ``flags`` entries) into an array, which TorchRL's
    info reader requires; a flag the info lacks (at reset) reads False.

    The image is the task's own camera (``base_camera``). Robots with cameras of
    their own add channels after it — StackCube-v1's default ``panda_wristcam``
    puts its hand camera in channels 3–5 of ManiSkill's flattened ``rgb`` — and
    those are dropped, so every task gives the policy one third-person view.
    """

    def __init__(self, env: gym.Env, obs_mode: ObsMode, flags: tuple[str, ...] = (), privileged: bool = False):
        super().__init__(env)
        self.obs_mode, self.flags, self.privileged = obs_mode, ("success", *flags), bool(privileged)
        space = env.observation_space
        if obs_mode == "rgb":
            h, w, _ = space["rgb"].shape
            spaces = dict(
                camera=gym.spaces.Box(0, 255, (3, h, w), np.uint8),
                proprio=gym.spaces.Box(-np.inf, np.inf, space["state"].shape, np.float32),
            )
            if self.privileged:
                spaces["privileged"] = gym.spaces.Box(-np.inf, np.inf, self._sim_state().shape, np.float32)
            self.observation_space = gym.spaces.Dict(**spaces)
        else:
            self.observation_space = gym.spaces.Dict(proprio=gym.spaces.Box(-np.inf, np.inf, space.shape, np.float32))

    def _sim_state(self) -> np.ndarray:
        return self.env.unwrapped.get_state().reshape(-1).cpu().numpy().astype(np.float32)

    def _obs(self, obs):
        if self.obs_mode == "rgb":
            image = np.ascontiguousarray(np.moveaxis(obs["rgb"][..., :3], -1, 0))  # the first camera only
            out = {"camera": image, "proprio": obs["state"].astype(np.float32)}
            if self.privileged:
                out["privileged"] = self._sim_state()
            return out
        return {"proprio": np.asarray(obs, dtype=np.float32)}

    def _info(self, info: dict) -> dict:
        info = dict(info)
        for flag in self.flags:
            info[flag] = np.asarray([bool(info.get(flag, False))])
        return info

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return self._obs(obs), self._info(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._obs(obs), float(reward), bool(terminated), bool(truncated), self._info(info)


class FreshContactsOnReset(gym.Wrapper):
    """Recompute the reset observation and info with the contacts of the new initial state.

    On the CPU backend ManiSkill answers contact queries (``is_grasping``, hence
    PickCube-v1's ``is_grasped`` state entry and its reward terms) from the last
    physics step, and a reset moves the bodies without stepping: the first
    observation of an episode reports the contacts of the previous episode's
    last step. After every episode that ends with the cube in hand (each
    planner demonstration does), the next one would start "grasped" with the
    gripper open in its rest pose, and only its first observation says so.
    This wrapper runs one physics step from the reset state, puts the state
    back exactly, and reads the observation and info again.

    Wraps the env returned by ``gym.make`` (inside the observation wrappers).
    """

    def reset(self, **kwargs):
        _, info = self.env.reset(**kwargs)
        base = self.env.unwrapped
        state = base.get_state_dict()
        base.scene.px.step()  # contacts at the reset configuration (velocities are zero)
        base.set_state_dict(state)
        fresh = base.get_info()
        obs = base.get_obs(fresh)
        base._last_obs = obs
        return obs, {**info, **fresh}


#: Held by every reset of a :func:`make_gym_env` env (:class:`ResetHoldsTorchRNG`). ManiSkill's reset seeds torch's
#: process-wide RNG with the episode's seed and puts it back after (``torch.random.fork_rng``); one RNG serves all the
#: threads of a process. A thread that draws from it while another resets an env in the same process (the
#: fine-tuning recipe's ``collector.overlap=thread`` with the env in the process) would draw the episode's numbers,
#: then have its own stream rewound: hold this lock to draw beside such a thread.
TORCH_RNG_LOCK = threading.RLock()


class ResetHoldsTorchRNG(gym.Wrapper):
    """Reset under :data:`TORCH_RNG_LOCK`, so that the reset's use of torch's RNG never interleaves with another
    thread's draws."""

    def reset(self, **kwargs):
        with TORCH_RNG_LOCK:
            return self.env.reset(**kwargs)


class SeedSchedule(gym.Wrapper):
    """Reset episode ``e`` with seed ``first_seed + e // group_size`` unless a seed is given.

    The seed used is reported in ``info["episode_seed"]`` at reset and at every step.
    """

    def __init__(self, env: gym.Env, first_seed: int, group_size: int = 1):
        super().__init__(env)
        self.first_seed, self.group_size = int(first_seed), int(group_size)
        self.episodes, self.seed = 0, -1

    def reset(self, *, seed: int | None = None, **kwargs):
        if seed is None:
            seed = self.first_seed + self.episodes // self.group_size
            self.episodes += 1
        self.seed = int(seed)
        obs, info = self.env.reset(seed=self.seed, **kwargs)
        return obs, self._info(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._info(info)

    def _info(self, info: dict) -> dict:
        return {**info, EPISODE_SEED_KEY: np.asarray([self.seed], dtype=np.int64)}


class ManiSkillEnv(GymWrapper):
    """TorchRL's ``GymWrapper`` for one unbatched ManiSkill env.

    With ``num_envs == 1`` TorchRL assumes a batch of ``[1]``, while ManiSkill's
    ``CPUGymWrapper`` returns unbatched data; an empty batch size fixes the spec check.
    """

    def _get_batch_size(self, env):  # noqa: D401 - TorchRL hook
        return torch.Size([])


def make_gym_env(cfg: EnvConfig, *, render_mode: str | None = None) -> gym.Env:
    """The ManiSkill gym env with our observation layout, unbatched, numpy.

    Raises:
        VulkanUnavailableError: SAPIEN found no usable Vulkan device.
    """
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    kwargs = dict(
        obs_mode=cfg.obs_mode,
        sim_backend="physx_cpu",
        render_backend="cpu",
        control_mode=cfg.control_mode,
        reward_mode=_REWARD_MODES[cfg.reward],
        render_mode=render_mode,
    )
    if cfg.obs_mode == "rgb":
        kwargs["sensor_configs"] = dict(width=cfg.image_size, height=cfg.image_size)
        if cfg.camera_fov is not None:
            kwargs["sensor_configs"]["base_camera"] = dict(fov=float(np.deg2rad(cfg.camera_fov)))
    if cfg.episode_steps is not None:
        kwargs["max_episode_steps"] = cfg.episode_steps
    if cfg.obs_mode == "rgb" or render_mode is not None:
        install_brdf_lut()  # its cameras shade with the table computed once per machine, not once per process
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = gym.make(cfg.task, **kwargs)
    except RuntimeError as err:
        if is_render_device_error(err):
            raise VulkanUnavailableError(str(err)) from None
        raise
    except (AssertionError, KeyError) as err:
        raise ValueError(f"ManiSkill could not build {cfg.task!r} with control_mode={cfg.control_mode!r}: {err}") from err
    env = ResetHoldsTorchRNG(FreshContactsOnReset(env))
    if cfg.obs_mode == "rgb":
        env = FlattenRGBDObservationWrapper(env, rgb=True, depth=False, state=True)
    env = CPUGymWrapper(env, ignore_terminations=cfg.ignore_terminations)
    return CanonicalObservation(env, cfg.obs_mode, task_spec(cfg.task).stages if cfg.stage_flags else (),
                                privileged=cfg.privileged_state)


def privileged_state_dim(task: str) -> int:
    """Size of ``task``'s privileged state (:attr:`EnvConfig.privileged_state`), read from a state-only env
    (nothing rendered): every actor's 13 pose and velocity entries, each articulation's root 13 and its joints'
    positions and velocities."""
    env = make_gym_env(EnvConfig(task=task, obs_mode="state"))
    try:
        return int(env.unwrapped.get_state().reshape(-1).shape[0])
    finally:
        env.close()


def _make_single_env(cfg: EnvConfig, worker: int = 0, extra_transform: Callable[[], Transform] | None = None) -> TransformedEnv:
    gym_env = make_gym_env(cfg)
    info_keys, info_specs = ["success"], [Binary(shape=(1,), dtype=torch.bool)]
    if cfg.train_seed is not None:
        gym_env = SeedSchedule(gym_env, cfg.train_seed + worker * WORKER_SEED_STRIDE, cfg.group_size)
        info_keys.append(EPISODE_SEED_KEY)
        info_specs.append(Unbounded(shape=(1,), dtype=torch.int64))
    if cfg.stage_flags:
        stages = task_spec(cfg.task).stages
        info_keys += list(stages)
        info_specs += [Binary(shape=(1,), dtype=torch.bool) for _ in stages]
    base = ManiSkillEnv(gym_env)
    base.set_info_dict_reader(default_info_dict_reader(info_keys, spec=info_specs))
    keys = {"camera": IMAGE_KEY, "proprio": STATE_KEY}
    if cfg.obs_mode != "rgb":
        keys.pop("camera")
    if cfg.privileged_state:
        keys["privileged"] = PRIVILEGED_STATE_KEY
    nest = RenameTransform(in_keys=list(keys), out_keys=list(keys.values()))
    transforms = [nest, InstructionTransform(task_spec(cfg.task).instruction), StepCounter()]
    if extra_transform is not None:
        transforms.append(extra_transform())
    return TransformedEnv(base, Compose(*transforms))


def make_env(task: str | EnvConfig = "PickCube-v1", *, extra_transform: Callable[[], Transform] | None = None,
             **overrides) -> TransformedEnv | ParallelEnv:
    """Build a ManiSkill3 task as a TorchRL env.

    Args:
        task: a task id, or a full :class:`EnvConfig`.
        extra_transform: a picklable callable returning a transform appended to
            every single env (inside each ``ParallelEnv`` worker).
        **overrides: :class:`EnvConfig` fields (``obs_mode``, ``image_size``,
            ``control_mode``, ``reward``, ``num_workers``, ...).

    Returns:
        a ``TransformedEnv`` (``num_workers == 1``) or a ``ParallelEnv`` of them.

    Examples:
        >>> env = make_env("PickCube-v1", image_size=64)
        >>> td = env.reset()
        >>> td["observation", "image"].shape
        torch.Size([3, 64, 64])
        >>> td["language_instruction"]
        'pick up the red cube and move it to the green goal'
    """
    cfg = task if isinstance(task, EnvConfig) else EnvConfig(task=task, **overrides)
    if isinstance(task, EnvConfig) and overrides:
        cfg = EnvConfig(**{**cfg.to_dict(), **overrides})
    if cfg.num_workers == 1:
        return _make_single_env(cfg, extra_transform=extra_transform)
    # forked from a server with the imports done (mmada_rl.envs.workers): ``fork`` from here deadlocks SAPIEN.
    # device="cpu": without a device, TorchRL 0.14.1 fails to stack a rollout whose episode ends mid-chunk
    factories = [_EnvFactory(cfg, worker, extra_transform) for worker in range(cfg.num_workers)]
    return ParallelEnv(cfg.num_workers, factories, mp_start_method=worker_context().get_start_method(), device="cpu")


class _EnvFactory:
    """Picklable constructor for ``ParallelEnv`` workers."""

    def __init__(self, cfg: EnvConfig, worker: int = 0, extra_transform: Callable[[], Transform] | None = None):
        self.cfg = EnvConfig(**{**cfg.to_dict(), "num_workers": 1})
        self.worker, self.extra_transform = worker, extra_transform

    def __call__(self) -> TransformedEnv:
        return _make_single_env(self.cfg, self.worker, self.extra_transform)
