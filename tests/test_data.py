"""Demonstration buffers: planner collection, persistence, resume, import, chunk windows."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import NonTensorStack, TensorDict
from tensordict.nn import TensorDictModule

from mmada_rl.data import BufferMismatchError, DemoBuffer, RandomShift, make_window_buffer
from mmada_rl.data.buffer import InstructionLookup
from mmada_rl.data.windows import LIFT_ACTION_DIM, grasp_holds, idle_actions
from mmada_rl.data.collect import collect
from mmada_rl.data.h5_import import import_h5
from mmada_rl.data.metadata import BufferMetadata
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.envs.tasks import UnknownTaskError
from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_GRIPPER_ONLY_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_KEY,
    EPISODE_KEY,
    GOAL_IMAGE_KEY,
    GOAL_IS_CLIPPED_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    STATE_KEY,
    STEP_KEY,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo_dir(pick_demos) -> Path:
    return pick_demos


def test_planner_demos_load_back_in_the_configured_control_mode(demo_dir):
    buf = DemoBuffer.open(demo_dir, task="PickCube-v1", control_mode="pd_ee_delta_pose", image_size=64)
    m = buf.metadata
    assert m.num_episodes == 2 and m.num_transitions == len(buf) > 0
    assert m.source == "planner" and m.attempts >= 2 and m.successes >= 2
    assert m.action_dim == 7 and len(m.action_stats["p99"]) == 7
    assert m.seeds == [0, 1] or len(set(m.seeds)) == 2
    assert m.versions["mani_skill"] == "3.0.1"
    episodes = list(buf.episodes())
    assert len(episodes) == 2
    for ep in episodes:
        T = ep.shape[0]
        assert ep[IMAGE_KEY].shape == (T, 3, 64, 64) and ep[IMAGE_KEY].dtype == torch.uint8
        assert ep["next", "success"][-1].item() and not ep["next", "success"][:-1].any()  # stops at first success
        assert ep["next", "done"][-1].item() and not ep["next", "done"][:-1].any()
        assert ep[STEP_KEY].squeeze(-1).tolist() == list(range(T))
        assert ep["action"].abs().max() <= 1.0 + 1e-6  # pd_ee_delta_pose actions are normalised
        assert set(ep["action"][:, -1].unique().tolist()) <= {-1.0, 1.0}  # binary gripper
        assert ep[INSTRUCTION_KEY][0] == "pick up the red cube and move it to the green goal"
        # consecutive frames chain: next observation of t is the observation of t+1
        assert torch.equal(ep["next", *IMAGE_KEY][:-1], ep[IMAGE_KEY][1:])
    assert "2 episodes" in buf.summary().replace("episodes      ", "") or "episodes      2" in buf.summary()


def test_stored_demo_replays_to_success_open_loop(demo_dir):
    """The recorded pd_ee_delta_pose actions, replayed from the same seed, solve the task again."""
    from mmada_rl.envs.maniskill import make_gym_env

    buf = DemoBuffer.open(demo_dir)
    ep = next(buf.episodes())
    env = make_gym_env(EnvConfig(task="PickCube-v1", obs_mode="state"))
    try:
        env.reset(seed=int(ep["seed"][0]))
        success = False
        for action in ep["action"].numpy():
            *_, info = env.step(action)
            success = success or bool(info["success"].any())
        assert success
    finally:
        env.close()


@pytest.mark.parametrize("field, value", [("task", "PushCube-v1"), ("control_mode", "pd_joint_delta_pos"), ("image_size", 128), ("obs_mode", "state")])
def test_mismatched_buffer_request_names_both_values(demo_dir, field, value):
    with pytest.raises(BufferMismatchError) as err:
        DemoBuffer.open(demo_dir, **{field: value})
    assert repr(value) in str(err.value) and field in str(err.value)
    assert repr(getattr(BufferMetadata.load(demo_dir), field)) in str(err.value)


def test_not_a_buffer_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="not an mmada_rl buffer"):
        DemoBuffer.open(tmp_path)


def _check_windows(buf, chunk_size, num):
    batch = make_window_buffer(buf, chunk_size=chunk_size, batch_size=num, seed=0).sample()
    assert batch[ACTION_CHUNK_KEY].shape[:2] == (num, chunk_size)
    return _check_windows_of(batch, buf, chunk_size)


def _check_windows_of(batch, buf, chunk_size):
    """Every window of ``batch`` holds its own episode's actions, pad flags and goal frame."""
    K, num = chunk_size, batch.shape[0]
    bounds = dict(enumerate(buf.episode_bounds()))
    storage = buf.storage
    for i in range(num):
        ep = int(batch[EPISODE_KEY][i])
        start, stop = bounds[ep]
        T = stop - start
        t = int(batch[STEP_KEY][i])
        ep_data = storage[start:stop]
        for j in range(K):
            if t + j < T:
                assert not batch[ACTION_IS_PAD_KEY][i, j]
                assert torch.equal(batch[ACTION_CHUNK_KEY][i, j], ep_data["action"][t + j])
            else:  # past the end: flagged, and the last action of the same episode repeated
                assert batch[ACTION_IS_PAD_KEY][i, j]
                assert torch.equal(batch[ACTION_CHUNK_KEY][i, j], ep_data["action"][T - 1])
        if GOAL_IMAGE_KEY in batch.keys(True):
            if t + K < T:
                expected = ep_data[IMAGE_KEY][t + K]
            else:  # o_{t+K} clipped to the episode's final frame
                expected = ep_data["next", *IMAGE_KEY][T - 1]
            assert torch.equal(batch[GOAL_IMAGE_KEY][i], expected)
            assert bool(batch[GOAL_IS_CLIPPED_KEY][i]) == (t + K > T)
        assert torch.equal(batch[IMAGE_KEY][i], ep_data[IMAGE_KEY][t]) if IMAGE_KEY in batch.keys(True) else True
    return batch


