"""MMaDAActor and chunk execution on a real ManiSkill env (PickCube-v1, 64x64 RGB)."""
from __future__ import annotations

import warnings
from dataclasses import asdict

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mmada_rl.diffusion.path import DecodingPath, path_log_prob
from mmada_rl.diffusion.sampler import MaskedDiffusionSampler, SamplerConfig
from mmada_rl.data.windows import append_state_differences
from mmada_rl.envs.maniskill import WORKER_SEED_STRIDE, EnvConfig, make_env
from mmada_rl.diffusion.keys import VISUAL_FEATURES_KEY
from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_KEY,
    ACTION_TOKENS_KEY,
    ADVANTAGE_KEY,
    GOAL_IMAGE_KEY,
    GROUP_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    SEQUENCE_KEY,
    STATE_KEY,
)
from mmada_rl.objectives import MaskedDiffusionLoss, PathPPOLoss
from mmada_rl.policy import (
    DECODING_PATH_KEY,
    PREDICTED_GOAL_IMAGE_KEY,
    MMaDAActor,
    MMaDAConfig,
    MMaDAModel,
    TemporalEnsemble,
    Tokenizers,
    make_policy_env,
)
from mmada_rl.tokenizers import (
    TextTokenizer,
    UniformBinActionTokenizer,
    UniformBinActionTokenizerConfig,
    VQActionTokenizer,
    VQActionTokenizerConfig,
    VQImageTokenizer,
    VQImageTokenizerConfig,
    fit_action_tokenizer,
    fit_image_tokenizer,
)

# a tokenizer fitted on seven states clips most new ones: expected here, and warned about
pytestmark = pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.ActionOutOfRangeWarning")
LOG_PROBS_KEY = ("vla_action", "log_probs")
CHUNK = 4  # K of the tiny model
EPISODE_STEPS = 7  # short episodes: a done falls inside the third chunk of k=3


def build_tiny_model(images: torch.Tensor, states: torch.Tensor, actions: torch.Tensor, instruction: str,
                     action_tokens: str = "vq", **config) -> MMaDAModel:
    """A ~0.1M-parameter policy whose tokenizers are fitted for a couple of steps on the given data
    (``action_tokens``: ``"vq"`` codes or 16 uniform ``"bins"`` per dimension; ``config``: MMaDAConfig fields)."""
    image = VQImageTokenizer(VQImageTokenizerConfig(image_size=images.shape[-1], grid_size=8, codebook_size=32, hidden_channels=8, embed_dim=8))
    if action_tokens == "vq":
        action = VQActionTokenizer(VQActionTokenizerConfig(action_dim=actions.shape[-1], codebook_size=16, tokens_per_action=2))
    else:
        action = UniformBinActionTokenizer(UniformBinActionTokenizerConfig(action_dim=actions.shape[-1], num_bins=16))
    proprio = UniformBinActionTokenizer(UniformBinActionTokenizerConfig(action_dim=states.shape[-1], gripper_dims=(), num_bins=16))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # k-means on a handful of vectors warns about duplicates
        fit_image_tokenizer(image, images, steps=2, batch_size=8, progress=False)
        fit_action_tokenizer(action, actions, steps=2, batch_size=8, progress=False)
        fit_action_tokenizer(proprio, states, progress=False)
    config = MMaDAConfig(**{"chunk_size": CHUNK, "denoiser": "tiny", "sampler": {"num_steps": 3}, **config})
    return MMaDAModel(config, Tokenizers(TextTokenizer().fit([instruction]), image, action, proprio)).eval()


@pytest.fixture(scope="module")
def env():
    env = make_env(EnvConfig(task="PickCube-v1", image_size=64, max_episode_steps=EPISODE_STEPS))
    yield env
    env.close()


@pytest.fixture(scope="module")
def observations(env):
    """Seven real observations, batch ``[7]`` (a random-action rollout from a fixed seed)."""
    env.set_seed(0)
    torch.manual_seed(0)
    return env.rollout(EPISODE_STEPS).exclude("next", ACTION_KEY)


@pytest.fixture(scope="module")
def model(observations):
    torch.manual_seed(0)
    return build_tiny_model(
        observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1, observations[INSTRUCTION_KEY][0]
    )


