"""``MMaDAEnsemble`` and ``ChunkPolicyEnsemble``: several policies' chunks averaged, evaluated as one policy."""
from __future__ import annotations

import json

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mmada_rl.baselines import ChunkPolicyEnsemble, make_policy
from mmada_rl.cli import main
from mmada_rl.evaluation import evaluate
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, ACTION_TOKENS_KEY, IMAGE_KEY, INSTRUCTION_KEY, STATE_KEY
from mmada_rl.policy import MMaDAActor, MMaDAEnsemble, PolicyOutput
from script_loader import load_script
from test_actor import CHUNK, LOG_PROBS_KEY, build_tiny_model, env, observations  # noqa: F401 (fixtures)
from test_baselines import K, STATS, TINY, TINY_HEADS, tiny_policy, window_batch

pytestmark = pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.ActionOutOfRangeWarning")
GRIPPER = 6  # PickCube-v1's pd_ee_delta_pose: 6 arm dimensions, then the gripper


def tiny_members(observations, count: int = 3, **config) -> list:
    """``count`` tiny bin-token policies on the same observations, each initialised from its own seed."""
    members = []
    for seed in range(count):
        torch.manual_seed(seed)
        members.append(build_tiny_model(observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1,
                                        observations[INSTRUCTION_KEY][0], action_tokens="bins", **config))
    return members


def test_the_ensemble_executes_the_members_mean_chunk_with_grippers_by_majority(observations):
    members = tiny_members(observations, action_readout="mean")
    batch = observations[:4]
    chunks = torch.stack([MMaDAActor(m)(batch.clone())[ACTION_CHUNK_KEY] for m in members])  # (3, 4, K, 7)
    out = MMaDAActor(MMaDAEnsemble(members), execute_steps=2)(batch.clone())
    chunk = out[ACTION_CHUNK_KEY]
    assert chunk.shape == (4, CHUNK, 7)
    torch.testing.assert_close(chunk[..., :GRIPPER], chunks[..., :GRIPPER].mean(0))
    assert set(chunks[..., GRIPPER].unique().tolist()) <= {-1.0, 1.0}  # each member's gripper is open or closed
    assert torch.equal(chunk[..., GRIPPER], chunks[..., GRIPPER].sum(0).sign())  # three votes: never a tie
    assert not torch.equal(chunks[0], chunks[1])  # the members do disagree, so the average is not one of them
    torch.testing.assert_close(out[ACTION_KEY], chunk[:, :2])
    assert torch.equal(out[ACTION_TOKENS_KEY], members[0].action_tokenizer.encode(chunk))  # the executed chunk's codes
    assert torch.isnan(out[LOG_PROBS_KEY]).all()  # no decoding path produced an average


def test_a_gripper_tie_takes_the_first_members_gripper(observations, monkeypatch):
    members = tiny_members(observations, count=2)
    arm = torch.tensor([[0.2, -0.4, 0.0, 0.1, 0.0, 0.3], [0.4, 0.0, 0.2, -0.1, 0.0, 0.1]])  # member 0, member 1

    def fixed(index: int, grippers: list[float]):
        def act(td, *, greedy=None, generator=None, decode_goal=True):
            chunk = torch.cat([arm[index].expand(CHUNK, 6), torch.tensor(grippers)[:, None]], -1)[None]  # (1, K, 7)
            real = type(members[index]).act(members[index], td, greedy=greedy, decode_goal=decode_goal)
            return real._replace(chunk=chunk)
        return act

    monkeypatch.setattr(members[0], "act", fixed(0, [1.0, 1.0, -1.0, -1.0, 1.0][:CHUNK]))
    monkeypatch.setattr(members[1], "act", fixed(1, [1.0, -1.0, 1.0, -1.0, -1.0][:CHUNK]))
    output = MMaDAEnsemble(members).act(observations[:1], greedy=True)
    assert isinstance(output, PolicyOutput)
    torch.testing.assert_close(output.chunk[0, :, :GRIPPER], arm.mean(0).expand(CHUNK, 6))
    assert output.chunk[0, :, GRIPPER].tolist() == [1.0, 1.0, -1.0, -1.0, 1.0][:CHUNK]  # agreed, or member 0's


