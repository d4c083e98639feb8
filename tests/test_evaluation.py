"""Evaluation protocol, its outputs and the ``mmada-rl eval`` command."""
from __future__ import annotations

import json

import pytest
import torch

from mmada_rl.cli import main
from mmada_rl.envs.tasks import UnknownTaskError, task_spec
from mmada_rl.evaluation import (EVAL_SEED_BASE, demonstration_seeds, eval_seeds, evaluate, resolve_model_dir,
                                 wilson_interval)
from test_actor import build_tiny_model  # the tiny policy of the actor tests
from script_loader import load_script

pytestmark = pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.ActionOutOfRangeWarning")


def tiny_policy(action_tokens: str = "vq"):
    """A tiny PickCube-v1 policy whose tokenizers are fitted on seeded random data (no env needed)."""
    gen = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (16, 3, 64, 64), dtype=torch.uint8, generator=gen)
    states = torch.randn(64, 29, generator=gen)
    actions = torch.rand(64, 7, generator=gen) * 2 - 1
    return build_tiny_model(images, states, actions, task_spec("PickCube-v1").instruction, action_tokens=action_tokens)


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    """A tiny policy (VQ action codes) saved by ``MMaDAModel.save``."""
    return tiny_policy().save(tmp_path_factory.mktemp("policy") / "model")


def load_benchmark(name: str):
    """A script of ``benchmarks/`` as a module (the scripts are not a package)."""
    return load_script(f"benchmarks/{name}.py")


def test_the_evaluation_env_uses_the_camera_the_policy_was_trained_on(model_dir, tmp_path):
    from mmada_rl.baselines import BCConfig, BCPolicy
    from mmada_rl.evaluation import eval_env_config, load_actor
    from mmada_rl.policy import MMaDAConfig, MMaDAModel

    assert eval_env_config(load_actor(model_dir), "PickCube-v1").camera_fov is None  # the task's own camera
    model = MMaDAModel.load(model_dir)
    model.config.camera_fov = 45.0
    narrow = load_actor(model.save(tmp_path / "narrow"))  # saved and loaded with its camera
    assert eval_env_config(narrow, "PickCube-v1").camera_fov == 45.0
    model.config.camera_fov = {"PickCube-v1": 45.0, "PushCube-v1": 60.0}  # a multi-task model: each task's camera
    per_task = load_actor(model.save(tmp_path / "per_task"))
    assert [eval_env_config(per_task, t).camera_fov for t in ("PickCube-v1", "PushCube-v1")] == [45.0, 60.0]
    with pytest.raises(ValueError, match=r"camera_fov must be a field of view in degrees"):
        MMaDAConfig(denoiser="tiny", camera_fov={"PushCube-v1": 500})
    bc = BCPolicy(BCConfig(camera_fov=30.0))
    assert eval_env_config(bc, "PickCube-v1").camera_fov == 30.0
    state_bc = BCPolicy(BCConfig(camera_fov=30.0, obs_mode="state", state_dim=42))
    assert eval_env_config(state_bc, "PickCube-v1").camera_fov is None  # no camera at all


