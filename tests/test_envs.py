"""ManiSkill3 tasks as TorchRL envs: real SAPIEN simulation and CPU rendering."""
from __future__ import annotations

import multiprocessing.forkserver
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mmada_rl.envs.maniskill import EnvConfig, make_env, make_gym_env
from mmada_rl.envs.tasks import SUPPORTED_TASKS, UnknownTaskError, task_spec
from mmada_rl.envs.vulkan import VulkanUnavailableError
from mmada_rl.envs.workers import START_METHOD_VARIABLE, worker_context
from mmada_rl.keys import IMAGE_KEY, INSTRUCTION_KEY, PRIVILEGED_STATE_KEY, STATE_KEY


@pytest.fixture(scope="module")
def pick_env():
    env = make_env("PickCube-v1", image_size=64)
    yield env
    env.close()


def test_rgb_rollout_follows_canonical_vla_keys(pick_env):
    check_env_specs(pick_env)
    td = pick_env.rollout(4)
    assert td.shape == (4,)
    assert td[IMAGE_KEY].dtype == torch.uint8 and td[IMAGE_KEY].shape == (4, 3, 64, 64)
    assert td[IMAGE_KEY].float().std() > 0  # a rendered frame, not a blank
    assert td[STATE_KEY].dtype == torch.float32 and td[STATE_KEY].shape[-1] == 29
    assert td["action"].shape == (4, 7)
    assert td[INSTRUCTION_KEY][0] == "pick up the red cube and move it to the green goal"
    for key in ("reward", "done", "terminated", "truncated", "success"):
        assert td["next", key].shape == (4, 1), key
    assert td["step_count"].squeeze(-1).tolist() == [0, 1, 2, 3]


def test_image_size_is_configurable():
    env = make_env("PushCube-v1", image_size=32)
    try:
        assert env.reset()[IMAGE_KEY].shape == (3, 32, 32)
    finally:
        env.close()


@pytest.mark.parametrize("task", SUPPORTED_TASKS)
def test_supported_tasks_build_and_step(task):
    env = make_env(task, obs_mode="state", reward="sparse")
    try:
        td = env.rollout(3)
        assert td["next", "reward"].shape == (3, 1)
        assert set(td["next", "reward"].unique().tolist()) <= {0.0, 1.0}  # sparse
        assert td[INSTRUCTION_KEY][0] == task_spec(task).instruction
    finally:
        env.close()


def test_a_robot_camera_is_dropped_from_the_image():
    # StackCube-v1's default robot (panda_wristcam) adds a hand camera after the task's base camera
    env = make_env("StackCube-v1", image_size=32)
    try:
        assert env.observation_spec[IMAGE_KEY].shape == (3, 32, 32)
        assert env.rollout(2)[IMAGE_KEY].shape == (2, 3, 32, 32)
    finally:
        env.close()


def red_cube_pixels(image: torch.Tensor) -> int:
    """Pixels of PickCube-v1's red cube in a CHW uint8 frame."""
    r, g, b = image.int()
    return int(((r > 120) & (g < 60) & (b < 60)).sum())


def test_camera_fov_narrows_the_task_camera(pick_env):
    narrow = make_env(EnvConfig(task="PickCube-v1", camera_fov=45))
    try:
        for seed in (0, 1, 2):
            wide, close = pick_env.reset(seed=seed)[IMAGE_KEY], narrow.reset(seed=seed)[IMAGE_KEY]
            assert close.shape == wide.shape == (3, 64, 64)
            assert red_cube_pixels(close) >= 3 * max(red_cube_pixels(wide), 1)  # the same cube, bigger
    finally:
        narrow.close()


def test_dense_reward_is_normalised(pick_env):
    td = pick_env.rollout(3)
    r = td["next", "reward"]
    assert ((r >= 0) & (r <= 1)).all() and (r > 0).any()