def test_keys_and_shapes_unbatched(model, observations):
    actor = MMaDAActor(model, execute_steps=3)
    assert actor.in_keys == [IMAGE_KEY, STATE_KEY, INSTRUCTION_KEY]
    assert actor.out_keys == [ACTION_CHUNK_KEY, ACTION_TOKENS_KEY, LOG_PROBS_KEY, PREDICTED_GOAL_IMAGE_KEY, DECODING_PATH_KEY, ACTION_KEY]
    td = actor(observations[0].clone())  # one env's output, batch []
    assert td[ACTION_CHUNK_KEY].shape == (CHUNK, 7)
    assert td[ACTION_TOKENS_KEY].shape == (CHUNK, 2)
    assert td[LOG_PROBS_KEY].shape == () and td[LOG_PROBS_KEY] < 0
    assert td[PREDICTED_GOAL_IMAGE_KEY].shape == (3, 64, 64) and td[PREDICTED_GOAL_IMAGE_KEY].dtype == torch.uint8
    assert isinstance(td[DECODING_PATH_KEY], DecodingPath) and td[DECODING_PATH_KEY].batch_size == ()
    torch.testing.assert_close(td[ACTION_KEY], td[ACTION_CHUNK_KEY][:3])


def test_keys_and_shapes_batched(model, observations):
    actor = MMaDAActor(model)
    td = actor(observations[:3].clone())  # a ParallelEnv-like batch [3]
    assert td[ACTION_CHUNK_KEY].shape == (3, CHUNK, 7) and td[ACTION_KEY].shape == (3, CHUNK, 7)
    assert td[LOG_PROBS_KEY].shape == (3,) and td[DECODING_PATH_KEY].batch_size == (3,)
    nested = actor(torch.stack([observations[:3], observations[3:6]]).clone())  # batch [2, 3]
    assert nested[ACTION_TOKENS_KEY].shape == (2, 3, CHUNK, 2)
    assert nested[PREDICTED_GOAL_IMAGE_KEY].shape == (2, 3, 3, 64, 64)
    assert nested[DECODING_PATH_KEY].batch_size == (2, 3)


def test_dropped_proprio_dims_leave_the_sequence(model, observations, tmp_path):
    tokenizers = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.proprio_tokenizer)
    velocities = list(range(9, 18))
    config = MMaDAConfig(chunk_size=CHUNK, denoiser="tiny", sampler={"num_steps": 3}, proprio_drop_dims=velocities)
    lean = MMaDAModel(config, tokenizers).eval()
    assert lean.layout.config.proprio_tokens == model.layout.config.proprio_tokens - 9 == 20
    obs = observations[:2].clone()
    states = observations[STATE_KEY]  # what the proprio tokenizer was fitted on

    def to_the_other_end(dims):  # a value in the upper half of the fitted range goes below it, and vice versa
        value, middle = moved[STATE_KEY][:, dims], (states[:, dims].amax(0) + states[:, dims].amin(0)) / 2
        moved[STATE_KEY][:, dims] = torch.where(value >= middle, value - 10.0, value + 10.0)  # another bin, clipped

    moved = obs.clone()
    to_the_other_end(slice(9, 18))  # what is not read cannot change the prompt
    assert torch.equal(lean.prompt(moved), lean.prompt(obs)) and not torch.equal(model.prompt(moved), model.prompt(obs))
    to_the_other_end(slice(0, 1))
    assert not torch.equal(lean.prompt(moved), lean.prompt(obs))
    assert MMaDAActor(lean)(obs)[ACTION_CHUNK_KEY].shape == (2, CHUNK, 7)
    reloaded = MMaDAModel.load(lean.save(tmp_path / "lean"))
    assert reloaded.config.proprio_drop_dims == velocities and torch.equal(reloaded.prompt(obs), lean.prompt(obs))
    # where state dims sit among the 20 tokens read (0..8, then 18..28): PickCube-v1's goal position is last
    assert lean.proprio_segment_index([26, 27, 28]).tolist() == [17, 18, 19]
    assert model.proprio_segment_index([26, 27, 28]).tolist() == [26, 27, 28]
    with pytest.raises(ValueError, match=r"state dimensions \[9\] are not in the sequence"):
        lean.proprio_segment_index([9, 26])
    with pytest.raises(ValueError, match=r"must name some, not all, of the state's dimensions 0..28"):
        MMaDAModel(MMaDAConfig(denoiser="tiny", proprio_drop_dims=[29]), tokenizers)
    with pytest.raises(ValueError, match="needs use_proprio=True"):
        MMaDAConfig(use_proprio=False, proprio_drop_dims=[9])