def test_window_sampler_never_mixes_episodes_on_real_demos(demo_dir):
    batch = _check_windows(DemoBuffer.open(demo_dir), chunk_size=5, num=300)
    assert batch[ACTION_IS_PAD_KEY].any()  # windows at the episode end are sampled too
    assert batch[INSTRUCTION_KEY][0].startswith("pick up")


def test_instruction_lookup_gives_each_window_its_text():
    """Each element of the stack is its window's text, also where the batch mixes instructions; one
    element per distinct text, already on the batch's device, so setting the stack converts nothing."""
    lookup = InstructionLookup(["pick up the cube", "push the cube"])
    ids = torch.tensor([[1, 0, 1], [0, 0, 1]])
    batch = lookup(TensorDict({"instruction_id": ids}, [2, 3], device="cpu"))
    texts = batch.get(INSTRUCTION_KEY)
    assert isinstance(texts, NonTensorStack) and texts.batch_size == (2, 3)
    assert texts.tolist() == [[lookup.instructions[i] for i in row] for row in ids.tolist()]
    assert texts[0, 1].device == torch.device("cpu")
    assert batch[1:, 2].get(INSTRUCTION_KEY).tolist() == ["push the cube"]
    assert lookup(TensorDict({"instruction_id": torch.tensor(1)}, []))[INSTRUCTION_KEY] == "push the cube"
    single = lookup(TensorDict({"instruction_id": torch.zeros(4, dtype=torch.long)}, [4]))
    assert single[INSTRUCTION_KEY] == ["pick up the cube"] * 4  # a list per window, as any stack


def _offset_of(shifted: torch.Tensor, original: torch.Tensor, pad: int) -> set[tuple[int, int]]:
    """Every (dy, dx) whose border-padded crop of ``original`` [3, H, W] is ``shifted``."""
    H, W = original.shape[-2:]
    padded = torch.nn.functional.pad(original.float()[None], (pad,) * 4, mode="replicate")[0]
    return {(dy, dx) for dy in range(2 * pad + 1) for dx in range(2 * pad + 1)
            if torch.equal(padded[:, dy:dy + H, dx:dx + W].to(original.dtype), shifted)}


def test_random_shift_moves_each_windows_observation_and_goal_by_one_offset(demo_dir):
    buffer = DemoBuffer.open(demo_dir)
    plain, shifted = (make_window_buffer(buffer, chunk_size=5, batch_size=6, seed=3) for _ in range(2))
    shifted.append_transform(RandomShift(3, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY]))
    torch.manual_seed(0)
    a, b = plain.sample(), shifted.sample()  # the same windows (same sampler seed), then shifted
    torch.testing.assert_close(b[ACTION_CHUNK_KEY], a[ACTION_CHUNK_KEY])
    moved = 0
    for i in range(6):
        obs = _offset_of(b[IMAGE_KEY][i], a[IMAGE_KEY][i], 3)
        goal = _offset_of(b[GOAL_IMAGE_KEY][i], a[GOAL_IMAGE_KEY][i], 3)
        assert obs & goal  # one offset explains both images of the window
        moved += (3, 3) not in obs
    assert moved >= 3  # offsets are drawn per window: most windows move


def test_random_shift_refuses_bad_pads_and_images_of_different_shapes():
    for pad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="must be a whole number of pixels >= 0"):
            RandomShift(pad)
    td = TensorDict({IMAGE_KEY: torch.zeros(2, 3, 8, 8, dtype=torch.uint8),
                     GOAL_IMAGE_KEY: torch.zeros(2, 3, 16, 16, dtype=torch.uint8)}, [2])
    with pytest.raises(ValueError, match="shifts images of one shape together"):
        RandomShift(2, image_keys=[IMAGE_KEY, GOAL_IMAGE_KEY])(td)


