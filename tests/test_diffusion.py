"""Forward process, denoiser, masked-diffusion loss and parallel sampler (tiny real models)."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mmada_rl.diffusion import (
    CORRUPTED_KEY,
    LOGITS_KEY,
    NOISY_SEQUENCE_KEY,
    DenoiserConfig,
    MaskedDiffusionDenoiser,
    MaskedDiffusionSampler,
    SamplerConfig,
    corrupt,
    make_denoiser_module,
    masked_counts,
    path_log_prob,
)
from mmada_rl.diffusion.schedules import CosineNoiseSchedule, FullMaskMixture, UniformNoiseSchedule
from mmada_rl.keys import ACTION_GRIPPER_ONLY_KEY, ACTION_IS_PAD_KEY, NOISE_LEVEL_KEY, SEQUENCE_KEY
from mmada_rl.objectives import MaskedDiffusionLoss
from mmada_rl.objectives.masked_diffusion import gaussian_bin_targets
from mmada_rl.tokenizers.layout import SEGMENTS, LayoutConfig, SequenceLayout
from mmada_rl.tokenizers.vocabulary import UnifiedVocabulary, VocabularyConfig

K, D_TOK, TEXT, IMG = 3, 2, 4, 4


def make_layout(goal_tokens=4, interleave=False, obs_tokens=IMG):
    vocab = UnifiedVocabulary(VocabularyConfig(text_vocab_size=20, image_codebook_size=32, action_codebook_size=16))
    return SequenceLayout(LayoutConfig(TEXT, obs_tokens, goal_tokens, K, D_TOK, interleave=interleave), vocab)


def make_batch(layout, batch=8, seed=0):
    """Clean sequences whose targets are a deterministic function of the conditioning."""
    g = torch.Generator().manual_seed(seed)
    text = torch.randint(0, 20, (batch, TEXT), generator=g)
    obs = torch.randint(0, 32, (batch, layout.config.obs_tokens), generator=g)
    goal = (text[:, :1] + 5 * torch.arange(layout.config.goal_tokens)) % 32 if layout.has_goal else None
    actions = ((text[:, :K, None] + torch.arange(D_TOK)) * 3) % 16  # (B, K, d_tok)
    return layout.assemble(text, obs if layout.config.obs_tokens else None, goal, actions)


def proprio_layout_and_batch(batch: int):
    """A layout with 3 proprio tokens (64 bins) and ``batch`` random clean sequences of it."""
    vocab = UnifiedVocabulary(VocabularyConfig(text_vocab_size=20, image_codebook_size=32, action_codebook_size=16,
                                               proprio_codebook_size=64))
    layout = SequenceLayout(LayoutConfig(TEXT, IMG, 4, K, D_TOK, proprio_tokens=3), vocab)
    g = torch.Generator().manual_seed(0)
    ids = layout.assemble(torch.randint(0, 20, (batch, TEXT), generator=g), torch.randint(0, 32, (batch, IMG), generator=g),
                          torch.randint(0, 32, (batch, 4), generator=g), torch.randint(0, 16, (batch, K, D_TOK), generator=g),
                          proprio_ids=torch.randint(0, 64, (batch, 3), generator=g))
    return layout, ids


def tiny(layout, **overrides):
    torch.manual_seed(0)
    return MaskedDiffusionDenoiser(DenoiserConfig.preset("tiny", **overrides), layout)


# -- forward process -------------------------------------------------------------
@pytest.mark.parametrize("kernel", ["absorbing", "uniform"])
@pytest.mark.parametrize("schedule", [UniformNoiseSchedule(), CosineNoiseSchedule(), FullMaskMixture(CosineNoiseSchedule())],
                         ids=["uniform", "cosine", "full_mask_mixture"])
def test_corrupt_only_targets(kernel, schedule):
    layout = make_layout()
    clean = make_batch(layout, batch=64)
    out = corrupt(clean, layout, schedule, kernel, torch.Generator().manual_seed(1))
    assert out.noisy_ids.shape == clean.shape and out.corrupted.dtype == torch.bool
    assert not out.corrupted[:, layout.is_condition].any()
    assert out.corrupted[:, layout.target_positions].sum(-1).min() >= 1
    assert torch.equal(out.noisy_ids[~out.corrupted], clean[~out.corrupted])
    low, high = schedule.support
    assert bool(((out.noise_level >= low) & (out.noise_level <= high)).all())
    expected = (out.noise_level * layout.num_targets).round().clamp(1, layout.num_targets)
    assert torch.equal(out.corrupted.sum(-1).float(), expected)
    noisy = out.noisy_ids[out.corrupted]
    if kernel == "absorbing":
        assert bool((noisy == layout.vocab.mask_id).all())
    else:
        lo, hi = layout.logit_bounds()
        pos = out.corrupted.nonzero()[:, 1]
        assert bool(((noisy >= lo[pos]) & (noisy < hi[pos])).all())
        assert not bool((noisy == layout.vocab.mask_id).any())


def test_corrupt_condition_masking_and_schedule_validation():
    layout = make_layout()
    clean = make_batch(layout, batch=64)
    out = corrupt(clean, layout, condition_mask_prob=0.5, generator=torch.Generator().manual_seed(2))
    cond = out.corrupted[:, layout.is_condition]
    assert 0.3 < cond.float().mean() < 0.6  # separators are never masked
    assert not out.corrupted[:, layout.is_separator].any()
    with pytest.raises(ValueError, match="low"):
        UniformNoiseSchedule(0.9, 0.5)
    with pytest.raises(ValueError, match="noise kernel"):
        corrupt(clean, layout, kernel="gaussian")


def test_full_mask_mixture_masks_every_target_of_its_share_of_windows():
    """``FullMaskMixture(base, p)``: about ``p`` of the windows have every target masked (the state a one-step
    decoder predicts from), the others keep the base schedule's ratios; it adds to the base's own rare full masks."""
    layout = make_layout()
    clean = make_batch(layout, batch=4000)
    base = UniformNoiseSchedule(0.5, 0.95)
    out = corrupt(clean, layout, FullMaskMixture(base, prob=0.3), generator=torch.Generator().manual_seed(4))
    full = out.noise_level == 1.0
    assert 0.27 < full.float().mean() < 0.33
    assert bool(out.corrupted[full][:, layout.target_positions].all())
    rest = out.noise_level[~full]
    assert bool(((rest >= 0.5) & (rest <= 0.95)).all())  # the base's draws, untouched
    assert not bool(out.corrupted[~full][:, layout.target_positions].all(-1).any())  # 0.95 of the targets at most
    everything = corrupt(clean[:8], layout, FullMaskMixture(base, prob=1.0))
    assert bool(everything.corrupted[:, layout.target_positions].all()) and FullMaskMixture(base, 1.0).support == (1.0, 1.0)
    assert FullMaskMixture(base, 0.3).support == (0.5, 1.0)
    with pytest.raises(ValueError, match=r"prob must lie in \[0, 1\], got 1.5"):
        FullMaskMixture(base, prob=1.5)
    with pytest.raises(TypeError, match="base must be a NoiseSchedule, got str"):
        FullMaskMixture("cosine", prob=0.5)


def test_proprio_dropout_corrupts_a_samples_whole_proprio_segment_or_none_of_it():
    """``proprio_drop_prob``: each sample's proprio tokens are all corrupted or all clean, at about that rate; the
    rest of the conditioning stays clean; the loss scores the dropped tokens as ``loss_condition``."""
    layout, clean = proprio_layout_and_batch(200)
    proprio = layout.positions("proprio")
    assert proprio.numel() == 3
    out = corrupt(clean, layout, proprio_drop_prob=0.3, generator=torch.Generator().manual_seed(3))
    dropped = out.corrupted[:, proprio]  # (B, P)
    per_sample = dropped.all(1)
    assert torch.equal(per_sample, dropped.any(1))  # all or none
    assert 0.2 < per_sample.float().mean() < 0.4
    other = layout.is_condition.clone()
    other[proprio] = False
    assert not out.corrupted[:, other].any()
    assert bool((out.noisy_ids[per_sample][:, proprio] == layout.vocab.mask_id).all())
    assert corrupt(clean, layout, proprio_drop_prob=1.0).corrupted[:, proprio].all()
    with pytest.raises(ValueError, match="proprio_drop_prob"):
        corrupt(clean, layout, proprio_drop_prob=1.5)
    with pytest.raises(ValueError, match="proprio_drop_prob"):
        MaskedDiffusionLoss(tiny(layout), proprio_drop_prob=-0.1)

    # proprio_drop_index: only those tokens of the segment drop (the goal position stays readable), still together
    some = corrupt(clean, layout, proprio_drop_prob=0.3, proprio_drop_index=torch.tensor([0, 2]),
                   generator=torch.Generator().manual_seed(3))
    assert torch.equal(some.corrupted[:, proprio[[0, 2]]], dropped[:, [0, 2]])  # the same draws, fewer tokens
    assert not some.corrupted[:, proprio[1]].any()
    for bad in ([3], [0, 0], []):
        with pytest.raises(ValueError, match="proprio_drop_index"):
            MaskedDiffusionLoss(tiny(layout), proprio_drop_prob=0.3, proprio_drop_index=bad)
    kept = MaskedDiffusionLoss(tiny(layout), proprio_drop_prob=1.0, proprio_drop_index=[1])
    scored = kept.corrupt(TensorDict({SEQUENCE_KEY: clean[:8]}, batch_size=[8]))
    assert scored[CORRUPTED_KEY][:, proprio].tolist() == [[False, True, False]] * 8

    loss_fn = MaskedDiffusionLoss(tiny(layout), proprio_drop_prob=1.0)
    assert "loss_condition" in loss_fn.out_keys
    td = TensorDict({SEQUENCE_KEY: clean[:4]}, batch_size=[4])
    out = loss_fn(td)
    assert torch.isfinite(out["loss_condition"]) and out["loss_condition"] > 0
    assert "loss_condition" not in MaskedDiffusionLoss(tiny(layout)).out_keys


def test_masked_counts():
    for kind in ("cosine", "linear"):
        for steps in (1, 4, 10, 30):
            counts = masked_counts(10, steps, kind)
            assert counts[-1] == 0 and len(counts) == steps
            assert all(a >= b for a, b in zip([10] + counts, counts))


# -- denoiser --------------------------------------------------------------------
@pytest.mark.parametrize("attention", ["bidirectional", "block_causal"])
def test_denoiser_shapes_and_restricted_logits(attention):
    layout = make_layout(interleave=True)
    net = tiny(layout, attention=attention)
    ids = make_batch(layout, batch=2)
    logits = net(ids, torch.tensor([0.3, 0.9]))
    assert logits.shape == (2, layout.length, layout.vocab.size)
    allowed = layout.allowed_logit_mask()
    tgt = layout.target_positions
    assert bool(torch.isneginf(logits[:, tgt][:, ~allowed[tgt]]).all())
    assert bool(torch.isfinite(logits[:, tgt][:, allowed[tgt]]).all())
    sub = net(ids, torch.tensor([0.3, 0.9]), positions=tgt)
    assert torch.allclose(sub, logits[:, tgt], atol=1e-5)
    module = make_denoiser_module(net)
    td = module(TensorDict({SEQUENCE_KEY: ids, NOISE_LEVEL_KEY: torch.ones(2)}, batch_size=[2]))
    assert td[LOGITS_KEY].shape == logits.shape


def test_block_causal_conditioning_ignores_targets_and_noise_level():
    layout = make_layout()
    ids = make_batch(layout, batch=2)
    changed = ids.clone()
    changed[:, layout.action_positions[0]] = layout.vocab.mask_id
    cond = layout.is_condition
    for attention, same in (("block_causal", True), ("bidirectional", False)):
        net = tiny(layout, attention=attention).eval()
        a, b = net(ids, torch.ones(2)), net(changed, torch.ones(2))
        assert torch.allclose(a[:, cond], b[:, cond], atol=1e-6) is same
        # the noise level conditions the targets only under block-causal attention
        c = net(ids, torch.full((2,), 0.3))
        assert torch.allclose(a[:, cond], c[:, cond], atol=1e-6) is same
        assert not torch.allclose(a[:, ~cond], c[:, ~cond], atol=1e-6)


def test_cross_attention_to_visual():
    layout = make_layout(obs_tokens=0)
    net = tiny(layout, cross_attention_to_visual=True, visual_dim=12).eval()
    ids = make_batch(layout, batch=2)
    visual = torch.randn(2, 5, 12)
    out = net(ids, torch.ones(2), visual=visual)
    assert out.shape == (2, layout.length, layout.vocab.size)
    assert not torch.allclose(out, net(ids, torch.ones(2), visual=visual + 1))
    with pytest.raises(ValueError, match="visual: expected shape"):
        net(ids, torch.ones(2))
    module = make_denoiser_module(net)
    assert len(module.in_keys) == 3


def test_keypoint_tokens_are_the_expected_positions_of_learned_maps():
    from mmada_rl.diffusion.visual import ConvPatchEncoder, SpatialSoftmax

    pool = SpatialSoftmax(1, num_keypoints=1)
    with torch.no_grad():
        pool.keypoints.weight.fill_(50.0)
        pool.keypoints.bias.zero_()
    x = torch.zeros(1, 1, 5, 9)
    x[0, 0, 1, 7] = 1.0  # one bright cell: row 1 of 5, column 7 of 9
    xy = pool(x)[0]
    torch.testing.assert_close(xy, torch.tensor([-1 + 2 * 7 / 8, -1 + 2 * 1 / 4]), atol=1e-4, rtol=0)
    enc = ConvPatchEncoder((8, 16), keypoints=3)
    images = torch.randint(0, 256, (2, 3, 16, 16), dtype=torch.uint8)
    tokens = enc(images)  # (B, K, C): each keypoint's position embedded, plus its own embedding
    assert tokens.shape == (2, 3, 16)
    positions = enc.pool(enc.cnn(images.float() / 127.5 - 1.0)).reshape(2, 3, 2)
    torch.testing.assert_close(tokens, enc.keypoint_position(positions) + enc.keypoint_embedding)
    with pytest.raises(ValueError, match="keypoints must be an int >= 0"):
        ConvPatchEncoder((8, 16), keypoints=-1)
    with pytest.raises(ValueError, match="needs visual_encoder_channels"):
        DenoiserConfig(cross_attention_to_visual=True, visual_keypoints=4)
    with pytest.raises(ValueError, match="visual_keypoints must be a positive int"):
        DenoiserConfig(cross_attention_to_visual=True, visual_encoder_channels=[8], visual_keypoints=0)


def test_proprio_value_embedding_reads_state_bins_as_ordered_values():
    layout, ids = proprio_layout_and_batch(2)
    at_proprio = layout.segment_ids == SEGMENTS.index("proprio")
    plain, valued = tiny(layout).eval(), tiny(layout, proprio_value_embedding=True).eval()
    missing, unexpected = valued.load_state_dict(plain.state_dict(), strict=False)  # the same weights elsewhere
    assert not unexpected and missing and all(k.startswith("proprio_value_embedding.") for k in missing)
    # only the proprio positions change, and by an embedding of the bin's value
    delta = valued._embed(ids) - plain._embed(ids)
    assert bool((delta[:, ~at_proprio] == 0).all()) and bool((delta[:, at_proprio].norm(dim=-1) > 0).all())
    # the further apart two bins, the further apart their value embeddings (at initialisation)
    value = valued.proprio_value_embedding(torch.arange(64) / 63)  # (64, D)
    dist = (value - value[:1]).norm(dim=-1)
    assert bool((dist[[1, 4, 16, 63]].diff() > 0).all())
    # a masked proprio token carries no value
    masked = ids.clone()
    masked[:, at_proprio] = layout.vocab.mask_id
    assert bool(((valued._embed(masked) - plain._embed(masked)) == 0).all())
    # the condition cache and the full pass agree with the value embedding too
    net = tiny(layout, proprio_value_embedding=True, attention="block_causal").eval()
    tgt = layout.target_positions
    noisy = ids.clone()
    noisy[:, tgt] = layout.vocab.mask_id
    full = net(noisy, torch.ones(2))[:, tgt]
    cached = net(noisy, torch.ones(2), cache=net.cache_condition(ids))
    finite = torch.isfinite(full)
    assert torch.allclose(cached[finite], full[finite], atol=1e-5)
    with pytest.raises(ValueError, match="needs proprio tokens"):
        tiny(make_layout(), proprio_value_embedding=True)


def test_action_value_embedding_makes_neighbouring_bins_alike():
    layout = make_layout()
    ids = make_batch(layout, batch=2)
    start, stop = layout.vocab.range_of("action")
    at_action = layout.segment_ids == SEGMENTS.index("action")
    plain, valued = tiny(layout).eval(), tiny(layout, action_value_embedding=True).eval()
    missing, unexpected = valued.load_state_dict(plain.state_dict(), strict=False)  # the same weights elsewhere
    assert not unexpected and missing and all(k.startswith("action_value_embedding.") for k in missing)
    # only the action positions change, by the embedding of the bin's value
    delta = valued._embed(ids) - plain._embed(ids)
    assert bool((delta[:, ~at_action] == 0).all()) and bool((delta[:, at_action].norm(dim=-1) > 0).all())
    # the action rows of the tied head carry it too: only the action ids' logits change
    hidden = torch.randn(3, plain.config.d_model)
    positions = at_action.nonzero().squeeze(-1)[:3]
    diff = (valued.project(hidden, positions) - plain.project(hidden, positions)).nan_to_num(0.0)
    ids_changed = diff.abs().sum(0).nonzero().squeeze(-1)
    assert ids_changed.numel() and bool(((ids_changed >= start) & (ids_changed < stop)).all())
    # at initialisation a bin's embedding is nearer its neighbour's than a distant bin's
    weight = valued._token_weight()[start:stop]  # (16, D)
    dist = (weight - weight[:1]).norm(dim=-1)
    assert dist[1] < dist[8] and dist[1] < dist[15]
    # the value embedding learns from the loss through both uses
    loss = valued(ids, torch.ones(2))[:, at_action].log_softmax(-1).nan_to_num(0.0).sum()
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in valued.action_value_embedding.parameters())
    # the condition cache and the full pass agree with it
    net = tiny(layout, action_value_embedding=True, attention="block_causal").eval()
    tgt = layout.target_positions
    noisy = ids.clone()
    noisy[:, tgt[::2]] = layout.vocab.mask_id  # some action tokens visible, as in the middle of decoding
    full = net(noisy, torch.ones(2))[:, tgt]
    cached = net(noisy, torch.ones(2), cache=net.cache_condition(ids))
    finite = torch.isfinite(full)
    assert torch.allclose(cached[finite], full[finite], atol=1e-5)


def test_denoiser_config_validation_and_presets():
    with pytest.raises(ValueError, match="num_heads=3"):
        DenoiserConfig(d_model=64, num_heads=3)
    with pytest.raises(ValueError, match="attention"):
        DenoiserConfig(attention="causal")
    with pytest.raises(ValueError, match="preset"):
        DenoiserConfig.preset("huge")
    assert DenoiserConfig.preset("small").d_model == 256
    assert DenoiserConfig.preset("base").num_heads == 8


def test_dropout_regularises_training_passes_only():
    layout = make_layout()
    ids, level = make_batch(layout, batch=2), torch.tensor([0.3, 0.9])
    net = tiny(layout, dropout=0.5).train()
    assert not torch.equal(net(ids, level), net(ids, level))  # a fresh dropout mask each training pass
    net.eval()
    assert torch.equal(net(ids, level), net(ids, level))
    with pytest.raises(ValueError, match="dropout"):
        DenoiserConfig(dropout=1.0)


def test_pretrained_path_errors(tmp_path):
    layout = make_layout()
    with pytest.raises(FileNotFoundError, match="does not exist"):
        tiny(layout, pretrained_path=str(tmp_path / "missing"))
    try:
        import transformers  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="transformers"):
            tiny(layout, pretrained_path=str(tmp_path))


# -- loss ----------------------------------------------------------------------
def test_loss_decreases_on_fixed_batch():
    layout = make_layout()
    loss_fn = MaskedDiffusionLoss(tiny(layout))
    loss_fn.generator = torch.Generator().manual_seed(0)
    train = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=16)}, batch_size=[16])
    probe = loss_fn.corrupt(train.clone(), generator=torch.Generator().manual_seed(123))

    def total(out):
        return out["loss_action"] + out["loss_goal"]

    with torch.no_grad():
        before = total(loss_fn(probe)).item()
    optim = torch.optim.Adam(loss_fn.parameters(), lr=3e-3)
    for _ in range(50):
        out = loss_fn(train)
        optim.zero_grad()
        total(out).backward()
        optim.step()
    with torch.no_grad():
        after = loss_fn(probe)
    assert total(after).item() < 0.7 * before, (before, total(after).item())
    assert after["action_accuracy"] > 0.3


def test_gaussian_bin_targets_are_ordinal_distributions():
    soft = gaussian_bin_targets(16, 0.75)
    torch.testing.assert_close(soft.sum(-1), torch.ones(16))
    assert torch.equal(soft.argmax(-1), torch.arange(16))
    c = 8  # an interior id: symmetric, falling with the distance
    assert torch.allclose(soft[c, c - 3:c], soft[c, c + 1:c + 4].flip(0))
    assert soft[c, c] > soft[c, c + 1] > soft[c, c + 2] > soft[c, c + 3] > 0
    assert soft[0, 0] > soft[8, 8]  # the edge keeps the mass that would fall outside the range
    torch.testing.assert_close(gaussian_bin_targets(16, 0.01), torch.eye(16))  # sigma -> 0: one-hot


def test_action_label_sigma_scores_action_tokens_against_gaussian_targets():
    layout = make_layout()
    plain = MaskedDiffusionLoss(tiny(layout))
    smooth = MaskedDiffusionLoss(tiny(layout), action_label_sigma=1.5)
    td = plain.corrupt(TensorDict({SEQUENCE_KEY: make_batch(layout, batch=4)}, batch_size=[4]),
                       generator=torch.Generator().manual_seed(0))
    a, b = plain.score(td), smooth.score(td)
    torch.testing.assert_close(a.logits, b.logits)  # same weights, same corruption
    is_action = b.segment == layout.segment_ids[layout.action_positions[0]]
    assert is_action.any() and (~is_action).any()
    torch.testing.assert_close(b.ce[~is_action], a.ce[~is_action])  # goal tokens: the clean id's cross-entropy
    start, stop = layout.vocab.range_of("action")
    soft = gaussian_bin_targets(stop - start, 1.5)[b.targets[is_action] - start]
    expected = -(soft * torch.log_softmax(b.logits[is_action, start:stop], -1)).sum(-1)
    torch.testing.assert_close(b.ce[is_action], expected)
    assert (b.ce[is_action] != a.ce[is_action]).all()
    # a prediction one id off costs less than one five ids off; without smoothing they cost the same
    target = torch.tensor([start + 8])
    logits = torch.full((2, layout.vocab.size), float("-inf"))
    logits[:, start:stop] = 0.0
    logits[0, start + 9] = logits[1, start + 13] = 5.0
    near, far = smooth._cross_entropy(logits, target.expand(2), torch.ones(2, dtype=torch.bool))
    assert near < far
    near, far = plain._cross_entropy(logits, target.expand(2), torch.ones(2, dtype=torch.bool))
    torch.testing.assert_close(near, far)
    with pytest.raises(ValueError, match="action_label_sigma must be >= 0"):
        MaskedDiffusionLoss(tiny(layout), action_label_sigma=-1.0)


def test_action_mean_weight_adds_the_l1_error_of_the_expected_bin():
    layout = make_layout()
    plain = MaskedDiffusionLoss(tiny(layout))
    mean = MaskedDiffusionLoss(tiny(layout), action_mean_weight=3.0)
    assert "loss_action_mean" in mean.out_keys and "loss_action_mean" not in plain.out_keys
    start, stop = layout.vocab.range_of("action")
    n = stop - start
    # half the mass one bin below the clean id 8, half three above: the expected bin is 9, one bin (2 / n) off
    logits = torch.full((2, layout.vocab.size), float("-inf"))
    logits[:, start:stop] = -30.0
    logits[0, start + 7] = logits[0, start + 11] = 0.0
    logits[1, start + 8] = 0.0  # all the mass on the clean bin: no error
    error = mean.action_mean_error(logits, torch.tensor([start + 8, start + 8]))
    torch.testing.assert_close(error, torch.tensor([2.0 / n, 0.0]), atol=1e-6, rtol=0)
    # forward: the weight times the mean error over the scored action tokens; the cross-entropies unchanged
    td = plain.corrupt(TensorDict({SEQUENCE_KEY: make_batch(layout, batch=4)}, batch_size=[4]),
                       generator=torch.Generator().manual_seed(0))
    out, base, s = mean(td), plain(td), mean.score(td)
    is_action = s.segment == layout.segment_ids[layout.action_positions[0]]
    expected = 3.0 * mean.action_mean_error(s.logits[is_action], s.targets[is_action]).mean()
    torch.testing.assert_close(out["loss_action_mean"], expected)
    torch.testing.assert_close(out["loss_action"], base["loss_action"])
    # its gradient moves the expected bin toward the clean one
    out["loss_action_mean"].backward()
    with torch.no_grad():
        for p in mean.parameters():
            if p.grad is not None:  # the parameters the action logits depend on
                p -= 0.5 * p.grad
        after = mean.score(td)
    before = expected / 3.0  # the unweighted mean error
    assert mean.action_mean_error(after.logits[is_action], after.targets[is_action]).mean() < before
    with pytest.raises(ValueError, match="action_mean_weight must be >= 0"):
        MaskedDiffusionLoss(tiny(layout), action_mean_weight=-1.0)


def test_only_masked_positions_are_scored():
    layout = make_layout()
    loss_fn = MaskedDiffusionLoss(tiny(layout))
    td = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=4)}, batch_size=[4])
    loss_fn.corrupt(td, generator=torch.Generator().manual_seed(0))
    base = loss_fn(td)
    corrupted = td[CORRUPTED_KEY]
    visible = (~corrupted[0]) & layout.is_target
    pos = visible.nonzero()[0, 0]
    td2 = td.clone()
    seq = td2[SEQUENCE_KEY]
    low, high = layout.logit_bounds()
    seq[0, pos] = low[pos] + (seq[0, pos] - low[pos] + 1) % (high[pos] - low[pos])  # another in-range token
    out = loss_fn(td2)
    for key in ("loss_action", "loss_goal"):
        assert torch.equal(out[key], base[key])
    # changing the clean token at a corrupted position does change it
    masked = (corrupted[0] & layout.is_target).nonzero()[0, 0]
    seq[0, masked] = low[masked] + (seq[0, masked] - low[masked] + 1) % (high[masked] - low[masked])
    out = loss_fn(td2)
    assert not (torch.equal(out["loss_action"], base["loss_action"]) and torch.equal(out["loss_goal"], base["loss_goal"]))


def test_set_keys_backward_and_diagnostics():
    layout = make_layout()
    net = tiny(layout, attention="block_causal")
    loss_fn = MaskedDiffusionLoss(net, schedule="cosine", goal_weight=0.5)
    loss_fn.set_keys(sequence="tokens", noise_level="rho")
    assert loss_fn.tensor_keys.sequence == "tokens" and loss_fn.in_keys == ["tokens"]
    td = TensorDict({"tokens": make_batch(layout, batch=4)}, batch_size=[4])
    out = loss_fn(td)
    assert set(out.keys()) == set(loss_fn.out_keys)
    assert "rho" not in td.keys()  # the input is not modified
    (out["loss_action"] + out["loss_goal"]).backward()
    grads = [p.grad for p in net.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    for key in ("action_accuracy", "goal_accuracy", "noise_level"):
        assert not out[key].requires_grad and not key.startswith("loss_")
    with pytest.raises(ValueError, match="not an accepted"):
        loss_fn.set_keys(bogus="x")


def test_loss_without_goal_with_padding_and_condition_masking():
    layout = make_layout(goal_tokens=0)
    loss_fn = MaskedDiffusionLoss(tiny(layout), kernel="uniform", condition_mask_prob=0.3)
    seq = make_batch(layout, batch=4)
    is_pad = torch.zeros(4, K, dtype=torch.bool)
    is_pad[:, 1:] = True
    td = TensorDict({SEQUENCE_KEY: seq, ACTION_IS_PAD_KEY: is_pad}, batch_size=[4])
    loss_fn.corrupt(td, generator=torch.Generator().manual_seed(0))
    out = loss_fn(td)
    assert out["loss_goal"] == 0 and "goal_accuracy" not in out.keys()
    assert torch.isfinite(out["loss_action"]) and torch.isfinite(out["loss_condition"])
    # padded chunk steps are not scored: changing their clean tokens leaves the loss unchanged
    td2 = td.clone()
    pad_pos = layout.action_positions[D_TOK:]
    td2[SEQUENCE_KEY][:, pad_pos] = layout.vocab.range_of("action")[0]
    assert torch.equal(loss_fn(td2)["loss_action"], out["loss_action"])
    assert NOISY_SEQUENCE_KEY in td.keys(True)


def test_gripper_only_rows_score_the_last_token_of_each_action_alone():
    layout = make_layout()
    loss_fn = MaskedDiffusionLoss(tiny(layout))
    td = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=4)}, batch_size=[4])
    loss_fn.corrupt(td, generator=torch.Generator().manual_seed(0))
    td[CORRUPTED_KEY][:, layout.action_positions] = True  # every action token scored, unless the flag says otherwise
    plain = loss_fn(td)
    flagged = torch.tensor([True, False, True, False])
    td[ACTION_GRIPPER_ONLY_KEY] = flagged
    out = loss_fn(td)
    assert plain["num_scored"] - out["num_scored"] == 2 * K * (D_TOK - 1)  # two rows lose their arm tokens
    action = layout.action_positions.reshape(K, D_TOK)  # each action's tokens in turn, the gripper's last
    arm, gripper = action[:, :-1].reshape(-1), action[:, -1]
    start, stop = layout.vocab.range_of("action")

    def relabelled(rows, cols):
        """``td`` with other clean action ids at ``rows`` x ``cols``."""
        changed = td.clone()
        ids = changed[SEQUENCE_KEY]
        ids[rows[:, None], cols] = (ids[rows[:, None], cols] - start + 1) % (stop - start) + start
        return changed

    flagged_rows, other_rows = flagged.nonzero().reshape(-1), (~flagged).nonzero().reshape(-1)
    assert torch.equal(loss_fn(relabelled(flagged_rows, arm))["loss_action"], out["loss_action"])  # not scored
    assert not torch.equal(loss_fn(relabelled(flagged_rows, gripper))["loss_action"], out["loss_action"])
    assert not torch.equal(loss_fn(relabelled(other_rows, arm))["loss_action"], out["loss_action"])
    # one token per action has no gripper token of its own
    one = SequenceLayout(LayoutConfig(TEXT, IMG, 4, K, 1), layout.vocab)
    ids = one.assemble(torch.zeros(2, TEXT, dtype=torch.long), torch.zeros(2, IMG, dtype=torch.long),
                       torch.zeros(2, 4, dtype=torch.long), torch.zeros(2, K, 1, dtype=torch.long))
    rows = TensorDict({SEQUENCE_KEY: ids, ACTION_GRIPPER_ONLY_KEY: torch.ones(2, dtype=torch.bool)}, batch_size=[2])
    with pytest.raises(ValueError, match="needs one token per action entry; this layout has 1 per action"):
        MaskedDiffusionLoss(tiny(one))(rows)


def test_loss_skips_samples_outside_torchrl_loss_mask():
    layout = make_layout()
    loss_fn = MaskedDiffusionLoss(tiny(layout))
    td = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=6).reshape(2, 3, -1)}, batch_size=[2, 3])
    loss_fn.corrupt(td, generator=torch.Generator().manual_seed(0))
    valid = torch.tensor([[True, True, False], [True, False, False]])
    td[("collector", "mask")] = valid
    out = loss_fn(td)
    assert out["num_scored"] == td[CORRUPTED_KEY][valid].sum()


# -- sampler -------------------------------------------------------------------
def prompt_of(layout, batch=3):
    ids = make_batch(layout, batch=batch)
    ids[:, layout.target_positions] = layout.vocab.mask_id
    return ids


@pytest.mark.parametrize("kernel", ["absorbing", "uniform"])
@pytest.mark.parametrize("remasking", [False, True])
def test_sampler_commits_every_target_in_range(kernel, remasking):
    layout = make_layout(interleave=True)
    net = tiny(layout).eval()
    prompt = prompt_of(layout)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=5, kernel=kernel, remasking=remasking))
    out = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(0))
    tgt = layout.target_positions
    assert torch.equal(out.ids[:, layout.is_condition], prompt[:, layout.is_condition])
    low, high = layout.logit_bounds()
    assert bool(((out.ids >= low) & (out.ids < high))[:, tgt].all())
    assert out.action_tokens.shape == (3, K, D_TOK) and out.goal_tokens.shape == (3, 4)
    committed = out.path.committed  # (B, N, T)
    assert bool((committed.sum(1) >= 1).all())
    if not remasking:  # each target committed exactly once, as many per step as the schedule says
        assert bool((committed.sum(1) == 1).all())
        counts = masked_counts(layout.num_targets, 5, "cosine")
        left = layout.num_targets - committed.sum(-1).cumsum(-1)  # (B, N)
        assert left.tolist() == [counts] * 3
    assert bool(out.path.noise_levels[:, 0].eq(1.0).all())


def test_greedy_is_deterministic_and_sampling_is_not():
    layout = make_layout()
    net = tiny(layout).eval()
    prompt = prompt_of(layout)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=4))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(0))
        b = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a.ids, b.ids)
    assert torch.equal(a.ids, sampler.sample(net, prompt, greedy=True).ids)
    with set_exploration_type(ExplorationType.RANDOM):
        c = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(0))
        d = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(1))
    assert not torch.equal(c.ids, d.ids)


@pytest.mark.parametrize("remasking", [False, True])
def test_sampler_returns_the_distribution_each_action_token_was_committed_from(remasking):
    layout = make_layout(interleave=True)
    net = tiny(layout).eval()
    prompt = prompt_of(layout, batch=4)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=5, remasking=remasking))
    assert sampler.sample(net, prompt, greedy=True).action_probs is None  # only on request
    for greedy in (True, False):
        out = sampler.sample(net, prompt, greedy=greedy, action_probs=True, generator=torch.Generator().manual_seed(0))
        probs = out.action_probs  # (B, K, d_tok, V_a)
        assert probs.shape == (4, K, D_TOK, 16)
        torch.testing.assert_close(probs.sum(-1), torch.ones(4, K, D_TOK))
        # the probability of each decoded action token is the one recorded at the step that (last) committed it
        index = layout.action_target_index
        committed = out.path.committed[:, :, index]  # (B, N, K * d_tok)
        last = (committed * torch.arange(1, 6)[:, None]).argmax(1)  # (B, K * d_tok)
        recorded = out.path.log_probs[:, :, index].gather(1, last[:, None]).squeeze(1).exp()
        chosen = probs.reshape(4, K * D_TOK, 16).gather(-1, out.action_tokens.reshape(4, -1, 1)).squeeze(-1)
        torch.testing.assert_close(chosen, recorded)
        if greedy:
            assert torch.equal(probs.argmax(-1), out.action_tokens)


class StubDenoiser(nn.Module):
    """Crafted logits: at step 0 (noise level 1) the first target is confident in token A;
    afterwards the model prefers B there and finds A very unlikely."""

    def __init__(self, layout):
        super().__init__()
        self.layout = layout
        self.scale = nn.Parameter(torch.ones(()))
        start = layout.vocab.range_of("action")[0]
        self.token_a, self.token_b = start + 3, start + 5

    def forward(self, ids, noise_level, visual=None, positions=None):
        batch, num = ids.shape[0], positions.numel()
        logits = torch.zeros(batch, num, self.layout.vocab.size)
        first = 0
        later = noise_level < 1.0  # (B,)
        logits[:, first, self.token_a] = torch.where(later, -10.0, 10.0)
        logits[:, first, self.token_b] = torch.where(later, 10.0, 0.0)
        logits[:, 1:, self.token_b + 1] = torch.where(later, 8.0, 0.0)[:, None]
        return logits * self.scale


@pytest.mark.parametrize("remasking", [False, True])
def test_remasking_revises_a_committed_token(remasking):
    layout = make_layout(goal_tokens=0)
    stub = StubDenoiser(layout)
    prompt = prompt_of(layout, batch=2)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=4, schedule="linear", remasking=remasking))
    out = sampler.sample(stub, prompt, greedy=True)
    first = layout.target_positions[0]
    path = out.path
    assert path.committed[:, 0, 0].all() and (path.tokens[:, 0, 0] == stub.token_a).all()
    if remasking:
        assert (out.ids[:, first] == stub.token_b).all()
        assert (path.committed[:, :, 0].sum(-1) == 2).all()  # committed, re-masked, committed again
        assert (path.inputs[:, 2, 0] == layout.vocab.mask_id).all()
    else:
        assert (out.ids[:, first] == stub.token_a).all()
    assert torch.allclose(path_log_prob(stub, path), path.log_prob, atol=1e-5)


@pytest.mark.parametrize("remasking", [False, True])
@pytest.mark.parametrize("kernel", ["absorbing", "uniform"])
def test_path_log_prob_replays_exactly(remasking, kernel):
    layout = make_layout(interleave=True)
    net = tiny(layout).eval()
    prompt = prompt_of(layout, batch=4)
    sampler = MaskedDiffusionSampler(
        SamplerConfig(num_steps=6, remasking=remasking, kernel=kernel, temperature=0.8, confidence_temperature=2.0)
    )
    with set_exploration_type(ExplorationType.RANDOM):
        out = sampler.sample(net, prompt, generator=torch.Generator().manual_seed(3))
    path = out.path
    replay = path_log_prob(make_denoiser_module(net), path)
    assert replay.shape == (4,)
    assert torch.allclose(replay, path.log_prob, atol=1e-5), (replay, path.log_prob)
    assert torch.allclose(path_log_prob(net, path[1:3]), path.log_prob[1:3], atol=1e-5)  # paths slice like tensors
    per_token = path_log_prob(net, path, per_token=True)
    assert torch.allclose(per_token, path.log_probs, atol=1e-5)
    path_log_prob(net, path).sum().backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


# -- conditioning cache (block-causal attention) -----------------------------------
def block_causal_net(layout, visual: str | None):
    """A tiny block-causal denoiser and its visual input: none, features, or images through its own CNN."""
    if visual is None:
        return tiny(layout, attention="block_causal").eval(), None
    if visual == "features":
        net = tiny(layout, attention="block_causal", cross_attention_to_visual=True, visual_dim=12)
        return net.eval(), torch.randn(3, 5, 12, generator=torch.Generator().manual_seed(1))
    net = tiny(layout, attention="block_causal", cross_attention_to_visual=True, visual_encoder_channels=[8, 16])
    return net.eval(), torch.randint(0, 256, (3, 3, 16, 16), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))


@pytest.mark.parametrize("visual", [None, "features", "images"])
@pytest.mark.parametrize("interleave", [False, True])
def test_condition_cache_gives_the_full_forward_target_logits(visual, interleave):
    layout = make_layout(interleave=interleave)
    net, vis = block_causal_net(layout, visual)
    ids = make_batch(layout, batch=3)
    tgt = layout.target_positions
    cache = net.cache_condition(prompt_of(layout), vis)  # the targets of the prompt do not matter
    g = torch.Generator().manual_seed(2)
    for rho in (torch.ones(3), torch.tensor([0.2, 0.5, 0.9])):
        partly = ids.clone()
        partly[:, tgt] = torch.where(torch.rand(3, len(tgt), generator=g) < rho[:, None], layout.vocab.mask_id, ids[:, tgt])
        full = net(partly, rho, visual=vis)[:, tgt]  # (B, T, V)
        cached = net(partly, rho, cache=cache)
        assert cached.shape == full.shape
        finite = torch.isfinite(full)
        assert torch.equal(finite, torch.isfinite(cached))
        assert torch.allclose(cached[finite], full[finite], atol=1e-5)
    assert cache.repeat_interleave(2).batch_size == 6


def test_condition_cache_errors():
    layout = make_layout()
    ids = prompt_of(layout)
    with pytest.raises(ValueError, match="needs attention='block_causal'"):
        tiny(layout).cache_condition(ids)
    net, _ = block_causal_net(layout, None)
    cache = net.cache_condition(ids)
    with pytest.raises(ValueError, match="only the target positions"):
        net(ids, torch.ones(3), positions=torch.arange(layout.length), cache=cache)
    with pytest.raises(ValueError, match="built for a batch of 3"):
        net(ids[:2], torch.ones(2), cache=cache)


@pytest.mark.parametrize("visual", [None, "features"])
@pytest.mark.parametrize("remasking", [False, True])
def test_cached_decoding_and_replay_match_the_uncached_ones(visual, remasking):
    layout = make_layout(interleave=True)
    net, vis = block_causal_net(layout, visual)
    prompt = prompt_of(layout)
    runs = {}
    for cached in (True, False):
        sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=5, remasking=remasking, cache_condition=cached))
        with set_exploration_type(ExplorationType.RANDOM):
            runs[cached] = sampler.sample(net, prompt, visual=vis, generator=torch.Generator().manual_seed(4))
    assert torch.equal(runs[True].ids, runs[False].ids)
    path = runs[True].path
    assert torch.allclose(path.log_probs, runs[False].path.log_probs, atol=1e-5)
    grads = {}
    for cached in (True, False):  # replay: same log-probabilities, same gradients
        net.zero_grad()
        replay = path_log_prob(net, path, visual=vis, cache_condition=cached)
        assert torch.allclose(replay, path.log_prob, atol=1e-4)
        replay.sum().backward()
        grads[cached] = [p.grad.clone() for p in net.parameters() if p.grad is not None]
    assert len(grads[True]) == len(grads[False])
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(grads[True], grads[False]))
    steps = torch.tensor([[1, 3]] * 3)
    assert torch.allclose(path_log_prob(net, path, visual=vis, steps=steps),
                          path_log_prob(net, path, visual=vis, steps=steps, cache_condition=False), atol=1e-5)


def loss_and_grads(loss_fn, td, seed=5):
    """The loss of ``td`` under a fixed forward-process RNG, its diagnostics, and the denoiser's gradients."""
    loss_fn.generator = torch.Generator().manual_seed(seed)
    loss_fn.zero_grad()
    out = loss_fn(td)
    (out["loss_action"] + out["loss_goal"]).backward()
    return out, [p.grad.clone() for p in loss_fn.parameters() if p.grad is not None]