def test_state_differences_put_the_goal_relative_to_the_gripper_into_the_sequence(observations, tmp_path):
    """``state_differences``: PickCube-v1's goal minus the TCP position, appended to the state as dims 29..31
    before the proprio tokens are made; each follows its two dimensions and nothing else."""
    pairs = [[26, 19], [27, 20], [28, 21]]
    states = observations[STATE_KEY]
    widened = append_state_differences(states, pairs)
    assert widened.shape[-1] == 32
    torch.testing.assert_close(widened[:, 29:], states[:, 26:29] - states[:, 19:22])
    torch.manual_seed(0)
    relative = build_tiny_model(observations[IMAGE_KEY], widened, torch.rand(64, 7) * 2 - 1,
                                observations[INSTRUCTION_KEY][0], state_differences=pairs)
    assert relative.state_dim == 29 and relative.layout.config.proprio_tokens == 32
    obs = observations[:2].clone()
    tokens = relative._condition(obs)["proprio_ids"]
    assert torch.equal(tokens, relative.proprio_tokenizer.encode(append_state_differences(obs[STATE_KEY], pairs)))
    lifted = obs.clone()
    lifted[STATE_KEY][:, 21] += 0.5 * (widened[:, 31].amax() - widened[:, 31].amin())  # the gripper higher
    moved = relative._condition(lifted)["proprio_ids"]
    changed = (moved != tokens).any(0).nonzero().flatten().tolist()
    assert changed == [21, 31]  # its own token and the goal's height relative to it
    assert relative.proprio_segment_index([29, 30, 31]).tolist() == [29, 30, 31]  # state dropout can keep them
    assert MMaDAActor(relative)(obs)[ACTION_CHUNK_KEY].shape == (2, CHUNK, 7)
    reloaded = MMaDAModel.load(relative.save(tmp_path / "relative"))
    assert reloaded.config.state_differences == pairs and torch.equal(reloaded.prompt(obs), relative.prompt(obs))
    # a proprio tokenizer fitted on the bare 29-dimensional state leaves no room for the differences
    plain = Tokenizers(relative.text_tokenizer, relative.image_tokenizer, relative.action_tokenizer,
                       build_tiny_model(observations[IMAGE_KEY], states, torch.rand(64, 7) * 2 - 1,
                                        observations[INSTRUCTION_KEY][0]).proprio_tokenizer)
    with pytest.raises(ValueError, match=r"covers 29 dimensions, so with 3 differences appended the state has only 26"):
        MMaDAModel(MMaDAConfig(denoiser="tiny", state_differences=pairs), plain)
    for bad in ([[26]], [[26, 26]], [[-1, 3]]):
        with pytest.raises(ValueError, match="must be pairs"):
            MMaDAConfig(state_differences=bad)
    with pytest.raises(ValueError, match="needs use_proprio=True"):
        MMaDAConfig(use_proprio=False, state_differences=pairs)


def test_greedy_is_deterministic_and_random_samples(model, observations):
    actor = MMaDAActor(model)
    batch = observations[:3]
    default = actor(batch.clone())[ACTION_TOKENS_KEY]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = [actor(batch.clone(), generator=torch.Generator().manual_seed(s))[ACTION_TOKENS_KEY] for s in (0, 1)]
    assert torch.equal(greedy[0], greedy[1]) and torch.equal(default, greedy[0])
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = [actor(batch.clone(), generator=torch.Generator().manual_seed(s))[ACTION_TOKENS_KEY] for s in (0, 1, 0)]
    assert not torch.equal(sampled[0], sampled[1])
    assert torch.equal(sampled[0], sampled[2])