def _synthetic_buffer(path, lengths):
    meta = BufferMetadata(task="PickCube-v1", control_mode="pd_ee_delta_pose", obs_mode="state", image_size=0, action_dim=2, state_dim=3, source="random")
    buf = DemoBuffer.create(path, meta, capacity=sum(lengths))
    for e, T in enumerate(lengths):
        done = torch.zeros(T, 1, dtype=torch.bool)
        done[-1] = True
        ep = TensorDict(
            {
                "observation": {"state": torch.randn(T, 3)},
                "action": torch.stack([torch.full((T,), float(e)), torch.arange(T, dtype=torch.float32)], -1),
                STEP_KEY: torch.arange(T).unsqueeze(-1),
                "next": {"observation": {"state": torch.randn(T, 3)}, "reward": torch.zeros(T, 1), "done": done,
                         "terminated": done.clone(), "truncated": torch.zeros(T, 1, dtype=torch.bool), "success": done.clone()},
            },
            [T],
        )
        buf.add_episode(ep, seed=e, instruction="pick up the red cube and move it to the green goal")
    return buf


def test_window_sampler_handles_episodes_shorter_than_the_chunk(tmp_path):
    buf = _synthetic_buffer(tmp_path / "syn", [2, 9, 1, 4])
    batch = _check_windows(buf, chunk_size=5, num=500)
    # every step of every episode can start a window (uniform over steps, none dropped)
    starts = {(int(e), int(t)) for e, t in zip(batch[EPISODE_KEY], batch[STEP_KEY].squeeze(-1))}
    assert starts == {(e, t) for e, T in enumerate([2, 9, 1, 4]) for t in range(T)}
    # actions encode (episode, step): a chunk never holds another episode's action
    assert (batch[ACTION_CHUNK_KEY][..., 0] == batch[EPISODE_KEY][:, None].float()).all()


def _leading_run(flags: torch.Tensor) -> int:
    return int(flags.logical_not().nonzero()[0]) if not flags.all() else len(flags)


def test_skip_idle_start_draws_no_window_in_the_planners_leading_hold(push_demos):
    buf = DemoBuffer.open(push_demos)
    ((start, stop),) = buf.episode_bounds()
    hold = _leading_run(idle_actions(buf)[start:stop])
    assert hold >= 5  # ManiSkill's PushCube-v1 planner holds the arm still before it moves
    plain = {int(t) for t in make_window_buffer(buf, 2, 400, seed=0).sample()[STEP_KEY].reshape(-1)}
    assert plain == set(range(stop - start))  # by default every step starts windows, the hold steps too
    batch = make_window_buffer(buf, 2, 400, seed=0, skip_idle_start=True).sample()
    assert {int(t) for t in batch[STEP_KEY].reshape(-1)} == set(range(hold, stop - start))
    assert not (batch[ACTION_CHUNK_KEY][..., :-1].abs() <= 1e-4).all(-1).all(-1).any()  # no hold-only chunk left
    _check_windows_of(batch, buf, chunk_size=2)  # the windows themselves are unchanged


def test_skip_pauses_draws_no_window_at_the_planners_pauses_mid_episode(state_demos):
    buf = DemoBuffer.open(state_demos)
    paused = idle_actions(buf, tol=0.02)
    bounds = buf.episode_bounds()
    # the PickCube-v1 planner nearly stops the arm while it closes the gripper: pauses after it has moved
    mid = [t for a, b in bounds for t in range(_leading_run(paused[a:b]), b - a) if paused[a + t]]
    assert mid
    batch = make_window_buffer(buf, 5, 2000, seed=0, skip_pauses=0.02).sample()
    starts = {(int(e), int(t)) for e, t in zip(batch[EPISODE_KEY], batch[STEP_KEY].reshape(-1))}
    episode = buf.storage[: len(buf)].get(EPISODE_KEY)
    expected = {(int(episode[a]), t) for a, b in bounds for t in range(b - a) if not paused[a + t]}
    assert starts == expected  # every moving step starts windows, no paused one does
    chunks = batch[ACTION_CHUNK_KEY][..., :-1].abs().amax(-1)  # (N, K)
    assert (chunks[:, 0] > 0.02).all() and (chunks[:, 1:] <= 0.02).any()  # pauses still inside windows
    _check_windows_of(batch[:200], buf, chunk_size=5)
    with pytest.raises(ValueError, match="skip_pauses=-0.1 must be >= 0"):
        make_window_buffer(buf, 5, 8, skip_pauses=-0.1)


def test_skip_grasp_hold_draws_no_window_between_the_gripper_close_and_the_lift(state_demos, push_demos):
    buf = DemoBuffer.open(state_demos)
    bounds = buf.episode_bounds()
    actions = buf.storage[: len(buf)].get("action")
    held = grasp_holds(buf, lift=0.05)
    for a, b in bounds:
        steps = held[a:b].nonzero().reshape(-1)
        assert steps.numel() >= 3 and (steps == torch.arange(int(steps[0]), int(steps[-1]) + 1)).all()  # one run
        close, lift = a + int(steps[0]), a + int(steps[-1]) + 1
        assert actions[close - 1, -1] >= 0 > actions[close, -1]  # it starts where the gripper closes
        assert (actions[lift:lift + 3, LIFT_ACTION_DIM] > 0.05).all()  # and ends where the arm rises
        assert not any((actions[t:t + 3, LIFT_ACTION_DIM] > 0.05).all() for t in range(close, lift))  # the first rise
    batch = make_window_buffer(buf, 5, 2000, seed=0, skip_grasp_hold=0.05).sample()
    starts = {(int(e), int(t)) for e, t in zip(batch[EPISODE_KEY], batch[STEP_KEY].reshape(-1))}
    episode = buf.storage[: len(buf)].get(EPISODE_KEY)
    assert starts == {(int(episode[a]), t) for a, b in bounds for t in range(b - a) if not held[a + t]}
    _check_windows_of(batch[:200], buf, chunk_size=5)
    assert not grasp_holds(DemoBuffer.open(push_demos), lift=0.05).any()  # PushCube-v1's gripper never opens
    with pytest.raises(ValueError, match="skip_grasp_hold=-1 must be >= 0"):
        make_window_buffer(buf, 5, 8, skip_grasp_hold=-1)
    buf.metadata.control_mode = "pd_joint_delta_pos"
    with pytest.raises(ValueError, match="end-effector delta action's z entry.*'pd_joint_delta_pos'"):
        make_window_buffer(buf, 5, 8, skip_grasp_hold=0.05)