def test_decoding_settings_reach_every_member_and_only_greedy_decoding_runs(observations):
    members = tiny_members(observations, count=2)
    ensemble = MMaDAEnsemble(members)
    own = [m.sampler for m in members]
    with ensemble.decoding(num_steps=1, readout="mean"):
        assert all(m.sampler.config.num_steps == 1 and m.action_readout == "mean" for m in members)
        assert ensemble.action_readout == "mean"
    assert [m.sampler for m in members] == own and ensemble.action_readout == "token"
    actor = MMaDAActor(ensemble)
    with set_exploration_type(ExplorationType.RANDOM), pytest.raises(ValueError, match="decodes greedily only"):
        actor(observations[:2].clone())
    with pytest.raises(ValueError, match="greedily only"):
        evaluate(ensemble, "PickCube-v1", 1, sample_temperature=1.0, progress=False)
    with pytest.raises(NotImplementedError, match="no decoding-path likelihood"):
        actor.log_prob(actor(observations[:2].clone()))


def test_members_must_act_alike(observations):
    members = tiny_members(observations, count=2)
    with pytest.raises(ValueError, match="two or more"):
        MMaDAEnsemble(members[:1])
    torch.manual_seed(0)
    shorter = build_tiny_model(observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1,
                               observations[INSTRUCTION_KEY][0], action_tokens="bins", chunk_size=CHUNK - 1)
    with pytest.raises(ValueError, match=f"member 0 has chunk size {CHUNK}, member 1 {CHUNK - 1}"):
        MMaDAEnsemble([members[0], shorter])