def test_mean_readout_executes_the_expected_bins_of_greedy_chunks_only(model, observations, tmp_path):
    """``action_readout="mean"``: a greedy chunk is each dimension's mean under the distribution its token was
    committed from (the tokens are those of the token read-out); a sampled chunk executes its tokens."""
    torch.manual_seed(0)
    bins = build_tiny_model(observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1,
                            observations[INSTRUCTION_KEY][0], action_tokens="bins", action_readout="mean")
    batch = observations[:3]
    mean = bins.act(batch, greedy=True)
    probs = bins.sampler.sample(bins.denoiser, bins.prompt(batch), greedy=True, action_probs=True).action_probs
    torch.testing.assert_close(mean.chunk, bins.action_tokenizer.decode_mean(probs))
    bins.set_action_readout("token")
    token = bins.act(batch, greedy=True)
    assert torch.equal(token.action_tokens, mean.action_tokens)
    assert torch.equal(token.chunk, bins.action_tokenizer.decode(token.action_tokens))
    assert not torch.allclose(token.chunk, mean.chunk)  # an untrained model's distributions are wide
    bins.set_action_readout("mean")
    sampled = bins.act(batch, greedy=False, generator=torch.Generator().manual_seed(0))
    assert torch.equal(sampled.chunk, bins.action_tokenizer.decode(sampled.action_tokens))
    assert MMaDAModel.load(bins.save(tmp_path / "policy")).action_readout == "mean"  # saved as switched last
    with pytest.raises(ValueError, match="action_readout must be one of"):
        MMaDAConfig(action_readout="median")
    with pytest.raises(ValueError, match=r"needs ordered bin tokens \(tokenizers.action_type=bins\), not a VQActionTokenizer"):
        model.set_action_readout("mean")
    assert model.action_readout == "token"


def test_decoding_switches_steps_and_readout_inside_the_block_only(model, observations):
    """``MMaDAModel.decoding``: N and the read-out apply inside the block (a one-step mean read-out is each
    action token's expected bin from the fully masked chunk); the policy's own come back after it, also
    when the block raises, and a bad read-out changes nothing."""
    torch.manual_seed(0)
    bins = build_tiny_model(observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1,
                            observations[INSTRUCTION_KEY][0], action_tokens="bins")
    batch, own = observations[:3], bins.sampler
    assert own.config.num_steps > 1 and bins.action_readout == "token"
    with bins.decoding(num_steps=1, readout="mean"):
        assert bins.sampler.config.num_steps == 1 and bins.action_readout == "mean"
        assert bins.sampler.config.remasking == own.config.remasking  # only what was asked changes
        one_step_mean = bins.act(batch, greedy=True).chunk
    assert bins.sampler is own and bins.action_readout == "token"
    probs = MaskedDiffusionSampler(SamplerConfig(**{**asdict(own.config), "num_steps": 1})).sample(
        bins.denoiser, bins.prompt(batch), greedy=True, action_probs=True).action_probs
    torch.testing.assert_close(one_step_mean, bins.action_tokenizer.decode_mean(probs))
    with pytest.raises(RuntimeError, match="inside"), bins.decoding(num_steps=2):
        raise RuntimeError("inside")
    assert bins.sampler is own
    vq_sampler = model.sampler
    with pytest.raises(ValueError, match="reads each action token's expected bin"), model.decoding(num_steps=1, readout="mean"):
        pass
    assert model.action_readout == "token" and model.sampler is vq_sampler


