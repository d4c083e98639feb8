"""ManiSkill3 tasks as TorchRL envs: real SAPIEN simulation and CPU rendering."""
from __future__ import annotations

import multiprocessing.forkserver
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mmada_rl.envs.brdf_lut import LUT_VARIABLE, brdf_lut, cache_path, compute_brdf_lut, install, lut_texture
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


# Renders PickCube-v1 in one fresh process twice: with SAPIEN's own BRDF table (the variable says "sapien", so
# make_gym_env installs nothing), then with the cached one, counting the cameras that are given it. Prints JSON.
_BRDF_FRAMES = """
import json, os
from mmada_rl.envs import brdf_lut
from mmada_rl.envs.maniskill import EnvConfig, make_gym_env

def frame():
    env = make_gym_env(EnvConfig(task="PickCube-v1", image_size=128))
    obs, _ = env.reset(seed=3)
    env.close()
    return obs["camera"]

given = []
texture = brdf_lut._texture
brdf_lut._texture = lambda: given.append(1) or texture()
os.environ[brdf_lut.LUT_VARIABLE] = "sapien"
sapiens = frame()
before = (brdf_lut.installed(), len(given))
os.environ[brdf_lut.LUT_VARIABLE] = "cached"
cached = frame()
print(json.dumps({"before": before, "after": (brdf_lut.installed(), len(given)),
                  "differ": int((cached != sapiens).sum()), "pixels": int(sapiens.size)}))
"""


@pytest.mark.slow
def test_make_gym_env_gives_its_cameras_the_cached_brdf_table_and_renders_the_same_frames():
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _BRDF_FRAMES], capture_output=True, text=True, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["before"] == [False, 0]
    assert result["after"] == [True, 2]  # the task's camera and the render camera
    # ManiSkill's scenes have no environment map, which is all the table shades: the same frame, bit for bit
    assert result["differ"] == 0, result


@pytest.mark.slow
@pytest.mark.parametrize(("shader_pack", "color_format", "tolerance"), [
    ("default", "r32g32b32a32sfloat", 2.0**-12),  # float colours: within a sixteenth of an 8-bit level
    ("minimal", "r8g8b8a8unorm", 1 / 255),  # ManiSkill's sensors' pack, 8-bit colours: within one level
])
def test_the_cached_brdf_table_shades_an_environment_map_as_sapiens_own(tmp_path, shader_pack, color_format, tolerance):
    import imageio.v3 as iio
    import sapien

    render = sapien.render
    # process-wide settings, which ManiSkill sets again (set_shader_pack) for each camera it adds
    render.set_camera_shader_dir(shader_pack)
    render.set_picture_format("Color", color_format)
    faces = []
    for i in range(6):  # a colourful environment map: each face its own gradient
        y, x = np.mgrid[0:32, 0:32]
        faces.append(str(tmp_path / f"face{i}.png"))
        iio.imwrite(faces[-1], np.stack([x * 8, y * 8, np.full_like(x, 40 * i)], -1).astype(np.uint8))
    scene = sapien.Scene()
    scene.render_system.cubemap = render.RenderCubemap(*faces)
    for k, roughness in enumerate((0.05, 0.3, 0.6, 0.9)):  # mirror-like to matte metal spheres
        builder = scene.create_actor_builder()
        material = render.RenderMaterial(base_color=[0.8, 0.8, 0.8, 1], metallic=1.0, roughness=roughness)
        builder.add_sphere_visual(radius=0.1, material=material)
        builder.build_kinematic().set_pose(sapien.Pose([0, -0.33 + 0.22 * k, 0.1]))
    tables = {"cached": brdf_lut(), "zero": np.zeros_like(brdf_lut())}
    frames = {}
    for name in ("sapien", *tables):
        camera = render.RenderCameraComponent(96, 96)
        entity = sapien.Entity()
        entity.add_component(camera)
        entity.set_pose(sapien.Pose([-0.6, 0, 0.2], [0.9848, 0, 0.1736, 0]))
        scene.add_entity(entity)  # a camera takes textures once in a scene
        if name in tables:
            camera.set_texture("BRDFLUT", lut_texture(tables[name]))
        frames[name] = camera
    scene.update_render()
    for name, camera in frames.items():
        camera.take_picture()
        color = camera.get_picture("Color")[..., :3]
        frames[name] = color / 255.0 if color.dtype == np.uint8 else color.astype(np.float64)
    zero_error = np.abs(frames["zero"] - frames["sapien"])
    cached_error = np.abs(frames["cached"] - frames["sapien"])
    assert zero_error.max() > 0.3 and (zero_error > 0.01).mean() > 0.05  # the spheres shade with the table
    # the same table up to its half floats' last bits (an 8-bit frame may round the odd value near a half level
    # the other way)
    assert cached_error.max() <= tolerance + 1e-9, cached_error.max()