def test_grasp_hold_gripper_only_draws_the_hold_windows_flagged(state_demos):
    buf = DemoBuffer.open(state_demos)
    held = grasp_holds(buf, lift=0.05)
    episode = buf.storage[: len(buf)].get(EPISODE_KEY)
    hold = {(int(episode[a]), t) for a, b in buf.episode_bounds() for t in range(b - a) if held[a + t]}
    batch = make_window_buffer(buf, 5, 2000, seed=0, skip_grasp_hold=0.05, grasp_hold_gripper_only=True).sample()
    starts = [(int(e), int(t)) for e, t in zip(batch[EPISODE_KEY], batch[STEP_KEY].reshape(-1))]
    assert set(starts) == {(int(episode[a]), t) for a, b in buf.episode_bounds() for t in range(b - a)}  # every step
    assert batch[ACTION_GRIPPER_ONLY_KEY].tolist() == [start in hold for start in starts]  # flagged: those in the hold
    assert batch[ACTION_CHUNK_KEY][batch[ACTION_GRIPPER_ONLY_KEY], 0, -1].lt(0).all()  # the gripper closed there
    _check_windows_of(batch[:200], buf, chunk_size=5)
    assert ACTION_GRIPPER_ONLY_KEY not in make_window_buffer(buf, 5, 12, skip_grasp_hold=0.05).sample().keys(True)
    with pytest.raises(ValueError, match="grasp_hold_gripper_only .* which skip_grasp_hold finds; set skip_grasp_hold > 0"):
        make_window_buffer(buf, 5, 8, grasp_hold_gripper_only=True)


def test_an_episode_that_only_holds_keeps_its_last_step_as_a_start(tmp_path):
    buf = _synthetic_buffer(tmp_path / "syn", [4, 3])  # action[..., 0] is the episode id: episode 0 "holds" throughout
    batch = make_window_buffer(buf, chunk_size=2, batch_size=300, seed=0, skip_idle_start=True).sample()
    starts = {(int(e), int(t)) for e, t in zip(batch[EPISODE_KEY], batch[STEP_KEY].reshape(-1))}
    assert starts == {(0, 3), (1, 0), (1, 1), (1, 2)}


def test_chunk_longer_than_every_episode_is_refused(tmp_path):
    buf = _synthetic_buffer(tmp_path / "syn", [3, 4])
    with pytest.raises(ValueError, match="chunk_size=9 is longer than every episode.*longest: 4"):
        make_window_buffer(buf, chunk_size=9, batch_size=4)