def test_stored_path_log_prob_is_recomputed_exactly(model, observations):
    actor = MMaDAActor(model)
    with set_exploration_type(ExplorationType.RANDOM):
        td = actor(observations[:3].clone(), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        replayed = path_log_prob(model.denoiser, td[DECODING_PATH_KEY])
        torch.testing.assert_close(replayed, td[LOG_PROBS_KEY], rtol=1e-4, atol=1e-3)
        rescored = actor.log_prob(td.clone(), log_probs_key="rescored")["rescored"]
    torch.testing.assert_close(rescored, td[LOG_PROBS_KEY], rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("keypoints", [None, 4], ids=["cells", "keypoints"])
def test_policy_cross_attends_to_its_own_cnn_features_of_the_image(model, observations, tmp_path, keypoints):
    """``visual_encoder_channels``: the denoiser reads the observation image through a CNN it trains
    (every cell of its last feature map, or with ``visual_keypoints`` one token per spatial-softmax keypoint)."""
    tokenizers = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.proprio_tokenizer)
    overrides = {"cross_attention_to_visual": True, "visual_encoder_channels": [8, 16, 32], "visual_keypoints": keypoints}
    config = MMaDAConfig(chunk_size=CHUNK, denoiser="tiny", sampler={"num_steps": 3}, denoiser_overrides=overrides)
    torch.manual_seed(0)
    seeing = MMaDAModel(config, tokenizers).eval()
    obs = observations[:3].clone()
    # the CNN's features change the logits: a shifted image gives other target logits for the same ids
    ids, level = seeing.prompt(obs), torch.ones(3)
    shifted = obs.clone()
    shifted[IMAGE_KEY] = torch.roll(shifted[IMAGE_KEY], 8, dims=-1)
    logits = [seeing.denoiser(ids, level, visual=seeing.visual_input(o)) for o in (obs, shifted)]
    assert not torch.allclose(logits[0], logits[1])
    actor = MMaDAActor(seeing)
    with set_exploration_type(ExplorationType.RANDOM):
        td = actor(obs, generator=torch.Generator().manual_seed(0))
    assert td[ACTION_CHUNK_KEY].shape == (3, CHUNK, 7)
    with torch.no_grad():  # the stored path is rescored with the same images
        rescored = actor.log_prob(td.clone(), log_probs_key="rescored")["rescored"]
    torch.testing.assert_close(rescored, td[LOG_PROBS_KEY], rtol=1e-4, atol=1e-3)
    ppo = td.clone().set(VISUAL_FEATURES_KEY, obs[IMAGE_KEY]).set(ADVANTAGE_KEY, torch.ones(3))
    assert float(PathPPOLoss(seeing.denoiser)(ppo)["ratio_mean"]) == pytest.approx(1.0, abs=1e-4)
    # the masked-diffusion loss trains the CNN with the denoiser
    windows = obs.clone()
    windows.set(ACTION_CHUNK_KEY, td[ACTION_CHUNK_KEY])
    windows.set(GOAL_IMAGE_KEY, shifted[IMAGE_KEY])
    windows.set(ACTION_IS_PAD_KEY, torch.zeros(3, CHUNK, dtype=torch.bool))
    rows = seeing.loss_inputs(windows)
    assert torch.equal(rows[VISUAL_FEATURES_KEY], obs[IMAGE_KEY])
    losses = MaskedDiffusionLoss(seeing.denoiser)(rows)
    (losses["loss_action"] + losses["loss_goal"]).backward()
    conv = seeing.denoiser.visual_encoder.cnn[0].weight
    assert conv.grad is not None and conv.grad.abs().sum() > 0
    memory = seeing.denoiser._visual_context(obs[IMAGE_KEY], 3)  # what the cross-attention reads
    assert memory.shape == (3, keypoints or (64 // 8) ** 2, seeing.denoiser.config.d_model)
    reloaded = MMaDAModel.load(seeing.save(tmp_path / "seeing")).eval()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(MMaDAActor(reloaded)(obs.clone())[ACTION_TOKENS_KEY], actor(obs.clone())[ACTION_TOKENS_KEY])
    with pytest.raises(ValueError, match="visual_encoder_channels"):
        MMaDAModel(MMaDAConfig(denoiser="tiny", denoiser_overrides={"cross_attention_to_visual": True}), tokenizers)
    with pytest.raises(ValueError, match="needs cross_attention_to_visual"):
        MMaDAConfig(denoiser="tiny", denoiser_overrides={"visual_encoder_channels": [8]})


def test_policy_sees_the_image_only_through_its_cnn(model, observations, tmp_path):
    """``observation_tokens=False``: no observation codes in the sequence; the CNN alone reads the image,
    so the prompt no longer depends on it while the actions still do; saved and reloaded."""
    tokenizers = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.proprio_tokenizer)
    overrides = {"cross_attention_to_visual": True, "visual_encoder_channels": [8, 16, 32]}
    config = MMaDAConfig(chunk_size=CHUNK, denoiser="tiny", sampler={"num_steps": 3}, observation_tokens=False,
                         denoiser_overrides=overrides)
    torch.manual_seed(0)
    cnn_only = MMaDAModel(config, tokenizers).eval()
    assert cnn_only.layout.config.obs_tokens == 0
    assert cnn_only.layout.length == model.layout.length - model.image_tokenizer.tokens_per_image - 1  # codes + tag
    obs = observations[:3].clone()
    shifted = obs.clone()
    shifted[IMAGE_KEY] = torch.roll(shifted[IMAGE_KEY], 8, dims=-1)
    assert torch.equal(cnn_only.prompt(obs), cnn_only.prompt(shifted))
    ids, level = cnn_only.prompt(obs), torch.ones(3)
    logits = [cnn_only.denoiser(ids, level, visual=cnn_only.visual_input(o)) for o in (obs, shifted)]
    assert not torch.allclose(logits[0], logits[1])
    windows = obs.clone()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        tokens = MMaDAActor(cnn_only)(obs.clone())[ACTION_TOKENS_KEY]
        reloaded = MMaDAModel.load(cnn_only.save(tmp_path / "cnn_only")).eval()
        assert reloaded.layout.config.obs_tokens == 0
        torch.testing.assert_close(MMaDAActor(reloaded)(obs.clone())[ACTION_TOKENS_KEY], tokens)
    windows.set(ACTION_CHUNK_KEY, cnn_only.action_tokenizer.decode(tokens))
    windows.set(GOAL_IMAGE_KEY, shifted[IMAGE_KEY])
    windows.set(ACTION_IS_PAD_KEY, torch.zeros(3, CHUNK, dtype=torch.bool))
    rows = cnn_only.loss_inputs(windows)
    assert rows[SEQUENCE_KEY].shape == (3, cnn_only.layout.length)
    losses = MaskedDiffusionLoss(cnn_only.denoiser)(rows)
    assert torch.isfinite(losses["loss_goal"]) and torch.isfinite(losses["loss_action"])
    with pytest.raises(ValueError, match="observation_tokens=false leaves the policy blind"):
        MMaDAConfig(denoiser="tiny", observation_tokens=False)


def test_policy_reads_proprio_bins_as_values(model, observations, tmp_path):
    """``proprio_value_embedding``: the state's tokens also carry their bins' values; saved and reloaded."""
    tokenizers = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.proprio_tokenizer)
    config = MMaDAConfig(chunk_size=CHUNK, denoiser="tiny", sampler={"num_steps": 3},
                         denoiser_overrides={"proprio_value_embedding": True})
    valued = MMaDAModel(config, tokenizers).eval()
    assert valued.denoiser.proprio_value_embedding is not None
    obs = observations[:2].clone()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        tokens = MMaDAActor(valued)(obs.clone())[ACTION_TOKENS_KEY]
        reloaded = MMaDAModel.load(valued.save(tmp_path / "valued")).eval()
        torch.testing.assert_close(MMaDAActor(reloaded)(obs.clone())[ACTION_TOKENS_KEY], tokens)
    vq_proprio = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.action_tokenizer)
    for tokens, use_proprio in ((tokenizers, False), (vq_proprio, True)):  # no proprio tokens; unordered codes
        with pytest.raises(ValueError, match="proprio_value_embedding=true needs proprio tokens that are ordered bins"):
            MMaDAModel(MMaDAConfig(denoiser="tiny", use_proprio=use_proprio,
                                   denoiser_overrides={"proprio_value_embedding": True}), tokens)