def test_brdf_table_is_cached_on_disk_and_computed_again_when_unreadable(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    brdf_lut.cache_clear()
    path = cache_path(16, 64)
    assert path.parent == tmp_path / "mmada_rl" and not path.exists()
    expected = compute_brdf_lut(16, 64)
    np.testing.assert_array_equal(brdf_lut(16, 64), expected)
    np.testing.assert_array_equal(np.load(path), expected)  # written for the next process
    assert path.stat().st_mode & 0o777 == 0o644 and list(path.parent.iterdir()) == [path]  # no temporary file left

    path.write_bytes(b"not a table")
    brdf_lut.cache_clear()
    np.testing.assert_array_equal(brdf_lut(16, 64), expected)
    np.testing.assert_array_equal(np.load(path), expected)  # and replaced

    blocked = tmp_path / "a_file"
    blocked.write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))  # a cache directory that cannot be made
    brdf_lut.cache_clear()
    np.testing.assert_array_equal(brdf_lut(16, 64), expected)
    brdf_lut.cache_clear()


def test_brdf_table_matches_the_shaders_integral_at_its_known_limits():
    lut = compute_brdf_lut(64, 1024).astype(np.float64)
    scale, bias = lut[..., 0], lut[..., 1]
    # a smooth surface seen head-on reflects all the light: scale + bias -> 1
    assert scale[-1, 0] + bias[-1, 0] == pytest.approx(1.0, abs=0.02)
    assert (lut >= 0).all()
    assert bias[0, 0] > bias[-1, 0]  # the Fresnel term grows at grazing angles
    with pytest.raises(ValueError, match="size and samples must be positive"):
        compute_brdf_lut(0, 1024)


def test_brdf_table_source_is_the_cache_unless_the_environment_asks_for_sapiens(monkeypatch):
    monkeypatch.setenv(LUT_VARIABLE, "sapien")
    assert install() is False
    monkeypatch.setenv(LUT_VARIABLE, "gpu")
    with pytest.raises(ValueError, match=r"MMADA_RL_BRDF_LUT='gpu': expected one of cached, sapien"):
        install()


def test_draws_under_the_torch_rng_lock_are_the_same_beside_env_resets_in_another_thread():
    # ManiSkill's reset seeds torch's process-wide RNG with the episode's seed and puts it back; a thread drawing
    # under TORCH_RNG_LOCK (the fine-tuning learner beside collector.overlap=thread) never sees one in between
    import threading

    from mmada_rl.envs.maniskill import TORCH_RNG_LOCK

    def draws(n: int) -> list[float]:
        out = []
        for _ in range(n):
            with TORCH_RNG_LOCK:
                out.extend(torch.rand(4).tolist())
        return out

    env = make_gym_env(EnvConfig(task="PickCube-v1", obs_mode="state"))
    try:
        torch.manual_seed(0)
        alone = draws(3000)
        resets, stop = [0], threading.Event()

        def reset_until_stopped():
            while not stop.is_set():
                env.reset(seed=resets[0])
                resets[0] += 1

        resetting = threading.Thread(target=reset_until_stopped)
        torch.manual_seed(0)
        resetting.start()
        try:
            beside = draws(3000)
        finally:
            stop.set()
            resetting.join()
    finally:
        env.close()
    assert resets[0] > 1  # the draws ran beside resets
    assert beside == alone
