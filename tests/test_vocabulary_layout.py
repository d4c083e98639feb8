"""Unified vocabulary and sequence layout."""
from __future__ import annotations

import json

import pytest
import torch

from mmada_rl.tokenizers.layout import SEGMENTS, LayoutConfig, SequenceLayout
from mmada_rl.tokenizers.vocabulary import MODALITIES, UnifiedVocabulary, VocabularyConfig

K, D_TOK, GRID = 3, 2, (2, 2)


@pytest.fixture(params=[0, 5], ids=["no-proprio", "proprio"])
def vocab(request):
    return UnifiedVocabulary(VocabularyConfig(50, 16, 12, proprio_codebook_size=request.param))


def make_layout(vocab, interleave=False, goal_tokens=4, proprio_tokens=None):
    if proprio_tokens is None:
        proprio_tokens = 3 if vocab.has("proprio") else 0
    cfg = LayoutConfig(text_tokens=5, obs_tokens=4, goal_tokens=goal_tokens, chunk_size=K,
                       tokens_per_action=D_TOK, proprio_tokens=proprio_tokens, interleave=interleave,
                       image_grid=GRID)
    return SequenceLayout(cfg, vocab)


def random_inputs(layout, batch=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    cfg, vocab = layout.config, layout.vocab

    def codes(modality, *shape):
        start, stop = vocab.range_of(modality)
        return torch.randint(0, stop - start, (batch, *shape), generator=g)

    return dict(
        text_ids=codes("text", cfg.text_tokens),
        obs_ids=codes("image", *GRID),
        goal_ids=codes("image", *GRID) if cfg.goal_tokens else None,
        action_ids=codes("action", K, D_TOK),
        proprio_ids=codes("proprio", cfg.proprio_tokens) if cfg.proprio_tokens else None,
    )


# -- vocabulary ---------------------------------------------------------------
def test_ranges_disjoint_and_cover_every_code(vocab):
    seen = torch.zeros(vocab.size, dtype=torch.long)
    for modality in MODALITIES:
        start, stop = vocab.range_of(modality)
        seen[start:stop] += 1
    assert bool((seen == 1).all())
    assert vocab.range_of("special") == (0, len(vocab.special_tokens))
    assert vocab.pad_id == 0 and vocab.mask_id == 1
    assert vocab.range_of("image")[1] - vocab.range_of("image")[0] == 16


def test_to_global_to_local_round_trip(vocab):
    for modality in ("text", "image", "action") + (("proprio",) if vocab.has("proprio") else ()):
        start, stop = vocab.range_of(modality)
        local = torch.arange(stop - start)
        ids = vocab.to_global(modality, local)
        assert ids.min() == start and ids.max() == stop - 1
        assert torch.equal(vocab.to_local(modality, ids), local)
        assert bool((vocab.modality_of(ids) == MODALITIES.index(modality)).all())
    with pytest.raises(ValueError, match="action ids must lie"):
        vocab.to_local("action", torch.tensor([vocab.range_of("image")[0]]))
    with pytest.raises(ValueError, match="image codes must lie"):
        vocab.to_global("image", torch.tensor([16]))


def test_vocabulary_serialises_and_validates(vocab):
    again = UnifiedVocabulary.from_dict(json.loads(json.dumps(vocab.to_dict())))
    assert again == vocab and again.size == vocab.size
    with pytest.raises(ValueError, match="image_codebook_size"):
        VocabularyConfig(10, 0, 4)
    with pytest.raises(ValueError, match=r"\[PAD\]"):
        VocabularyConfig(10, 4, 4, special_tokens=("[MASK]", "[PAD]"))


def test_allowed_mask_matches_ranges(vocab):
    modality_ids = torch.arange(len(MODALITIES))
    allowed = vocab.allowed_mask(modality_ids)  # (M, V)
    for i, modality in enumerate(MODALITIES):
        start, stop = vocab.range_of(modality)
        assert allowed[i].nonzero().squeeze(-1).tolist() == list(range(start, stop))


# -- layout --------------------------------------------------------------------
@pytest.mark.parametrize("interleave", [False, True])
def test_assemble_split_round_trip(vocab, interleave):
    layout = make_layout(vocab, interleave)
    inputs = random_inputs(layout)
    ids = layout.assemble(**inputs)
    assert ids.shape == (3, layout.length) and ids.dtype == torch.long
    parts = layout.split(ids)
    assert torch.equal(parts["text"], inputs["text_ids"])
    assert torch.equal(parts["obs"], inputs["obs_ids"])
    assert torch.equal(parts["goal"], inputs["goal_ids"])
    assert torch.equal(parts["action"], inputs["action_ids"])
    if inputs["proprio_ids"] is not None:
        assert torch.equal(parts["proprio"], inputs["proprio_ids"])
    else:
        assert "proprio" not in parts
    targets = layout.split_targets(ids[:, layout.target_positions])
    assert torch.equal(targets["action"], inputs["action_ids"])
    assert torch.equal(targets["goal"], inputs["goal_ids"])


@pytest.mark.parametrize("interleave", [False, True])
def test_each_modality_lands_where_the_layout_says(vocab, interleave):
    layout = make_layout(vocab, interleave)
    inputs = random_inputs(layout)
    ids = layout.assemble(**inputs)
    action_start = vocab.range_of("action")[0]
    # action k, token j sits at action_positions[k * d_tok + j]
    for k in range(K):
        for j in range(D_TOK):
            pos = layout.action_positions[k * D_TOK + j]
            assert torch.equal(ids[:, pos], inputs["action_ids"][:, k, j] + action_start)
    goal_flat = inputs["goal_ids"].reshape(3, -1) + vocab.range_of("image")[0]
    assert torch.equal(ids[:, layout.goal_positions], goal_flat)
    # every position's id lies in its modality's range
    low, high = vocab.bounds(layout.modality_ids)
    assert bool(((ids >= low) & (ids < high)).all())
    # separators are fixed special tokens and conditioning
    assert bool((ids[:, layout.is_separator] < vocab.range_of("special")[1]).all())
    assert ids[0, 0] == vocab.token_id("[BOS]")
    assert not bool((layout.is_separator & layout.is_target).any())
    # targets: exactly goal + action positions
    assert layout.num_targets == 4 + K * D_TOK
    assert int(layout.is_target.sum()) == layout.num_targets
    assert layout.is_target[layout.goal_positions].all() and layout.is_target[layout.action_positions].all()
    expected_segments = {SEGMENTS.index("goal"), SEGMENTS.index("action")}
    assert set(layout.segment_ids[layout.is_target].tolist()) == expected_segments
    if interleave:  # goal group k precedes action k
        for k in range(K):
            assert layout.action_positions[k * D_TOK] > layout.goal_positions[k]
        assert "goal" not in layout.spans
    else:
        assert layout.goal_positions.max() < layout.action_positions.min()
        assert layout.spans["action"].stop == layout.length


def test_layout_without_goal_and_masked_targets(vocab):
    layout = make_layout(vocab, goal_tokens=0)
    inputs = random_inputs(layout)
    inputs.pop("goal_ids")
    inputs.pop("action_ids")
    ids = layout.assemble(**inputs)  # targets left as [MASK]
    assert layout.goal_positions.numel() == 0 and not layout.has_goal
    assert bool((ids[:, layout.target_positions] == vocab.mask_id).all())
    with pytest.raises(ValueError, match="action ids must lie"):
        layout.split(ids)


def test_shape_errors_name_expected_and_got(vocab):
    layout = make_layout(vocab)
    inputs = random_inputs(layout)
    inputs["action_ids"] = inputs["action_ids"][:, :2]
    with pytest.raises(ValueError, match=r"action_ids: expected shape \[3, 3, 2\] or \[3, 6\], got \[3, 2, 2\]"):
        layout.assemble(**inputs)
    with pytest.raises(ValueError, match="text_ids: expected"):
        layout.assemble(None, inputs["obs_ids"])
    with pytest.raises(ValueError, match="image_grid"):
        LayoutConfig(5, 4, 9, K, D_TOK, image_grid=(2, 2))
    with pytest.raises(ValueError, match="chunk_size"):
        LayoutConfig(5, 4, 4, 0, D_TOK)


def test_allowed_logit_mask_and_attention_mask(vocab):
    layout = make_layout(vocab, interleave=True)
    allowed = layout.allowed_logit_mask(vocab)  # (L, V)
    assert allowed.shape == (layout.length, vocab.size)
    start, stop = vocab.range_of("action")
    assert allowed[layout.action_positions].sum(-1).eq(stop - start).all()
    assert not allowed[layout.target_positions][:, vocab.mask_id].any()
    free = layout.allowed_logit_mask(restrict_condition=False)
    assert free[layout.is_condition].all() and torch.equal(free[layout.is_target], allowed[layout.is_target])

    mask = layout.attention_mask("block_causal")  # (L, L)
    cond, tgt = layout.is_condition, layout.is_target
    assert mask[tgt].all()
    assert mask[cond][:, cond].all() and not mask[cond][:, tgt].any()
    assert layout.attention_mask("bidirectional") is None


def test_layout_serialises(vocab):
    layout = make_layout(vocab, interleave=True)
    again = SequenceLayout.from_dict(json.loads(json.dumps(layout.to_dict())))
    assert torch.equal(again.segment_ids, layout.segment_ids)
    assert torch.equal(again.action_positions, layout.action_positions)
    with pytest.raises(ValueError, match="no proprio range"):
        SequenceLayout(LayoutConfig(5, 4, 4, K, D_TOK, proprio_tokens=2),
                       UnifiedVocabulary(VocabularyConfig(50, 16, 12)))