def test_policy_embeds_action_bins_by_value(model, observations, tmp_path):
    """``action_value_embedding``: the action bins' embeddings carry their values; saved and reloaded; bins only."""
    valued = build_tiny_model(observations[IMAGE_KEY], observations[STATE_KEY], torch.rand(64, 7) * 2 - 1,
                              observations[INSTRUCTION_KEY][0], action_tokens="bins",
                              denoiser_overrides={"action_value_embedding": True}).eval()
    assert valued.denoiser.action_value_embedding is not None
    obs = observations[:2].clone()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        tokens = MMaDAActor(valued)(obs.clone())[ACTION_TOKENS_KEY]
        reloaded = MMaDAModel.load(valued.save(tmp_path / "valued")).eval()
        assert reloaded.denoiser.action_value_embedding is not None
        torch.testing.assert_close(MMaDAActor(reloaded)(obs.clone())[ACTION_TOKENS_KEY], tokens)
    tokenizers = Tokenizers(model.text_tokenizer, model.image_tokenizer, model.action_tokenizer, model.proprio_tokenizer)
    with pytest.raises(ValueError, match="action_value_embedding=true embeds the value of each action token's bin, so it needs ordered bin tokens"):
        MMaDAModel(MMaDAConfig(denoiser="tiny", denoiser_overrides={"action_value_embedding": True}), tokenizers)


def test_set_keys_moves_our_fields_with_the_root(model):
    actor = MMaDAActor(model).set_keys(vla_action="policy")
    assert ("policy", "goal_image") in actor.out_keys and ("policy", "path") in actor.out_keys


@pytest.mark.parametrize("bad", [0, CHUNK + 1, 2.0])
def test_execute_steps_must_lie_in_one_to_chunk_size(model, bad):
    with pytest.raises(ValueError, match=r"execute_steps must be an int in \[1, chunk_size=4\]"):
        MMaDAActor(model, execute_steps=bad)