@pytest.mark.parametrize("visual", [None, "features", "images"])
@pytest.mark.parametrize("copies", [1, 3])
def test_loss_with_the_condition_cache_equals_full_passes(visual, copies, monkeypatch):
    layout = make_layout(interleave=True)
    net, vis = block_causal_net(layout, visual)
    td = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=3)}, batch_size=[3])
    if vis is not None:
        td["visual"] = vis
    passes, real = [], MaskedDiffusionDenoiser.cache_condition
    monkeypatch.setattr(MaskedDiffusionDenoiser, "cache_condition", lambda self, *a: passes.append(a[0].shape[0]) or real(self, *a))
    results = {}
    for cached in (True, False):
        loss_fn = MaskedDiffusionLoss(net, corruptions_per_sample=copies, cache_condition=cached)
        loss_fn.set_keys(visual="visual")
        results[cached] = loss_and_grads(loss_fn, td)
    assert passes == [3]  # one conditioning pass per sample for all its corruptions, only when asked
    (out, grads), (ref, ref_grads) = results[True], results[False]
    assert out["num_scored"] == ref["num_scored"] and out["num_scored"] > 0
    for key in ("loss_action", "loss_goal"):
        torch.testing.assert_close(out[key], ref[key], rtol=1e-5, atol=1e-6)
    assert len(grads) == len(ref_grads)
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(grads, ref_grads))