def test_non_finite_actions_are_refused(tmp_path):
    buf = _synthetic_buffer(tmp_path / "syn", [3])
    ep = next(buf.episodes()).exclude(EPISODE_KEY, "instruction_id", "seed", INSTRUCTION_KEY, "index")
    ep["action"][1, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite actions"):
        buf.add_episode(ep, seed=9, instruction="x")


def test_an_instruction_that_is_not_a_string_is_refused(tmp_path):
    # e.g. the NonTensorData an episode's own language_instruction entry holds when indexed
    buf = _synthetic_buffer(tmp_path / "syn", [3])
    episode = next(buf.episodes())
    ep = episode.exclude(EPISODE_KEY, "instruction_id", "seed", INSTRUCTION_KEY, "index")
    with pytest.raises(TypeError, match="instruction must be a string, got NonTensorData"):
        buf.add_episode(ep, seed=9, instruction=episode[0].get(INSTRUCTION_KEY, as_non_tensor=True))
    assert buf.metadata.num_episodes == 1 and len(buf.metadata.instructions) == 1


def test_unknown_task_is_refused_before_any_work(tmp_path):
    with pytest.raises(UnknownTaskError):
        collect(tmp_path / "x", EnvConfig(task="PickBanana-v9"), episodes=1, progress=False)
    assert not (tmp_path / "x").exists()


def test_random_and_torchrl_policy_rollouts_share_the_format(tmp_path):
    cfg = EnvConfig(task="PushCube-v1", max_episode_steps=6)
    res = collect(tmp_path / "random", cfg, episodes=1, policy="random", progress=False)
    ep = next(res.buffer.episodes())
    assert ep.shape == (6,) and ep["next", "truncated"][-1].item()
    zero = TensorDictModule(lambda state: torch.zeros(*state.shape[:-1], 7), in_keys=[("observation", "state")], out_keys=["action"])
    res = collect(tmp_path / "policy", cfg, episodes=1, torchrl_policy=zero, progress=False)
    ep2 = next(res.buffer.episodes())
    assert res.buffer.metadata.source == "policy" and (ep2["action"] == 0).all()
    assert set(ep.keys(True, True)) == set(ep2.keys(True, True))


def test_h5_import_of_a_recording_made_here(tmp_path):
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    from mani_skill.examples.motionplanning.panda.solutions import solvePickCube
    from mani_skill.utils.wrappers.record import RecordEpisode

    env = gym.make("PickCube-v1", obs_mode="none", control_mode="pd_joint_pos", sim_backend="physx_cpu", render_backend="cpu", max_episode_steps=1000)
    env = RecordEpisode(env, output_dir=str(tmp_path / "rec"), trajectory_name="traj", save_video=False, record_reward=False, save_on_reset=False)
    solvePickCube(env, seed=3)
    env.flush_trajectory()
    env.close()
    result = import_h5(tmp_path / "rec" / "traj.h5", tmp_path / "imported", progress=False)
    assert result.imported == 1
    buf = DemoBuffer.open(tmp_path / "imported", task="PickCube-v1", control_mode="pd_ee_delta_pose")
    assert buf.metadata.source == "h5" and buf.metadata.seeds == [3]
    ep = next(buf.episodes())
    assert ep["next", "success"][-1].item() and ep[IMAGE_KEY].shape[1:] == (3, 64, 64)


def _wait_for_episodes(out: Path, n: int, proc, timeout=240):
    deadline = time.time() + timeout
    while time.time() < deadline:
        meta = out / "metadata.json"
        if meta.exists() and json.loads(meta.read_text())["num_episodes"] >= n:
            return
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else "collector exited early"
        time.sleep(0.2)
    raise TimeoutError(f"no {n} episodes in {out}")


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_interrupted_collection_is_loadable_and_resumes(tmp_path, sig):
    out = tmp_path / "demos"
    total = 5  # enough that the signal lands while the collector is still working (a planner episode takes seconds)
    cmd = [sys.executable, "-m", "mmada_rl.cli", "collect", "--task", "PickCube-v1", "--episodes", str(total),
           "--out", str(out), "--obs-mode", "state"]
    # a shell that starts jobs in the background hands them SIGINT ignored, and Python then keeps it
    # ignored; restore the default so Ctrl-C behaves as in a terminal
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_episodes(out, 1, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    if sig == signal.SIGINT:
        assert proc.returncode == 130 and "run the same command again to resume" in err
    buf = DemoBuffer.open(out)
    kept = buf.metadata.num_episodes
    assert 1 <= kept < total and len(buf) == buf.metadata.num_transitions
    first = next(buf.episodes())["action"].clone()
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    buf = DemoBuffer.open(out)
    assert buf.metadata.num_episodes == total
    assert torch.equal(next(buf.episodes())["action"], first)  # resumed, not overwritten
    assert len(set(buf.metadata.seeds)) == total


def test_resuming_past_the_allocated_storage_is_refused_before_collecting(tmp_path):
    cfg = EnvConfig(task="PickCube-v1", obs_mode="state")
    collect(tmp_path / "d", cfg, episodes=1, policy="scripted", progress=False)  # storage for 1 episode
    with pytest.raises(ValueError, match="Collect into a new directory with --episodes 3"):
        collect(tmp_path / "d", cfg, episodes=3, policy="scripted", progress=False)
    meta = DemoBuffer.open(tmp_path / "d").metadata
    assert meta.num_episodes == 1 and meta.attempts == 1  # nothing was attempted
    assert collect(tmp_path / "d", cfg, episodes=1, policy="scripted", progress=False).attempts == 0  # same size: fine


@pytest.mark.parametrize("task", ["PickCube-v1", "PushCube-v1", "PullCube-v1"])
def test_scripted_experts_solve_their_tasks_in_pd_ee_delta_pose(tmp_path, task):
    res = collect(tmp_path / task, EnvConfig(task=task, obs_mode="state"), episodes=2, policy="scripted", progress=False)
    assert res.new_episodes == 2 and res.attempts == 2  # no failed attempt
    ep = next(res.buffer.episodes())
    assert ep["next", "success"][-1].item() and res.buffer.metadata.source == "scripted"


def test_scripted_expert_refuses_other_tasks_and_control_modes(tmp_path):
    with pytest.raises(ValueError, match="no scripted expert for 'StackCube-v1'"):
        collect(tmp_path / "a", EnvConfig(task="StackCube-v1", obs_mode="state"), episodes=1, policy="scripted", progress=False)
    with pytest.raises(ValueError, match="pd_ee_delta_pose"):
        collect(tmp_path / "b", EnvConfig(task="PushCube-v1", obs_mode="state", control_mode="pd_joint_delta_pos"), episodes=1, policy="scripted", progress=False)


def test_keep_after_success_records_the_planner_to_the_end_of_its_path(tmp_path, state_demos):
    """PickCube-v1's planner reaches the goal region still moving; the kept steps slow it down there."""
    cut = next(DemoBuffer.open(state_demos).episodes())  # seed 0, ends at the first success
    res = collect(tmp_path / "full", EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=1,
                  keep_after_success=True, progress=False)
    assert res.buffer.metadata.keep_after_success and res.buffer.metadata.seeds == [0]
    full = next(res.buffer.episodes())
    T = cut[ACTION_KEY].shape[0]
    assert full[ACTION_KEY].shape[0] > T
    torch.testing.assert_close(full[ACTION_KEY][:T], cut[ACTION_KEY])  # the same replay, continued
    assert full["next", "success"][T - 1].item() and full["next", "terminated"][-1].item()
    arm = full[ACTION_KEY][:, :6].abs().amax(-1)
    assert arm[-1] < arm[T - 1]  # still moving at the first success, slower at the end
    with pytest.raises(BufferMismatchError, match="keep_after_success=True"):
        collect(tmp_path / "full", EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=2, progress=False)
    with pytest.raises(ValueError, match="motion planner"):
        collect(tmp_path / "s", EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=1, policy="scripted",
                keep_after_success=True, progress=False)


def test_the_camera_is_recorded_and_a_buffer_of_another_camera_is_refused(tmp_path):
    from mmada_rl.envs.maniskill import make_env
    from mmada_rl.training.demos import open_demos

    narrow = EnvConfig(task="PickCube-v1", camera_fov=45)
    res = collect(tmp_path / "fov45", narrow, episodes=1, progress=False)
    assert res.buffer.metadata.camera_fov == 45 and "camera fov 45 deg" in res.buffer.summary()
    env = make_env(narrow)
    try:  # the stored frames are the narrowed camera's
        first = env.reset(seed=res.buffer.metadata.seeds[0])[IMAGE_KEY]
    finally:
        env.close()
    torch.testing.assert_close(res.buffer.storage[0].get(IMAGE_KEY), first)
    assert open_demos(tmp_path / "fov45", narrow).metadata.num_episodes == 1
    with pytest.raises(BufferMismatchError, match="camera_fov=45.0 but None was asked for"):
        open_demos(tmp_path / "fov45", EnvConfig(task="PickCube-v1"))
    with pytest.raises(BufferMismatchError, match="camera_fov"):  # resuming with the task's own camera
        collect(tmp_path / "fov45", EnvConfig(task="PickCube-v1"), episodes=2, progress=False)


def test_action_noise_executes_noisy_actions_and_records_the_exact_ones(tmp_path):
    """DART: the env moves by the noisy action, the demonstration keeps the expert's label."""
    from mmada_rl.data.recording import StepRecorder
    from mmada_rl.data.sources import NoisyExecution
    from mmada_rl.envs.maniskill import make_gym_env

    def tcp_after_three_still_steps(std):
        rec = StepRecorder(NoisyExecution(make_gym_env(EnvConfig(task="PickCube-v1", obs_mode="state")), std, dims=6))
        rec.reset(seed=3)
        still = np.zeros(7, dtype=np.float32)
        for _ in range(3):
            rec.step(still)
        out = rec.episode()
        rec.close()
        assert torch.equal(out[ACTION_KEY], torch.zeros(3, 7))  # the label, not what was executed
        return out["next", STATE_KEY][-1, 19:22]  # TCP position

    exact, noisy, again = tcp_after_three_still_steps(0.0), tcp_after_three_still_steps(0.1), tcp_after_three_still_steps(0.1)
    assert (noisy - exact).norm() > 1e-3  # the arm moved although every label says "stay"
    torch.testing.assert_close(noisy, again)  # noise reseeded from the episode seed
    res = collect(tmp_path / "dart", EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=1, action_noise=0.05,
                  progress=False)
    assert res.new_episodes == 1 and res.buffer.metadata.action_noise == 0.05
    with pytest.raises(BufferMismatchError, match="action_noise=0.05"):
        collect(tmp_path / "dart", EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=2, progress=False)


@pytest.fixture(scope="module")
def policy_rollouts(toy_pretrain_run, tmp_path_factory) -> Path:
    """Two 12-step episodes of the toy pretrained policy, recorded by ``--policy checkpoint``."""
    out = tmp_path_factory.mktemp("rollouts") / "PickCube-v1"
    res = collect(out, EnvConfig(task="PickCube-v1", max_episode_steps=12), episodes=2, policy="checkpoint",
                  checkpoint=[toy_pretrain_run], seed=70, progress=False)
    assert res.new_episodes == 2 and res.attempts == 2  # failures are kept by default
    return out


def test_checkpoint_rollouts_record_every_executed_action_of_the_greedy_chunks(policy_rollouts, toy_pretrain_run,
                                                                               pick_demos):
    """A trained policy's episodes are stored in the demonstrations' layout, with the policy's own camera and
    provenance; each step is one executed action of its chunks: the first chunk is the greedy chunk the policy
    decodes from the reset observation, and the actions replayed open loop from the episode's seed give its
    stored observations back, step after step."""
    from mmada_rl.envs.maniskill import make_env
    from mmada_rl.evaluation import eval_env_config, load_actor
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    buf = DemoBuffer.open(policy_rollouts)
    meta = buf.metadata
    assert meta.source == "checkpoint" and meta.checkpoint == [str(toy_pretrain_run)] and meta.seeds == [70, 71]
    planner = DemoBuffer.open(pick_demos)
    assert (meta.camera_fov, meta.image_size) == (planner.metadata.camera_fov, planner.metadata.image_size)
    ep, demo = next(buf.episodes()), next(planner.episodes())
    assert set(ep.keys(True, True)) == set(demo.keys(True, True))
    assert ep.shape == (12,) and ep["next", "truncated"][-1].item() and not ep["next", "done"][:-1].any()
    assert ep[STEP_KEY].flatten().tolist() == list(range(12))
    torch.testing.assert_close(ep["next", "observation", "state"][:-1], ep["observation", "state"][1:])

    actor = load_actor(toy_pretrain_run)
    cfg = eval_env_config(actor, "PickCube-v1", max_episode_steps=12)
    env = make_env(cfg)
    try:
        td = env.reset(seed=70)
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            chunk = actor(td.clone())[ACTION_CHUNK_KEY]
        torch.testing.assert_close(ep[ACTION_KEY][: actor.chunk_size], chunk)
        for t in range(ep.shape[0]):
            image_gap = (td["observation", "image"].float() - ep["observation", "image"][t].float()).abs().mean()
            assert image_gap < 0.5, (t, image_gap)
            torch.testing.assert_close(td["observation", "state"], ep["observation", "state"][t], atol=1e-3, rtol=0)
            td = env.step(td.set("action", ep[ACTION_KEY][t]))["next"]
    finally:
        env.close()
    assert "policy        " + str(toy_pretrain_run) in buf.summary()


def test_checkpoint_source_refuses_another_camera_or_a_missing_checkpoint(toy_pretrain_run, tmp_path, capsys):
    from mmada_rl.cli import main

    with pytest.raises(ValueError, match="trained with image_size=64 but 32 was asked for"):
        collect(tmp_path / "a", EnvConfig(task="PickCube-v1", image_size=32), episodes=1, policy="checkpoint",
                checkpoint=[toy_pretrain_run], progress=False)
    with pytest.raises(ValueError, match="trained with camera_fov=None but 45.0 was asked for"):
        collect(tmp_path / "b", EnvConfig(task="PickCube-v1", camera_fov=45), episodes=1, policy="checkpoint",
                checkpoint=[toy_pretrain_run], progress=False)
    assert main(["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", str(tmp_path / "c"),
                 "--policy", "checkpoint"]) == 2
    assert "--checkpoint PATH" in capsys.readouterr().err
    assert main(["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", str(tmp_path / "d"),
                 "--policy", "checkpoint", "--checkpoint", str(tmp_path / "nowhere")]) == 2
    assert "mmada-rl collect: error:" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "d").exists()


def test_merged_buffer_holds_both_parts_episodes_and_their_provenance(pick_demos, policy_rollouts, push_demos,
                                                                      tmp_path, capsys):
    """Planner demonstrations and a policy's rollouts of one task make one buffer that chunk windows are drawn
    from; buffers of another task are refused, naming both."""
    from mmada_rl.cli import main
    from mmada_rl.data import merge_buffers

    assert main(["merge", str(pick_demos), str(policy_rollouts), "--out", str(tmp_path / "both")]) == 0
    assert "part          2 episodes of" in capsys.readouterr().out
    merged, parts = DemoBuffer.open(tmp_path / "both"), [DemoBuffer.open(pick_demos), DemoBuffer.open(policy_rollouts)]
    meta = merged.metadata
    assert meta.source == "planner+checkpoint" and meta.num_episodes == 4
    assert meta.seeds == parts[0].metadata.seeds + parts[1].metadata.seeds
    assert [p["source"] for p in meta.parts] == ["planner", "checkpoint"]
    assert meta.parts[1]["checkpoint"] == parts[1].metadata.checkpoint
    for got, want in zip(merged.episodes(), [e for p in parts for e in p.episodes()]):
        assert torch.equal(got[ACTION_KEY], want[ACTION_KEY])
        assert torch.equal(got["observation", "image"], want["observation", "image"])
    assert merged.episodes().__next__()[INSTRUCTION_KEY][0] == parts[0].metadata.instructions[0]
    batch = make_window_buffer(merged, chunk_size=5, batch_size=8, seed=0).sample()
    assert batch[ACTION_CHUNK_KEY].shape == (8, 5, 7)

    with pytest.raises(BufferMismatchError, match="task='PushCube-v1' but .* has 'PickCube-v1'"):
        merge_buffers(tmp_path / "mixed", [pick_demos, push_demos])
    with pytest.raises(FileExistsError):
        merge_buffers(tmp_path / "both", [pick_demos, policy_rollouts])
    with pytest.raises(ValueError, match="given twice"):
        merge_buffers(tmp_path / "twice", [pick_demos, pick_demos])
    assert main(["merge", str(pick_demos), "--out", str(tmp_path / "one")]) == 2
    assert "two or more buffers" in capsys.readouterr().err


def test_a_teacher_relabels_every_step_with_its_chunk_and_windows_train_on_it(pick_demos, toy_pretrain_run,
                                                                              policy_rollouts, tmp_path, capsys):
    """``mmada-rl relabel`` copies every episode and stores, for each step, the greedy chunk the teacher (here two
    checkpoints as one ensemble) predicts from that step's observation; windows drawn with ``teacher_labels`` take
    that chunk (the demonstrated one without), and the pretraining recipe trains a student on it. A buffer without
    a teacher's labels, another chunk size, relabelling twice and merging relabelled buffers are refused."""
    from mmada_rl.cli import main
    from mmada_rl.data import every_window, merge_buffers, relabel_buffer
    from mmada_rl.data.windows import step_ids
    from mmada_rl.evaluation import resolve_model_dir
    from mmada_rl.keys import EPISODE_KEY, STEP_KEY, TEACHER_CHUNK_KEY
    from mmada_rl.policy import MMaDAEnsemble

    teacher = [toy_pretrain_run / "checkpoints" / "step_00000003", toy_pretrain_run]
    out = tmp_path / "relabelled"
    assert main(["relabel", "--checkpoint", *map(str, teacher), "--demos", str(pick_demos), "--out", str(out),
                 "--batch-size", "16"]) == 0
    assert "teacher       " in capsys.readouterr().out
    source, relabelled = DemoBuffer.open(pick_demos), DemoBuffer.open(out)
    meta = relabelled.metadata
    assert meta.teacher["checkpoints"] == list(map(str, teacher)) and meta.teacher["chunk_size"] == 5
    assert meta.seeds == source.metadata.seeds and len(relabelled) == len(source)
    for got, want in zip(relabelled.episodes(), source.episodes()):  # the demonstrations unchanged
        assert torch.equal(got[ACTION_KEY], want[ACTION_KEY])
        assert torch.equal(got["observation", "image"], want["observation", "image"])
    stored = relabelled.storage[: len(relabelled)]
    labels = stored.get(TEACHER_CHUNK_KEY)
    assert labels.shape == (len(source), 5, 7)

    ensemble = MMaDAEnsemble.load([resolve_model_dir(p) for p in teacher]).eval()
    windows = list(every_window(source, 5, 16))
    assert sum(w.shape[0] for w in windows) == len(source)
    want = torch.cat([ensemble.act(w, greedy=True, decode_goal=False).chunk for w in windows])
    torch.testing.assert_close(labels, want)  # each step's label: the teacher's chunk from its observation
    errors = torch.cat([(c - w[ACTION_CHUNK_KEY]).abs()[~w[ACTION_IS_PAD_KEY]] for c, w in zip(want.split(16), windows)])
    assert meta.teacher["chunk_mae"] == pytest.approx(float(errors.mean(0).mean()), rel=1e-5)
    assert labels.sub(stored.get(ACTION_KEY).unsqueeze(1)).abs().amax() > 0  # not the demonstrated actions

    ids = step_ids(stored.get(EPISODE_KEY).reshape(-1), stored.get(STEP_KEY).reshape(-1))  # sorted: storage order
    for flag in (True, False):
        batch = make_window_buffer(relabelled, 5, 32, seed=0, teacher_labels=flag).sample()
        row = torch.searchsorted(ids, step_ids(batch[EPISODE_KEY].reshape(-1), batch[STEP_KEY].reshape(-1)))
        assert TEACHER_CHUNK_KEY not in batch.keys(include_nested=True)
        if flag:
            assert torch.equal(batch[ACTION_CHUNK_KEY], labels[row])
        else:
            assert torch.equal(batch[ACTION_CHUNK_KEY][:, 0], stored.get(ACTION_KEY)[row])

    with pytest.raises(ValueError, match="mmada-rl relabel --checkpoint TEACHER"):
        make_window_buffer(source, 5, 8, teacher_labels=True)
    with pytest.raises(ValueError, match="chunks of 5 actions, but chunk_size is 4"):
        make_window_buffer(relabelled, 4, 8, teacher_labels=True)
    with pytest.raises(ValueError, match="already relabelled"):
        relabel_buffer(out, teacher, tmp_path / "twice", progress=False)
    with pytest.raises(FileExistsError):
        relabel_buffer(pick_demos, teacher, out, progress=False)
    with pytest.raises(ValueError, match="hold a teacher's labels"):
        merge_buffers(tmp_path / "merged", [out, policy_rollouts])

    student = subprocess.run(
        [sys.executable, "recipes/pretrain/pretrain.py", f"run_dir={tmp_path / 'student'}", f"data.dir={out}",
         "data.collect_episodes=0", "data.teacher_labels=true", "optim.total_steps=2", "eval.episodes=0",
         "num_threads=1"], cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=600)
    assert student.returncode == 0, student.stderr[-3000:]
    assert json.loads((tmp_path / "student" / "checkpoints" / "step_00000002" / "config.json").read_text())["data"]["teacher_labels"]