def test_the_evaluation_env_replays_the_training_demonstrations_observation_for_observation(toy_pretrain_run,
                                                                                            pick_demos):
    """The env ``mmada-rl eval`` builds for a policy shows it what it was trained on: reset with a
    demonstration's seed and stepped with its recorded actions, it gives the stored images and states
    again, step after step, and solves the task (no mismatch between the training windows and evaluation:
    camera, image size, state layout, the contact flag after reset)."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.envs.maniskill import make_env
    from mmada_rl.evaluation import eval_env_config, load_actor

    cfg = eval_env_config(load_actor(toy_pretrain_run), "PickCube-v1")
    ep = next(DemoBuffer.open(pick_demos).episodes())
    env = make_env(cfg)
    try:
        td, success = env.reset(seed=int(ep["seed"][0])), False
        for t in range(ep.shape[0]):
            # the CPU simulation may drift by a hair between two env instances (measured: < 1e-4 in the state)
            image_gap = (td["observation", "image"].float() - ep["observation", "image"][t].float()).abs().mean()
            assert image_gap < 0.5, (t, image_gap)
            torch.testing.assert_close(td["observation", "state"], ep["observation", "state"][t], atol=1e-3, rtol=0)
            td = env.step(td.set("action", ep["action"][t]))["next"]
            success = success or bool(td["success"].any())
        assert success
    finally:
        env.close()


def test_wilson_interval_matches_hand_computation():
    # 7/10, z = 1.96: centre (0.7 + 1.9208/10) / 1.38415 = 0.64449, half-width 0.24770
    low, high = wilson_interval(7, 10)
    assert low == pytest.approx(0.39677, abs=1e-4) and high == pytest.approx(0.89220, abs=1e-4)
    assert wilson_interval(0, 2) == pytest.approx((0.0, 0.65762), abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    assert wilson_interval(0, 50).low == 0.0 and wilson_interval(50, 50).high == 1.0  # exact, not +-1e-17
    with pytest.raises(ValueError, match="successes=3, trials=2"):
        wilson_interval(3, 2)


def test_evaluation_seeds_are_disjoint_from_training_seeds():
    assert eval_seeds(3, seed_offset=5) == [EVAL_SEED_BASE + 5, EVAL_SEED_BASE + 6, EVAL_SEED_BASE + 7]
    with pytest.raises(ValueError, match="seed_offset must be >= 0"):
        eval_seeds(3, seed_offset=-1)


def test_demonstration_seeds_rerun_the_initial_states_of_a_buffer(model_dir, pick_demos, tmp_path):
    from mmada_rl.data.metadata import BufferMetadata

    recorded = BufferMetadata.load(pick_demos).seeds
    assert demonstration_seeds(pick_demos, 2, "PickCube-v1") == recorded[:2] and len(recorded) == 2
    result = evaluate(model_dir, "PickCube-v1", 1, demo_seeds=pick_demos, max_episode_steps=3, num_denoise_steps=1,
                      out_dir=tmp_path, progress=False)
    assert result.seeds == recorded[:1] and [r.seed for r in result.per_episode] == recorded[:1]
    assert result.demo_seeds == str(pick_demos) and f"initial states ({pick_demos})" in result.table()
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["demo_seeds"] == str(pick_demos) and saved["seeds"] == recorded[:1]
    with pytest.raises(ValueError, match="holds 2 demonstrations; ask for at most that many episodes"):
        demonstration_seeds(pick_demos, 3)
    with pytest.raises(ValueError, match="holds PickCube-v1 demonstrations, not PushCube-v1"):
        evaluate(model_dir, "PushCube-v1", 1, demo_seeds=pick_demos)
    with pytest.raises(ValueError, match="seed_offset=4 applies to evaluation seeds"):
        evaluate(model_dir, "PickCube-v1", 1, seed_offset=4, demo_seeds=pick_demos)
    with pytest.raises(FileNotFoundError, match="is not an mmada_rl buffer"):
        demonstration_seeds(tmp_path / "nope", 1)


def test_model_dir_is_found_directly_or_under_model(model_dir, tmp_path):
    assert resolve_model_dir(model_dir) == model_dir
    assert resolve_model_dir(model_dir.parent) == model_dir  # a checkpoint directory holding model/
    with pytest.raises(FileNotFoundError, match="no MMaDA policy"):
        resolve_model_dir(tmp_path)


def test_clear_errors_before_any_env_is_built(model_dir):
    with pytest.raises(ValueError, match=r"image_size=32 .* fitted on 64x64"):
        evaluate(model_dir, "PickCube-v1", 1, image_size=32)
    with pytest.raises(UnknownTaskError, match="NoSuchTask-v9"):
        evaluate(model_dir, "NoSuchTask-v9", 1)


def test_evaluate_two_short_episodes(model_dir, tmp_path):
    result = evaluate(
        model_dir.parent, "PickCube-v1", 2, max_episode_steps=6, execute_steps=2, num_denoise_steps=2,
        out_dir=tmp_path, video=True, goal_grid=True, progress=False,
    )  # fmt: skip
    metrics = result.to_dict()
    for name in ("success_once", "success_at_end"):
        rate, low, high = (metrics[f"eval/{name}{s}"] for s in ("", "_ci_low", "_ci_high"))
        assert 0.0 <= low <= rate <= high <= 1.0
    assert result.seeds == [EVAL_SEED_BASE, EVAL_SEED_BASE + 1]
    assert [r.steps for r in result.per_episode] == [6, 6]  # run to the limit: terminations ignored
    assert [len(r.decode_ms) for r in result.per_episode] == [3, 3]  # 6 steps / k=2
    assert 1 <= result.episode_length <= 6 and result.max_episode_steps == 6
    assert 0 < result.decode_ms_mean <= result.decode_ms_p95 and result.env_steps_per_second > 0
    assert result.num_denoise_steps == 2
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["eval/success_once"] == result.success_once and len(saved["per_episode"]) == 2
    assert saved["checkpoint"] == str(model_dir.parent)  # provenance
    assert "success_once" in (tmp_path / "eval.md").read_text()
    assert set(result.stages) == {"is_grasped", "is_obj_placed"}  # how far each episode got (PickCube-v1's flags)
    for flag, share in result.stages.items():
        assert share == sum(r.stages[flag] for r in result.per_episode) / 2 == metrics[f"eval/reached/{flag}"]
    assert set(saved["per_episode"][0]["stages"]) == {"is_grasped", "is_obj_placed"}
    assert "reached is_grasped" in (tmp_path / "eval.md").read_text()
    # the seeds report pools the episodes that reached each stage
    assert load_script("benchmarks/seeds.py").main(["--group", "two episodes", str(tmp_path / "eval.json"),
                                                    "--name", "stages", "--out", str(tmp_path / "report")]) == 0
    group = json.loads((tmp_path / "report" / "stages.json").read_text())["groups"][0]
    assert {flag: (r["episodes"], r["trials"]) for flag, r in group["reached"].items()} == {
        flag: (sum(e.stages[flag] for e in result.per_episode), 2) for flag in result.stages}
    assert "episodes reaching each stage, pooled" in (tmp_path / "report" / "stages.md").read_text()
    assert (tmp_path / "goal_grid.png").stat().st_size > 0
    assert len(list((tmp_path / "videos").iterdir())) == 2


def test_sampled_evaluation_decodes_with_sampling_at_the_given_temperature(model_dir, monkeypatch):
    from mmada_rl.diffusion.sampler import MaskedDiffusionSampler, is_greedy
    from mmada_rl.policy import MMaDAModel

    calls, decoded, original = [], [], MaskedDiffusionSampler.sample

    def recording(self, *args, greedy=None, **kwargs):
        calls.append((is_greedy(greedy), self.config.temperature))
        out = original(self, *args, greedy=greedy, **kwargs)
        decoded.append(out.target_ids.clone())
        return out

    monkeypatch.setattr(MaskedDiffusionSampler, "sample", recording)
    model = MMaDAModel.load(model_dir)
    own = model.sampler.config.temperature
    greedy = evaluate(model, "PickCube-v1", 1, max_episode_steps=4, progress=False)
    assert calls and all(g and t == own for g, t in calls) and greedy.sample_temperature == 0.0
    calls.clear()
    sampled = evaluate(model, "PickCube-v1", 1, max_episode_steps=4, sample_temperature=2.0, progress=False)
    assert calls and all(not g and t == 2.0 for g, t in calls)
    assert sampled.sample_temperature == 2.0 and "sampled at T=2" in sampled.table()
    # each episode's sampling is seeded by its env seed: the same seeds decode the same tokens, others do not
    runs = []
    for offset in (0, 0, 1):
        decoded.clear()
        torch.manual_seed(123 + len(runs))
        before = torch.random.get_rng_state()
        evaluate(model, "PickCube-v1", 1, seed_offset=offset, max_episode_steps=4, sample_temperature=2.0, progress=False)
        assert torch.equal(torch.random.get_rng_state(), before)  # the caller's RNG is untouched
        runs.append(torch.cat(decoded[1:]))  # after the warm-up decode
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])
    assert model.sampler.config.temperature == own  # the policy's own sampler is restored
    with pytest.raises(ValueError, match="sample_temperature"):
        evaluate(model, "PickCube-v1", 1, sample_temperature=0.0)


def test_noisy_evaluation_executes_the_greedy_chunks_with_seeded_noise(monkeypatch):
    """``action_noise`` evaluates fine-tuning's exploration policy: the greedy chunk with Gaussian noise on the arm's
    actions (the gripper's left alone), the same noise for the same episode seed, and clear errors otherwise."""
    from mmada_rl.policy import ExecutionNoise, MMaDAActor

    greedy_chunks, executed, original_actor, original_noise = [], [], MMaDAActor.forward, ExecutionNoise.forward

    def actor_recording(self, td, *args, **kwargs):
        out = original_actor(self, td, *args, **kwargs)
        greedy_chunks.append(out.get(self.tensor_keys.action_chunk).clone())
        return out

    def noise_recording(self, td, *args, **kwargs):
        out = original_noise(self, td, *args, **kwargs)
        executed.append(out.get("action").clone())
        return out

    monkeypatch.setattr(MMaDAActor, "forward", actor_recording)
    monkeypatch.setattr(ExecutionNoise, "forward", noise_recording)
    model = tiny_policy("bins")  # uniform bins: the noisy chunk re-tokenized keeps its noise (a VQ code would snap back)
    runs = []
    for offset in (0, 0, 1):
        greedy_chunks.clear(), executed.clear()
        result = evaluate(model, "PickCube-v1", 1, seed_offset=offset, max_episode_steps=4, execute_steps=2,
                          action_noise=0.2, progress=False)
        first = greedy_chunks[1][..., :2, :]  # after the warm-up decode: the first decision's greedy actions
        moved = (executed[0] - first).abs()
        assert moved[..., :-1].max() > 0.02 and moved[..., -1].max() < 0.02  # arm perturbed (gripper: re-binned only)
        runs.append(torch.cat(executed))
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])
    assert result.action_noise == 0.2 and "N(0, 0.2^2)" in result.table()
    assert result.to_dict()["eval/action_noise"] == 0.2
    for bad, match in (({"action_noise": 0.0}, "action_noise needs"),
                       ({"action_noise": 0.1, "sample_temperature": 1.0}, "does not combine"),
                       ({"action_noise": 0.1, "temporal_ensemble": True}, "does not combine")):
        with pytest.raises(ValueError, match=match):
            evaluate(model, "PickCube-v1", 1, **bad)