def test_unregistered_task_gets_generic_instruction():
    spec = task_spec("PushT-v1")
    assert spec.registered
    other = task_spec("TwoRobotStackCube-v1")
    assert not other.registered and "TwoRobotStackCube" in other.instruction


def test_unknown_task_lists_supported_ones():
    with pytest.raises(UnknownTaskError, match="PickCube-v1.*PushCube-v1"):
        make_env("PickBanana-v9")


@pytest.mark.parametrize(
    "field, value, match",
    [("obs_mode", "depth", "obs_mode"), ("reward", "shaped", "reward"), ("image_size", 7, "image_size"), ("num_workers", 0, "num_workers"),
     ("camera_fov", 0, "camera_fov"), ("camera_fov", 180, "camera_fov"), ("privileged_state", True, "obs_mode='rgb'")],
)
def test_bad_env_config_values_raise_one_clear_error(field, value, match):
    overrides = {"obs_mode": "state"} if field == "privileged_state" else {}  # the state is privileged already
    with pytest.raises(ValueError, match=match):
        EnvConfig(**{field: value, **overrides})


def test_privileged_state_holds_the_simulator_state_beside_the_policy_observation():
    """``privileged_state=True`` adds ManiSkill's ``get_state()``: the cube's and the goal's positions in it are the
    ones ManiSkill's own state observation reports for the same seed, and the policy's entries do not change."""
    from mmada_rl.envs import privileged_state_dim

    env = make_env(EnvConfig(task="PickCube-v1", privileged_state=True))
    plain = make_env(EnvConfig(task="PickCube-v1"))
    state = make_env(EnvConfig(task="PickCube-v1", obs_mode="state"))
    try:
        check_env_specs(env)
        td, td_plain, td_state = env.reset(seed=3), plain.reset(seed=3), state.reset(seed=3)
        assert td[PRIVILEGED_STATE_KEY].shape == (privileged_state_dim("PickCube-v1"),) == (70,)
        assert PRIVILEGED_STATE_KEY not in td_plain.keys(True)  # off by default: buffers keep their layout
        assert torch.equal(td[STATE_KEY], td_plain[STATE_KEY]) and torch.equal(td[IMAGE_KEY], td_plain[IMAGE_KEY])
        # get_state(): table, cube, goal (13 each: position, quaternion, velocities), then the robot;
        # ManiSkill's state observation: qpos, qvel, is_grasped, tcp pose, goal position, cube pose, ...
        privileged, observed = td[PRIVILEGED_STATE_KEY], td_state[STATE_KEY]
        torch.testing.assert_close(privileged[13:16], observed[29:32])  # the cube's position
        torch.testing.assert_close(privileged[26:29], observed[26:29])  # the goal's
        rollout = env.rollout(3)
        assert rollout["next", *PRIVILEGED_STATE_KEY].shape == (3, 70)
        assert not torch.equal(rollout["next", *PRIVILEGED_STATE_KEY][-1], privileged)  # the arm moved
    finally:
        for e in (env, plain, state):
            e.close()


def test_missing_vulkan_device_gets_the_doctor_message(monkeypatch):
    import gymnasium as gym

    def no_device(*args, **kwargs):
        raise RuntimeError("vk::PhysicalDevice::createDeviceUnique: failed to find a rendering device")

    monkeypatch.setattr(gym, "make", no_device)
    with pytest.raises(VulkanUnavailableError, match="bookworm-backports"):
        make_gym_env(EnvConfig())


def _parent_pid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


@pytest.mark.slow
def test_parallel_env_passes_spec_check():
    env = make_env("PickCube-v1", num_workers=2)
    try:
        check_env_specs(env)  # starts the workers: they were forked by the fork server (mmada_rl.envs.workers)
        server = multiprocessing.forkserver._forkserver._forkserver_pid
        assert server is not None and [_parent_pid(p.pid) for p in env._workers] == [server, server]
        td = env.rollout(2)
        assert td.batch_size == (2, 2)
        assert td[IMAGE_KEY].shape == (2, 2, 3, 64, 64)
    finally:
        env.close()


