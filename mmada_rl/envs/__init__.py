"""ManiSkill3 tasks as TorchRL environments (SAPIEN CPU physics, CPU Vulkan rendering)."""
from mmada_rl.envs.maniskill import EnvConfig, make_env, make_gym_env, privileged_state_dim, task_camera_fov
from mmada_rl.envs.tasks import SUPPORTED_TASKS, TASKS, TaskSpec, UnknownTaskError, task_spec
from mmada_rl.envs.vulkan import VulkanUnavailableError

__all__ = [
    "EnvConfig",
    "SUPPORTED_TASKS",
    "TASKS",
    "TaskSpec",
    "UnknownTaskError",
    "VulkanUnavailableError",
    "make_env",
    "make_gym_env",
    "privileged_state_dim",
    "task_camera_fov",
    "task_spec",
]