def test_mean_readout_is_switched_for_one_evaluation(model_dir, tmp_path):
    """``evaluate(..., action_readout="mean")`` decodes greedy chunks by their expected bins for that run only,
    says so in its outputs, and refuses policies whose action codes are not ordered bins."""
    from mmada_rl.diffusion.sampler import MaskedDiffusionSampler
    from mmada_rl.policy import MMaDAModel

    model = tiny_policy("bins")
    asked, original = [], MaskedDiffusionSampler.sample

    def recording(self, *args, action_probs=False, **kwargs):
        asked.append(action_probs)
        return original(self, *args, action_probs=action_probs, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(MaskedDiffusionSampler, "sample", recording)
        result = evaluate(model, "PickCube-v1", 1, max_episode_steps=4, action_readout="mean", out_dir=tmp_path,
                          progress=False)
    assert asked and all(asked)  # every chunk read out by its mean
    assert result.action_readout == "mean" and "mean read-out" in result.table()
    assert json.loads((tmp_path / "eval.json").read_text())["action_readout"] == "mean"
    assert model.action_readout == "token"  # the policy's own read-out is restored
    with pytest.raises(ValueError, match="needs ordered bin tokens"):
        evaluate(MMaDAModel.load(model_dir), "PickCube-v1", 1, action_readout="mean")


def test_cli_help_and_missing_checkpoint(run_cli, tmp_path, capsys):
    done = run_cli("eval", "--help", timeout=120)
    assert done.returncode == 0 and "--execute-steps" in done.stdout and "--temporal-ensemble" in done.stdout
    assert "--action-readout {token,mean}" in done.stdout and "--demo-seeds BUFFER" in done.stdout
    assert "--action-noise STD" in done.stdout
    assert main(["eval", "--checkpoint", str(tmp_path / "nope"), "--task", "PickCube-v1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mmada-rl eval: error: no MMaDA policy at") and "\n" not in err


def test_benchmark_figures_are_written_into_new_folders_and_closed(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    common = load_benchmark("common")
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = common.save_figure(fig, tmp_path / "new" / "folder" / "curve.png")
    assert path.read_bytes().startswith(b"\x89PNG") and not plt.fignum_exists(fig.number)


def test_seed_report_pools_runs_and_eval_files_evaluated_alike(toy_pretrain_run, tmp_path):
    bench = load_benchmark("seeds")
    # the toy run logged a 1-episode evaluation at its last step; evaluate it again into an eval.json
    model_dir = toy_pretrain_run / "checkpoints" / "step_00000006" / "model"  # what `mmada-rl eval` records
    evaluate(model_dir, "PickCube-v1", 1, max_episode_steps=10, out_dir=tmp_path / "e1", progress=False)
    sources = [str(toy_pretrain_run), str(tmp_path / "e1" / "eval.json")]
    assert bench.main(["--group", "toy", *sources, "--name", "seeds_toy", "--out", str(tmp_path / "out")]) == 0
    group, = json.loads((tmp_path / "out" / "seeds_toy.json").read_text())["groups"]
    assert group["num_seeds"] == 2 and group["episodes_per_seed"] == 1
    assert [r["seed"] for r in group["seeds"]] == [0, 0]  # read from the run's checkpoint config, both times
    assert group["seeds"][0]["step"] == 6 and group["seeds"][1]["step"] is None
    successes = sum(r["successes"] for r in group["seeds"])
    assert group["pooled"]["successes"] == successes and group["pooled"]["trials"] == 2
    assert group["mean"] == pytest.approx(successes / 2)
    low, high = group["pooled"]["ci"]
    assert 0 <= low <= successes / 2 <= high <= 1
    assert "| toy | 2 | 1 |" in (tmp_path / "out" / "seeds_toy.md").read_text()
    assert (tmp_path / "out" / "seeds_toy.png").stat().st_size > 0
    # evaluations on different numbers of episodes are not pooled
    evaluate(toy_pretrain_run, "PickCube-v1", 2, max_episode_steps=4, out_dir=tmp_path / "e2", progress=False)
    with pytest.raises(ValueError, match="different numbers of episodes"):
        bench.main(["--group", "toy", str(toy_pretrain_run), str(tmp_path / "e2" / "eval.json"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench.main(["--group", "no sources", "--out", str(tmp_path)])
    with pytest.raises(FileNotFoundError, match="neither"):
        bench.main(["--group", "toy", str(tmp_path / "missing"), "--out", str(tmp_path)])
    # RUN@STEP: the evaluation the run logged at that step, and a clear error for a step it did not evaluate at
    assert bench.main(["--group", "at step", f"{toy_pretrain_run}@6", "--name", "at", "--out", str(tmp_path)]) == 0
    row, = json.loads((tmp_path / "at.json").read_text())["groups"][0]["seeds"]
    assert row["step"] == 6 and row["source"] == f"{toy_pretrain_run}@6"
    assert row["success_once"] == group["seeds"][0]["success_once"]
    with pytest.raises(ValueError, match=r"no evaluation at step 3 \(it logged: 6\)"):
        bench.main(["--group", "toy", f"{toy_pretrain_run}@3", "--out", str(tmp_path)])
    # REPORT.json#G/sS: a seed an earlier report recorded, pooled with a new evaluation as if its run were still here
    earlier = tmp_path / "at.json"
    assert bench.main(["--group", "pooled", f"{earlier}#1/s0", str(tmp_path / "e1" / "eval.json"),
                       "--name", "pooled", "--out", str(tmp_path)]) == 0
    pooled, = json.loads((tmp_path / "pooled.json").read_text())["groups"]
    assert pooled["seeds"][0]["source"] == f"{earlier}#1/s0" and pooled["seeds"][0]["step"] == 6
    assert pooled["seeds"][0]["successes"] == row["successes"] and pooled["pooled"]["trials"] == 2
    assert pooled["pooled"]["successes"] == row["successes"] + group["seeds"][1]["successes"]
    with pytest.raises(ValueError, match=r"more than one seed 0"):  # seeds_toy holds seed 0 twice
        bench.main(["--group", "x", f"{tmp_path / 'out' / 'seeds_toy.json'}#1/s0", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match=r"no seed 3 \(its seeds: 0\)"):
        bench.main(["--group", "x", f"{earlier}#1/s3", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match=r"has groups 1 to 1"):
        bench.main(["--group", "x", f"{earlier}#2/s0", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match=r"REPORT.json#G/sS"):
        bench.main(["--group", "x", f"{earlier}#s0", "--out", str(tmp_path)])


def test_push_contact_report_records_where_the_gripper_comes_down(toy_pretrain_run, tmp_path):
    bench = load_benchmark("push_contact")
    # the toy PickCube-v1 policy run in PushCube-v1 (its smaller state is zero-padded): a real rollout, not a good one
    assert bench.main(["--checkpoint", str(toy_pretrain_run), "--episodes", "2", "--max-episode-steps", "10",
                       "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "push_contact.json").read_text())
    assert [e["seed"] for e in result["episodes"]] == eval_seeds(2)
    for e in result["episodes"]:
        assert isinstance(e["success"], bool)
        assert e["down_dx_dy_cm"] is None or len(e["down_dx_dy_cm"]) == 2
    groups = result["groups"]
    assert groups["success"]["episodes"] + groups["failure"]["episodes"] == 2
    assert "median abs(dy) (cm)" in (tmp_path / "push_contact.md").read_text()
    assert (tmp_path / "push_contact.png").stat().st_size > 0


def test_tilt_is_the_angle_between_pointing_axes_whatever_the_turn_about_them():
    tilt = load_benchmark("pick_progress").tilt_deg
    down = torch.tensor([0.0, 1.0, 0.0, 0.0])  # w x y z: the Panda's TCP pointing at the table
    c, s = torch.cos(torch.tensor(0.3)), torch.sin(torch.tensor(0.3))
    turned = torch.tensor([0.0, c, s, 0.0])  # the same, turned 2 * 0.3 rad about the pointing axis
    tilted = torch.tensor([c * 0, c, 0.0, s])  # 2 * 0.3 rad about a horizontal axis
    assert float(tilt(down, down)) == 0.0 and float(tilt(down, turned)) < 1e-3
    torch.testing.assert_close(tilt(down, tilted), torch.rad2deg(torch.tensor(0.6)), rtol=1e-4, atol=1e-3)


def test_pick_progress_sorts_each_failure_into_one_mode():
    mode = load_benchmark("pick_progress").failure_mode

    def episode(success=False, grasped_at=1, lost=0, distance=(20.0, 20.0, 20.0)):
        after = distance[grasped_at:] if grasped_at is not None else ()
        return {"success": success, "grasped_at_decision": grasped_at, "grasp_lost": lost,
                "closest_cm": min(after) if after else None, "distance_cm": list(distance)}

    assert mode(episode(success=True, distance=(20.0, 10.0, 2.0))) is None
    assert mode(episode(grasped_at=None)) == "never grasped"
    assert mode(episode(lost=1, distance=(20.0, 20.0, 4.0))) == "dropped"  # a lost grasp, however near it came
    assert mode(episode(distance=(20.0, 20.0, 18.5))) == "stalled"  # 1.5 cm nearer than at the grasp: under 2
    assert mode(episode(distance=(20.0, 20.0, 4.0))) == "near miss"
    assert mode(episode(distance=(20.0, 20.0, 9.0))) == "short"


def test_pick_progress_tells_a_released_grasp_from_a_slipped_one():
    released = load_benchmark("pick_progress").released
    close, open_ = torch.tensor([[0.0] * 6 + [-1.0]] * 5), torch.tensor([[0.0] * 6 + [-1.0]] * 4 + [[0.0] * 6 + [1.0]])
    # held at decisions 1 and 2, lost at 3: the chunk executed at 2 opened the gripper on the held cube
    assert released([False, True, True, False], [open_, close, open_, close])  # an open before the grasp does not count
    assert not released([False, True, True, False], [open_, close, close, open_])  # lost with the fingers closed
    assert not released([False, True, False, True], [close, close, close, open_])  # opened only after the first loss
    assert not released([False, False, False], [open_, open_, open_])  # never held


def test_pick_progress_report_follows_the_cube_to_the_goal(toy_pretrain_run, pick_demos, tmp_path):
    bench = load_benchmark("pick_progress")
    assert bench.main(["--checkpoint", str(toy_pretrain_run), "--episodes", "2", "--max-episode-steps", "10",
                       "--out", str(tmp_path), "--demo-tilt", str(pick_demos)]) == 0
    result = json.loads((tmp_path / "pick_progress.json").read_text())
    # the planner keeps the gripper pointing down: its demonstrations tilt it by a few degrees at most
    assert result["demo_tilt"]["episodes"] == 2 and 0 <= result["demo_tilt"]["max_tilt_deg"] < 15
    assert all(0 <= e["max_tilt_deg"] <= 180 for e in result["episodes"])
    assert "median max tilt" in (tmp_path / "pick_progress.md").read_text()
    assert [e["seed"] for e in result["episodes"]] == eval_seeds(2)
    for e in result["episodes"]:
        assert 1 <= len(e["distance_cm"]) <= 3  # 10 steps at k = 5: two decisions (one more probe at most)
        assert e["final_cm"] == e["distance_cm"][-1] and 0 < e["final_cm"] < 100
        assert (e["closest_cm"] is None) == (e["grasped_at_decision"] is None)  # distances after a grasp only
    assert result["summary"]["episodes"] == 2 and result["summary"]["grasped"] <= 2
    failures = result["summary"]["failures"]
    assert sum(failures.values()) == 2 - result["summary"]["successes"]
    assert failures["never grasped"] == 2 - result["summary"]["grasped"]
    assert all(e["failure_mode"] == bench.failure_mode(e) for e in result["episodes"])
    assert "median max height above goal (cm)" in (tmp_path / "pick_progress.md").read_text()
    assert ("| never grasped | dropped | stalled | near miss | short | of the drops, released by the policy |"
            in (tmp_path / "pick_progress.md").read_text())
    assert result["summary"]["dropped_released"] == sum(e["released"] for e in result["episodes"]) <= failures["dropped"]
    assert (tmp_path / "pick_progress.png").stat().st_size > 0
    assert result["action_readout"] is None  # the policy's own
    with pytest.raises(ValueError, match="needs ordered bin tokens"):  # the toy policy's actions are VQ codes
        bench.main(["--checkpoint", str(toy_pretrain_run), "--episodes", "1", "--action-readout", "mean"])
    # the same probe on the demonstrations' own initial states
    assert bench.main(["--checkpoint", str(toy_pretrain_run), "--episodes", "1", "--max-episode-steps", "5",
                       "--out", str(tmp_path), "--demo-seeds", str(pick_demos), "--name", "on_demos"]) == 0
    on_demos = json.loads((tmp_path / "on_demos.json").read_text())
    assert [e["seed"] for e in on_demos["episodes"]] == demonstration_seeds(pick_demos, 1)
    assert on_demos["demo_seeds"] == str(pick_demos) and "initial states of the first 1 demonstrations" in (
        tmp_path / "on_demos.md").read_text()
    with pytest.raises(SystemExit, match="holds 2 demonstrations"):
        bench.main(["--checkpoint", str(toy_pretrain_run), "--episodes", "3", "--demo-seeds", str(pick_demos)])


def test_goal_sensitivity_measures_how_the_first_action_follows_the_goal(toy_pretrain_run, pick_demos, state_demos,
                                                                        tmp_path):
    from mmada_rl.keys import ACTION_CHUNK_KEY, STATE_KEY

    bench = load_benchmark("goal_sensitivity")
    episodes = bench.grasped_observations(pick_demos, 2)
    assert all(bool((e.get(STATE_KEY)[:, bench.IS_GRASPED] > 0.5).all()) for e in episodes)

    def controller(gain):  # a policy moving by gain * (goal - TCP), in metres: gain / 100 per cm of goal shift
        def act(td):
            state = td.get(STATE_KEY)
            step = gain * (state[:, bench.GOAL_POSITION] - state[:, 19:22])
            return td.set(ACTION_CHUNK_KEY, torch.cat([step, torch.zeros(len(td), 4)], -1)[:, None].expand(-1, 5, -1))
        return act

    follows = bench.sensitivity(controller(3.0), episodes, shift_cm=2.0)
    blind = bench.sensitivity(controller(0.0), episodes, shift_cm=2.0)
    assert follows["states"] == blind["states"] == sum(len(e) for e in episodes) > 0
    for axis in bench.AXES:
        assert follows["axes"][axis]["mean_per_cm"] == pytest.approx(0.03, abs=1e-4)
        assert follows["axes"][axis]["positive"] == 1.0 and blind["axes"][axis]["unmoved"] == 1.0
    # end to end on a real (tiny) policy: results files, one row per checkpoint
    assert bench.main(["--checkpoint", str(toy_pretrain_run), "--demos", str(pick_demos), "--episodes", "1",
                       "--action-readout", "token", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "goal_sensitivity.json").read_text())
    assert result["action_readout"] == "token" and "(token read-out)" in (tmp_path / "goal_sensitivity.md").read_text()
    axes = result["results"][str(toy_pretrain_run)]["axes"]
    assert set(axes) == {"x", "y", "z"} and all(0 <= a["positive"] <= 1 for a in axes.values())
    assert f"`{toy_pretrain_run}`" in (tmp_path / "goal_sensitivity.md").read_text()
    assert (tmp_path / "goal_sensitivity.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="RGB observations"):
        bench.main(["--checkpoint", str(toy_pretrain_run), "--demos", str(state_demos), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="holds only 2 demonstrations"):
        bench.main(["--checkpoint", str(toy_pretrain_run), "--demos", str(pick_demos), "--episodes", "3"])


def test_train_throughput_benchmark_times_each_configuration_on_the_same_windows(toy_pretrain_run, pick_demos,
                                                                                  tmp_path):
    bench = load_benchmark("train_throughput")
    tokenizers = toy_pretrain_run / "tokenizers"
    variants = [f'with codes={tokenizers}={{"denoiser": "tiny"}}',
                f'cnn only={tokenizers}={{"denoiser": "tiny", "observation_tokens": false, "predict_goal": false}}']
    assert bench.main(["--demos", str(pick_demos), *(a for v in variants for a in ("--variant", v)), "--bc",
                       "--batch-size", "2", "--repeats", "2", "--warmup", "0", "--precisions", "fp32", "bf16",
                       "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "train_throughput.json").read_text())
    first, first_bf16, second, second_bf16, bc = result["variants"]
    assert [first["name"], second["name"], bc["name"]] == ["with codes", "cnn only", "BC baseline"]
    assert [v["precision"] for v in result["variants"]] == ["fp32", "bf16", "fp32", "bf16", "fp32"]  # each variant at both
    assert first_bf16["name"] == "with codes" and second_bf16["sequence_length"] == second["sequence_length"]
    # without the observation codes and the goal image the sequence is shorter by both
    assert second["sequence_length"] < first["sequence_length"] and bc["sequence_length"] is None
    assert first["fields"]["denoiser_overrides"]["visual_encoder_channels"] == [32, 64, 128]  # the base's CNN kept
    for v in result["variants"]:
        assert len(v["step_s"]) == 2 and all(t > 0 for t in v["step_s"]) and v["windows_per_s"] > 0
    assert first["step_time_vs_first"] == 1.0
    markdown = (tmp_path / "train_throughput.md").read_text()
    assert "| cnn only | cpu | bf16 |" in markdown and "| BC baseline |" in markdown and "Reproduce:" in markdown
    assert (tmp_path / "train_throughput.png").stat().st_size > 0
    with pytest.raises(SystemExit):  # no fitted tokenizers there
        bench.main(["--demos", str(pick_demos), "--variant", f"x={tmp_path}={{}}", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):  # fields that are not a JSON object
        bench.main(["--demos", str(pick_demos), "--variant", f"x={tokenizers}=[1]", "--out", str(tmp_path)])


def test_decode_cache_benchmark_times_the_three_variants(toy_pretrain_run, tmp_path):
    bench = load_benchmark("decode_cache")
    assert bench.main(["--layout-from", str(toy_pretrain_run), "--preset", "tiny", "--batch", "2", "--steps", "1", "3",
                       "--repeats", "1", "--replay-paths", "2", "--replay-steps", "2", "--train-batch", "2",
                       "--corruptions", "1", "2", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "decode_cache.json").read_text())
    assert result["conditioning"] + result["targets"] == result["length"]
    assert [(r["batch"], r["num_steps"]) for r in result["decode"]] == [(2, 1), (2, 3)]
    for r in result["decode"]:
        assert all(r[f"{name} ms"] > 0 for name in ("bidirectional", "block-causal", "block-causal + cache"))
    assert result["replay"]["replayed_steps"] == 2 and result["replay"]["block-causal + cache ms"] > 0
    assert [(r["windows"], r["corruptions"]) for r in result["training"]] == [(2, 1), (2, 2)]
    assert all(r["block-causal + cache ms"] > 0 and r["cache / bidirectional"] > 0 for r in result["training"])
    markdown = (tmp_path / "decode_cache.md").read_text()
    assert "| 2 | 3 |" in markdown and "Pretraining loss" in markdown and "cost vs C = 1" in markdown
    assert (tmp_path / "decode_cache.png").stat().st_size > 0
    with pytest.raises(SystemExit):
        bench.main(["--layout-from", str(toy_pretrain_run), "--replay-steps", "20", "--out", str(tmp_path)])