def test_worker_start_method_is_the_fork_server_unless_the_environment_asks_for_spawn(monkeypatch):
    monkeypatch.delenv(START_METHOD_VARIABLE, raising=False)
    assert worker_context().get_start_method() == "forkserver"
    monkeypatch.setenv(START_METHOD_VARIABLE, "spawn")
    assert worker_context().get_start_method() == "spawn"
    monkeypatch.setenv(START_METHOD_VARIABLE, "fork")
    with pytest.raises(ValueError, match=r"MMADA_RL_WORKER_START='fork': simulator workers start by forkserver or spawn"):
        worker_context()


def test_readme_environment_snippet():
    from mmada_rl.envs import make_env as readme_make_env

    env = readme_make_env("PickCube-v1", image_size=64, control_mode="pd_ee_delta_pose", reward="dense", num_workers=1)
    try:
        td = env.rollout(10)
        assert td["observation", "image"].shape == (10, 3, 64, 64) and td["observation", "image"].dtype == torch.uint8
        assert td["observation", "state"].shape == (10, 29)
        assert td["language_instruction"][0] == "pick up the red cube and move it to the green goal"
        assert td["next", "success"].dtype == torch.bool
    finally:
        env.close()


def test_an_episode_starts_with_its_own_contacts_not_the_previous_ones(state_demos):
    """ManiSkill's CPU contact query answers from the last physics step; after a planner episode that ends
    with the cube in hand, the next reset must not report the cube grasped (``make_gym_env`` refreshes it)."""
    from mmada_rl.data import DemoBuffer

    buf = DemoBuffer.open(state_demos)
    state = buf.storage[: len(buf)].get(STATE_KEY)
    grasped = 18  # PickCube-v1's state: qpos (9), qvel (9), then extra/is_grasped
    (_, end0), (start1, _) = buf.episode_bounds()[:2]
    assert state[end0 - 1, grasped] == 1  # the first episode ends holding the cube
    assert state[start1, grasped] == 0  # the next one starts in the rest pose, grasping nothing


def test_reset_after_the_contact_refresh_is_reproducible():
    env = make_gym_env(EnvConfig(task="PickCube-v1", obs_mode="state"))
    try:
        first, _ = env.reset(seed=3)
        env.step(env.action_space.sample())
        again, _ = env.reset(seed=3)
    finally:
        env.close()
    assert (first["proprio"] == again["proprio"]).all()


def test_stage_flags_follow_a_demonstration_through_grasp_and_placement(state_demos):
    """With ``stage_flags`` the env reads the task's own progress flags: a planner demonstration's actions,
    replayed from its seed, grasp the cube before they place it, and place it by the step the task succeeds."""
    from torchrl.envs.utils import step_mdp

    from mmada_rl.data import DemoBuffer

    assert task_spec("PickCube-v1").stages == ("is_grasped", "is_obj_placed")
    episode = next(iter(DemoBuffer.open(state_demos).episodes()))
    env = make_env(EnvConfig(task="PickCube-v1", obs_mode="state", stage_flags=True))
    plain = make_env(EnvConfig(task="PickCube-v1", obs_mode="state"))
    try:
        check_env_specs(env)
        td, flags = env.reset(seed=int(episode["seed"][0])), []
        assert not td["is_grasped"].any() and not td["is_obj_placed"].any()  # nothing reached at reset
        for action in episode["action"]:
            td = env.step(td.set("action", action))
            flags.append([bool(td["next", key]) for key in ("is_grasped", "is_obj_placed", "success")])
            td = step_mdp(td)
        assert "is_grasped" not in plain.reset().keys()  # off by default: buffers keep their layout
    finally:
        env.close()
        plain.close()
    first = {name: next(i for i, f in enumerate(flags) if f[col]) for col, name in enumerate(("grasp", "placed", "success"))}
    assert first["grasp"] < first["placed"] <= first["success"], first