def test_chunks_run_k_env_steps_and_stop_at_done(env, model):
    penv = make_policy_env(env, MMaDAActor(model), execute_steps=3, log_keys=["step_count"])
    rollout = penv.env.rollout(10, penv.policy)  # breaks at the first done
    assert rollout[ACTION_KEY].shape == (3, 3, 7)  # three decisions of k=3 actions
    assert rollout["next", "step_count"].squeeze(-1).tolist() == [3, 6, EPISODE_STEPS]  # 7: the done cut chunk 3 short
    assert rollout["next", "done"].squeeze(-1).tolist() == [False, False, True]
    assert [int(s["step_count"]) for s in penv.step_log.steps] == list(range(EPISODE_STEPS + 1))
    with pytest.raises(ValueError, match="temporal_ensemble replans at every step"):
        make_policy_env(env, MMaDAActor(model), execute_steps=2, temporal_ensemble=True)


def test_temporal_ensemble_in_env(env, model):
    penv = make_policy_env(env, MMaDAActor(model), temporal_ensemble=True)
    rollout = penv.env.rollout(EPISODE_STEPS + 2, penv.policy, break_when_any_done=False)
    assert rollout[ACTION_KEY].shape == (EPISODE_STEPS + 2, 1, 7)
    assert rollout["next", "step_count"].squeeze(-1).tolist() == [*range(1, EPISODE_STEPS + 1), 1, 2]  # one step per call


class _CountingChunks(TensorDictModuleBase):
    """Call ``c`` returns the chunk ``[10c, 10c + 1, ...]`` (one action dim)."""

    in_keys, out_keys = [IMAGE_KEY], [ACTION_CHUNK_KEY]

    def __init__(self):
        super().__init__()
        self.calls = 0

    def forward(self, td):
        self.calls += 1
        return td.set(ACTION_CHUNK_KEY, (10.0 * self.calls + torch.arange(3.0)).reshape(3, 1))


def test_temporal_ensemble_weights_the_overlapping_predictions():
    policy = TemporalEnsemble(_CountingChunks(), decay=0.0)

    def step(is_init):
        td = TensorDict({IMAGE_KEY: torch.zeros(1), "is_init": torch.tensor([is_init])}, [])
        return policy(td)[ACTION_KEY].item()

    assert step(True) == 10.0  # only chunk 1, index 0
    assert step(False) == pytest.approx((20 + 11) / 2)  # chunk 2 at 0, chunk 1 at 1
    assert step(False) == pytest.approx((30 + 21 + 12) / 3)
    assert step(False) == pytest.approx((40 + 31 + 22) / 3)  # chunk 1 has run out
    assert step(True) == 50.0  # a reset drops the history
    policy = TemporalEnsemble(_CountingChunks(), decay=1.0)  # ACT: exp(-m i), i = 0 the oldest
    step(True)
    assert step(False) == pytest.approx((11 * 1 + 20 * torch.e**-1) / (1 + torch.e**-1))


@pytest.mark.slow
def test_parallel_env_runs_chunks_across_episode_ends(model):
    # seeded: with unseeded resets, one run under load saw an episode end after its first step
    env = make_env(EnvConfig(task="PickCube-v1", image_size=64, max_episode_steps=EPISODE_STEPS, num_workers=2, train_seed=0))
    try:
        penv = make_policy_env(env, MMaDAActor(model), execute_steps=3)
        rollout = penv.env.rollout(4, penv.policy, break_when_any_done=False)  # the third chunk ends the episodes
        assert rollout["next", "step_count"].squeeze(-1).tolist() == [[3, 6, EPISODE_STEPS, 3]] * 2
        # each worker's own episode seeds, the next one after the reset (what fine-tuning's resume counts)
        assert rollout[GROUP_KEY].squeeze(-1).tolist() == [[0, 0, 0, 1], [WORKER_SEED_STRIDE] * 3 + [WORKER_SEED_STRIDE + 1]]
        assert rollout[LOG_PROBS_KEY].shape == (2, 4) and rollout[ACTION_CHUNK_KEY].shape == (2, 4, CHUNK, 7)
        ensemble = make_policy_env(env, MMaDAActor(model), temporal_ensemble=True)
        rollout = ensemble.env.rollout(EPISODE_STEPS + 1, ensemble.policy, break_when_any_done=False)
        assert rollout[ACTION_KEY].shape == (2, EPISODE_STEPS + 1, 1, 7)
        assert rollout["is_init"].squeeze(-1).tolist() == [[True] + [False] * (EPISODE_STEPS - 1) + [True]] * 2
    finally:
        env.close()