def test_several_corruptions_per_sample_score_the_repeated_batch():
    """C corruptions of each sample are the loss of the batch with each sample repeated C times (same RNG draws):
    each at its own noise level, every one scored."""
    layout = make_layout()
    net = tiny(layout, attention="block_causal")
    seq = make_batch(layout, batch=4)
    is_pad = torch.zeros(4, K, dtype=torch.bool)
    is_pad[1, 2:] = True
    td = TensorDict({SEQUENCE_KEY: seq, ACTION_IS_PAD_KEY: is_pad}, batch_size=[4])
    repeated = TensorDict({SEQUENCE_KEY: seq.repeat_interleave(3, 0), ACTION_IS_PAD_KEY: is_pad.repeat_interleave(3, 0)},
                          batch_size=[12])
    several = MaskedDiffusionLoss(net, corruptions_per_sample=3)
    out, grads = loss_and_grads(several, td)
    ref, ref_grads = loss_and_grads(MaskedDiffusionLoss(net), repeated)
    assert out["num_scored"] == ref["num_scored"]
    for key in ("loss_action", "loss_goal", "action_accuracy", "noise_level"):
        torch.testing.assert_close(out[key], ref[key], rtol=1e-5, atol=1e-6)
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(grads, ref_grads))
    several.generator = torch.Generator().manual_seed(5)
    scored = several.score(td)
    assert scored.batch == 4 and scored.noisy.shape[0] == 12 and scored.noise_level.unique().numel() > 4
    assert torch.equal(scored.sample, scored.rows // 3) and set(scored.sample.tolist()) == {0, 1, 2, 3}
    given = several.corrupt(td.clone(), generator=torch.Generator().manual_seed(0))  # a given corruption: scored once
    assert several.score(given).noisy.shape[0] == 4
    with pytest.raises(ValueError, match="positive integer"):
        MaskedDiffusionLoss(net, corruptions_per_sample=0)