def test_mmada_rl_eval_runs_several_checkpoints_as_one_ensemble(observations, tmp_path, capsys):
    dirs = [m.save(tmp_path / f"seed{i}" / "model") for i, m in enumerate(tiny_members(observations, count=2))]
    code = main(["eval", "--checkpoint", str(dirs[0].parent), str(dirs[1].parent), "--task", "PickCube-v1",
                 "--episodes", "1", "--max-episode-steps", "4", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    saved = json.loads((dirs[0].parent / "eval_ensemble" / "eval.json").read_text())  # not the member's own eval/
    assert saved["checkpoint"] == f"{dirs[0]} + {dirs[1]}" and saved["eval/episodes"] == 1
    assert saved["per_episode"][0]["steps"] == 4
    for seed, directory in enumerate(dirs):  # what a training checkpoint keeps beside its model/
        (directory.parent / "config.json").write_text(json.dumps({"seed": seed}))
    seeds = load_script("benchmarks/seeds.py")
    assert seeds.main(["--group", "ensemble", str(dirs[0].parent / "eval_ensemble" / "eval.json"),
                       "--name", "ensemble", "--out", str(tmp_path / "report")]) == 0
    assert "s0+1: " in (tmp_path / "report" / "ensemble.md").read_text()  # the members' seeds label the row
    assert main(["eval", "--checkpoint", str(dirs[0].parent), str(tmp_path / "nope"), "--task", "PickCube-v1"]) == 2
    assert "no MMaDA policy at" in capsys.readouterr().err


# -- the imitation baselines' ensemble ------------------------------------------------
def test_a_baseline_ensemble_executes_its_members_mean_chunk():
    members = [tiny_policy("bc", seed=0), tiny_policy("bc", seed=1), tiny_policy("diffusion_policy", seed=2)]
    batch = window_batch(batch=4).select(IMAGE_KEY, STATE_KEY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        chunks = torch.stack([m(batch.clone())[ACTION_CHUNK_KEY] for m in members])  # (3, 4, K, 7)
        ensemble = ChunkPolicyEnsemble(members, execute_steps=2)
        out = ensemble(batch.clone())
        by_majority = ChunkPolicyEnsemble(members, gripper_dims=[GRIPPER])(batch.clone())[ACTION_CHUNK_KEY]
    chunk = out[ACTION_CHUNK_KEY]
    assert chunk.shape == (4, K, 7) and out[ACTION_KEY].shape == (4, 2, 7)
    torch.testing.assert_close(chunk, chunks.mean(0))  # a regressed gripper is averaged like the arm
    assert not torch.equal(chunks[0], chunks[1])  # the members disagree: the average is none of them
    torch.testing.assert_close(out[ACTION_KEY], chunk[:, :2])
    torch.testing.assert_close(by_majority[..., :GRIPPER], chunk[..., :GRIPPER])
    assert torch.equal(by_majority[..., GRIPPER], chunks[..., GRIPPER].sign().sum(0).sign())  # three votes: no tie
    assert ensemble.num_denoise_steps == 1 + 1 + members[2].num_denoise_steps  # network evaluations per chunk
    assert ensemble.last_decode_seconds > 0
    unbatched = ensemble(batch[0].clone())  # one env's observation
    assert unbatched[ACTION_CHUNK_KEY].shape == (K, 7)


def test_a_baseline_ensemble_refuses_unlike_members_and_has_nothing_to_save(tmp_path):
    members = [tiny_policy("bc", seed=0), tiny_policy("bc", seed=1)]
    with pytest.raises(ValueError, match="two or more ChunkPolicy"):
        ChunkPolicyEnsemble(members[:1])
    torch.manual_seed(0)
    longer = make_policy("bc", {**TINY, **TINY_HEADS["bc"], "chunk_size": K + 1}, STATS)
    with pytest.raises(ValueError, match=f"member 0 has chunk size {K}, member 1 {K + 1}"):
        ChunkPolicyEnsemble([members[0], longer])
    with pytest.raises(ValueError, match="outside"):
        ChunkPolicyEnsemble(members, gripper_dims=(7,))
    ensemble = ChunkPolicyEnsemble(members)
    with pytest.raises(ValueError, match="single policies"):
        ChunkPolicyEnsemble([ensemble, members[0]])
    with pytest.raises(ValueError, match="keep their own num_denoise_steps"):
        ensemble.get_new_version(num_denoise_steps=2)
    assert ensemble.get_new_version(execute_steps=1).execute_steps == 1
    with pytest.raises(NotImplementedError, match="no weights of its own"):
        ensemble.save(tmp_path / "ensemble")


def test_mmada_rl_eval_runs_several_baselines_as_one_ensemble(observations, tmp_path, capsys):
    dirs = [tiny_policy("bc", seed=s).save(tmp_path / f"bc{s}") for s in range(2)]
    code = main(["eval", "--checkpoint", *map(str, dirs), "--task", "PickCube-v1", "--episodes", "1",
                 "--max-episode-steps", "3", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    saved = json.loads((dirs[0] / "eval_ensemble" / "eval.json").read_text())
    assert saved["checkpoint"] == f"{dirs[0]} + {dirs[1]}" and saved["per_episode"][0]["steps"] == 3
    mmada = tiny_members(observations, count=1)[0].save(tmp_path / "mmada" / "model")
    assert main(["eval", "--checkpoint", str(dirs[0]), str(mmada), "--task", "PickCube-v1"]) == 2
    assert "all MMaDA-VLA policies or all imitation baselines" in capsys.readouterr().err


def test_a_view_ensemble_decodes_each_shifted_view_and_averages_them(observations):
    views = load_script("benchmarks/view_ensemble.py")
    model = tiny_members(observations, count=1, action_readout="mean")[0]
    batch = observations[:3]
    alone = MMaDAActor(model)(batch.clone())[ACTION_CHUNK_KEY]
    same = MMaDAActor(views.view_ensemble([model, model], [(0, 0), (0, 0)]))(batch.clone())[ACTION_CHUNK_KEY]
    torch.testing.assert_close(same, alone)  # two unshifted views: the policy's own chunk
    # a view shifted 2 px down: the image padded by repeating its edge rows, cropped 2 rows higher
    image = batch[IMAGE_KEY]
    down = torch.cat([image[..., :1, :].expand(*image.shape[:-2], 2, image.shape[-1]), image[..., :-2, :]], dim=-2)
    shifted_batch = batch.clone()
    shifted_batch.set(IMAGE_KEY, down)
    shifted = MMaDAActor(model)(shifted_batch)[ACTION_CHUNK_KEY]
    assert not torch.equal(shifted, alone)  # the policy reads the image: the view changes its chunk
    both = MMaDAActor(views.view_ensemble([model, model], [(0, 0), (-2, 0)]))(batch.clone())[ACTION_CHUNK_KEY]
    torch.testing.assert_close(both[..., :GRIPPER], (alone[..., :GRIPPER] + shifted[..., :GRIPPER]) / 2)


def test_the_state_dropped_view_masks_what_state_dropout_masked_and_leaves_the_policy_alone(observations):
    views = load_script("benchmarks/view_ensemble.py")
    model = tiny_members(observations, count=1)[0]
    batch = observations[:2]
    prompt = model.prompt(batch)
    proprio = model.layout.positions("proprio")
    keep = [0, 1]  # the first two state dimensions stay readable
    dropped = views.state_dropped(model, keep).prompt(batch)
    mask = model.layout.vocab.mask_id
    masked = (dropped != prompt).any(0)
    assert masked.nonzero().flatten().tolist() == proprio[2:].tolist()  # one token per state dimension here
    assert (dropped[:, proprio[2:]] == mask).all()
    torch.testing.assert_close(model.prompt(batch), prompt)  # the policy's own prompt is untouched
    every = views.state_dropped(model, []).prompt(batch)
    assert (every[:, proprio] == mask).all()
