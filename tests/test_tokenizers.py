"""Tokenizers: round trips, EMA codebooks, dead-code restarts, save / load, bad inputs, TensorDict I/O."""
from __future__ import annotations

import json
import warnings

import pytest
import torch
from tensordict import NonTensorData, NonTensorStack, TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.data.vla.tokenizers import ActionTokenizerBase
from vector_quantize_pytorch import VectorQuantize

from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_TOKENS_KEY,
    GOAL_TOKENS_KEY,
    IMAGE_KEY,
    IMAGE_TOKENS_KEY,
    INSTRUCTION_KEY,
    INSTRUCTION_TOKENS_KEY,
)
from mmada_rl.tokenizers import (
    PAD_ID,
    UNK_ID,
    ActionNormalizer,
    ActionOutOfRangeWarning,
    FSQActionTokenizer,
    FSQActionTokenizerConfig,
    TextTokenizer,
    UniformBinActionTokenizer,
    UniformBinActionTokenizerConfig,
    VQActionTokenizer,
    VQActionTokenizerConfig,
    VQImageTokenizer,
    VQImageTokenizerConfig,
    count_dead_code_restarts,
    fit_action_tokenizer,
    fit_image_tokenizer,
    load_tokenizer,
)
from mmada_rl.tokenizers.report import (
    action_reconstruction_report,
    image_reconstruction_report,
    markdown_table,
    save_reconstruction_grid,
)

INSTRUCTIONS = [
    "pick up the red cube and move it to the green goal",
    "Push the cube to the goal region.",
    "lift the red cube",
]


# -- synthetic data -------------------------------------------------------------
def robot_actions(num_episodes: int = 24, steps: int = 60, seed: int = 0) -> torch.Tensor:
    """``pd_ee_delta_pose``-like actions [N, 7]: smooth clipped random walks + a gripper that closes once."""
    g = torch.Generator().manual_seed(seed)
    noise = 0.15 * torch.randn(num_episodes, steps, 6, generator=g)
    v = torch.zeros(num_episodes, 6)
    walk = []
    for t in range(steps):
        v = (0.9 * v + noise[:, t]).clamp(-1, 1)
        walk.append(v)
    walk = torch.stack(walk, 1)  # (E, T, 6)
    close_at = torch.randint(steps // 4, 3 * steps // 4, (num_episodes, 1), generator=g)
    gripper = torch.where(torch.arange(steps)[None] < close_at, 1.0, -1.0)[..., None]  # (E, T, 1)
    return torch.cat([walk, gripper], -1).reshape(-1, 7)


PALETTE = torch.tensor([[0.8, 0.8, 0.75], [0.35, 0.3, 0.25], [0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.2, 0.3, 0.9]])


def scene_images(n: int = 64, size: int = 16, seed: int = 0) -> torch.Tensor:
    """uint8 [n, 3, size, size]: a table-coloured background and two rectangles aligned to 4-pixel cells,
    colours from a small palette (so a 4x4 grid of 32 codes can represent them exactly)."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    images = []
    for _ in range(n):
        img = PALETTE[int(torch.randint(0, 2, (1,), generator=g))][:, None, None].expand(3, size, size)
        for _ in range(2):
            x0, y0 = (4 * torch.randint(0, size // 4, (2,), generator=g)).tolist()
            w, h = (4 * torch.randint(1, 3, (2,), generator=g)).tolist()
            box = (xx >= x0) & (xx < x0 + w) & (yy >= y0) & (yy < y0 + h)
            img = torch.where(box, PALETTE[int(torch.randint(2, 5, (1,), generator=g))][:, None, None], img)
        images.append(img)
    return (torch.stack(images) * 255).round().to(torch.uint8)


def no_information_error(tokenizer, actions: torch.Tensor) -> float:
    """Mean absolute error (normalised units, continuous dims) of always predicting the mean action."""
    normed = tokenizer.normalizer.affine(actions)[:, :6]
    return (normed - normed.mean(0)).abs().mean().item()


TINY_VQ = dict(codebook_size=64, embed_dim=8, tokens_per_action=3, hidden_sizes=(64,), ema_decay=0.8)
TINY_FSQ = dict(levels=(2,) * 8, num_quantizers=3, embed_dim=8, hidden_sizes=(64,))
TINY_IMAGE = dict(image_size=16, grid_size=4, codebook_size=32, hidden_channels=16, embed_dim=8)


def tiny_vq(**overrides) -> VQActionTokenizer:
    return VQActionTokenizer(VQActionTokenizerConfig(**{**TINY_VQ, **overrides}))


@pytest.fixture(scope="module")
def actions() -> torch.Tensor:
    return robot_actions()


@pytest.fixture(scope="module")
def images() -> torch.Tensor:
    return scene_images()


@pytest.fixture(scope="module")
def fitted_vq(actions):
    torch.manual_seed(0)
    tok = tiny_vq()
    result = fit_action_tokenizer(tok, actions, steps=150, batch_size=256, lr=3e-3, progress=False)
    return tok, result


@pytest.fixture(scope="module")
def fitted_fsq(actions):
    torch.manual_seed(0)
    tok = FSQActionTokenizer(FSQActionTokenizerConfig(**TINY_FSQ))
    fit_action_tokenizer(tok, actions, steps=150, batch_size=256, lr=3e-3, progress=False)
    return tok


@pytest.fixture(scope="module")
def fitted_bins(actions):
    tok = UniformBinActionTokenizer()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ActionOutOfRangeWarning)
        fit_action_tokenizer(tok, actions, progress=False)
    return tok


@pytest.fixture(scope="module")
def fitted_image(images):
    torch.manual_seed(0)
    tok = VQImageTokenizer(VQImageTokenizerConfig(**TINY_IMAGE))
    result = fit_image_tokenizer(tok, images, steps=60, batch_size=16, lr=3e-3, progress=False)
    return tok, result


@pytest.fixture(scope="module")
def fitted_text():
    return TextTokenizer().fit(INSTRUCTIONS)


# -- interfaces ---------------------------------------------------------------------
@pytest.mark.parametrize("cls", [VQActionTokenizer, UniformBinActionTokenizer, FSQActionTokenizer])
def test_action_tokenizers_are_torchrl_tokenizers_and_td_modules(cls):
    tok = cls()
    assert isinstance(tok, ActionTokenizerBase) and isinstance(tok, TensorDictModuleBase)
    mro = type(tok).__mro__
    assert mro.index(ActionTokenizerBase) < mro.index(TensorDictModuleBase) < mro.index(torch.nn.Module)
    assert tok.in_keys == [ACTION_CHUNK_KEY] and tok.out_keys == [ACTION_TOKENS_KEY]
    assert tok.vocab_size == 256


def test_default_sizes():
    assert UniformBinActionTokenizer().tokens_per_action == 7
    assert VQActionTokenizer(VQActionTokenizerConfig(tokens_per_action=7)).tokens_per_action == 7
    fsq = FSQActionTokenizer(FSQActionTokenizerConfig(levels=(8, 8, 4), num_quantizers=7))
    assert (fsq.tokens_per_action, fsq.vocab_size) == (7, 256)
    image = VQImageTokenizer()
    assert (image.tokens_per_image, image.vocab_size) == (64, 512)
    assert image.in_keys == [IMAGE_KEY] and image.out_keys == [IMAGE_TOKENS_KEY]


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: VQActionTokenizerConfig(codebook_size=1), "codebook_size"),
        (lambda: VQActionTokenizerConfig(ema_decay=1.5), "ema_decay"),
        (lambda: VQActionTokenizerConfig(tokens_per_action=0), "tokens_per_action"),
        (lambda: VQActionTokenizerConfig(gripper_dims=(9,)), "gripper_dims"),
        (lambda: VQActionTokenizerConfig(low_quantile=0.9, high_quantile=0.1), "low_quantile"),
        (lambda: UniformBinActionTokenizerConfig(clip_to="data_range"), "clip_to"),
        (lambda: FSQActionTokenizerConfig(levels=(1, 4)), "levels"),
        (lambda: VQImageTokenizerConfig(image_size=64, grid_size=5), "grid_size"),
        (lambda: VQImageTokenizerConfig(dead_code_threshold=-1), "dead_code_threshold"),
    ],
)
def test_config_validation_names_the_bad_value(make, field):
    with pytest.raises(ValueError, match=field):
        make()


# -- normalisation ----------------------------------------------------------------------
def test_normalizer_maps_quantiles_and_keeps_gripper_binary():
    data = torch.cat([torch.linspace(-0.5, 0.5, 1001)[:, None].repeat(1, 2), torch.ones(1001, 1)], -1)
    data[::2, 2] = -1
    norm = ActionNormalizer(3, gripper_dims=(2,)).fit(data)
    torch.testing.assert_close(norm.low[:2], torch.full((2,), -0.49))
    torch.testing.assert_close(norm.high[:2], torch.full((2,), 0.49))
    out = norm.normalize(torch.tensor([[0.49, 0.0, 0.3], [-0.49, 0.245, -0.2]]))
    torch.testing.assert_close(out, torch.tensor([[1.0, 0.0, 1.0], [-1.0, 0.5, -1.0]]))
    back = norm.denormalize(out)
    torch.testing.assert_close(back, torch.tensor([[0.49, 0.0, 1.0], [-0.49, 0.245, -1.0]]))


def test_out_of_range_actions_are_clipped_counted_and_warned(fitted_bins):
    norm = fitted_bins.normalizer
    norm.reset_out_of_range()
    inside = (norm.low + norm.high) / 2
    bad = inside.repeat(3, 1)
    bad[0, 1] = norm.high[1] + 0.3  # above, dim 1
    bad[1, 1] = norm.low[1] - 0.3  # below, dim 1
    bad[1, 4] = norm.high[4] + 1.0  # and dim 4 in the same action
    with pytest.warns(ActionOutOfRangeWarning, match=r"2 of 3 actions.*\{1: 2, 4: 1\}"):
        tokens = fitted_bins.encode(bad)
    assert norm.num_out_of_range == 2 and norm.num_actions_seen == 3
    assert norm.out_of_range_per_dim.tolist() == [0, 2, 0, 0, 1, 0, 0]
    # clipped to the edge bins, never wrapped
    assert tokens[0, 1] == 255 and tokens[1, 1] == 0 and tokens[1, 4] == 255
    with pytest.warns(ActionOutOfRangeWarning, match="Running total: 3"):
        fitted_bins.encode(bad[:1])
    assert norm.num_out_of_range == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fitted_bins.encode(inside)  # in range: silent


def test_data_range_mode_does_not_clip_training_actions(fitted_vq, actions):
    tok, _ = fitted_vq
    tok.normalizer.reset_out_of_range()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tok.encode(actions)
    assert tok.normalizer.num_out_of_range == 0
    with pytest.warns(ActionOutOfRangeWarning, match=r"\{0: 1\}"):
        tok.encode(torch.tensor([[5.0, 0, 0, 0, 0, 0, 1]]))


@pytest.mark.parametrize("which", ["bins", "vq"])
def test_bad_actions_raise_one_clear_error(which, fitted_bins, fitted_vq):
    tok = fitted_bins if which == "bins" else fitted_vq[0]
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 7\]"):
        tok.encode(torch.zeros(4, 6))
    nan = torch.zeros(4, 7)
    nan[2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"NaN or inf values in dimensions \[3\]"):
        tok.encode(nan)
    inf = torch.zeros(4, 7)
    inf[0, 0] = float("inf")
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_action_tokenizer(UniformBinActionTokenizer(), inf, progress=False)
    with pytest.raises(ValueError, match="tokens must lie in"):
        tok.decode(torch.full((2, tok.tokens_per_action), tok.vocab_size))
    with pytest.raises(ValueError, match="tokens must have shape"):
        tok.decode(torch.zeros(2, tok.tokens_per_action + 1, dtype=torch.long))


def test_unfitted_tokenizer_says_so():
    with pytest.raises(RuntimeError, match="not fitted"):
        UniformBinActionTokenizer().encode(torch.zeros(2, 7))
    tok = tiny_vq()
    tok.normalizer.fit(robot_actions(2, 10))
    with pytest.raises(RuntimeError, match="fit_action_tokenizer"):
        tok.encode(torch.zeros(2, 7))


# -- round trips ------------------------------------------------------------------------
def test_uniform_bins_round_trip_within_half_a_bin(fitted_bins, actions):
    norm = fitted_bins.normalizer
    inside = actions[((actions >= norm.low) & (actions <= norm.high)).all(-1)]
    assert inside.shape[0] > 100
    rec = fitted_bins.decode(fitted_bins.encode(inside))
    half_bin_env = (norm.high - norm.low) / 2 * fitted_bins.half_bin_width  # normalised -> env units
    err = (rec - inside).abs()
    assert (err[:, :6] <= half_bin_env[:6] + 1e-6).all()
    assert torch.equal(rec[:, 6], inside[:, 6])


def test_mean_readout_of_bin_distributions(fitted_bins, fitted_vq, fitted_fsq, actions):
    """``decode_mean``: a one-hot distribution reads its bin's centre, a split one the weighted mean of the
    centres; grippers follow the sign of their mean; codes without an order have none."""
    tok, norm = fitted_bins, fitted_bins.normalizer
    tokens = tok.encode(actions[:6].clamp(norm.low, norm.high))  # (6, 7)
    onehot = torch.nn.functional.one_hot(tokens, tok.vocab_size).float()
    assert torch.equal(tok.decode_mean(onehot), tok.decode(tokens))
    low_bin, high_bin = torch.full((1, 7), 10), torch.full((1, 7), 13)
    split = 0.25 * torch.nn.functional.one_hot(low_bin, 256).float() + 0.75 * torch.nn.functional.one_hot(high_bin, 256).float()
    expected = 0.25 * tok.decode(low_bin) + 0.75 * tok.decode(high_bin)
    torch.testing.assert_close(tok.decode_mean(split)[:, :6], expected[:, :6])
    gripper = torch.zeros(1, 7, 256)
    gripper[..., 0], gripper[0, 6, 0], gripper[0, 6, 255] = 1.0, 0.3, 0.7  # most mass on "open" (+1)
    assert tok.decode_mean(gripper)[0, 6] == 1.0
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 7, 256\]"):
        tok.decode_mean(torch.ones(2, 7, 255) / 255)
    for unordered in (fitted_vq[0], fitted_fsq):
        probs = torch.ones(1, unordered.tokens_per_action, unordered.vocab_size) / unordered.vocab_size
        with pytest.raises(ValueError, match="the mean read-out averages each token's bin centres, so it needs ordered bin tokens"):
            unordered.decode_mean(probs)


@pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.normalize.ActionOutOfRangeWarning")
def test_vq_round_trip_after_short_fit(fitted_vq):
    tok, result = fitted_vq
    test = robot_actions(8, 60, seed=1)
    tokens = tok.encode(test)
    assert tokens.dtype == torch.long and tokens.shape == (test.shape[0], 3)
    assert 0 <= tokens.min() and tokens.max() < 64
    rec = tok.decode(tokens)
    assert set(rec[:, 6].unique().tolist()) <= {-1.0, 1.0}
    report = action_reconstruction_report(tok, test)["summary"]
    assert report["mae_normalized"] < 0.35 * no_information_error(tok, test), report
    assert report["mae_normalized"] < 0.12, report
    assert report["gripper_sign_agreement"] > 0.99
    assert result.losses[-1] < 0.3 * result.losses[0]
    # nested batch shapes round-trip too
    assert tok.decode(tok.encode(test[:12].reshape(3, 4, 7))).shape == (3, 4, 7)
    # encoding never moves the codebook, even in train mode
    codebooks = tok.codebooks.clone()
    tok.train()
    tok.encode(test)
    tok.eval()
    assert torch.equal(codebooks, tok.codebooks)


@pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.normalize.ActionOutOfRangeWarning")
def test_fsq_round_trip_after_short_fit(fitted_fsq):
    test = robot_actions(8, 60, seed=1)
    tokens = fitted_fsq.encode(test)
    assert tokens.dtype == torch.long and tokens.max() < fitted_fsq.vocab_size == 256
    report = action_reconstruction_report(fitted_fsq, test)["summary"]
    assert report["mae_normalized"] < 0.4 * no_information_error(fitted_fsq, test), report
    assert report["gripper_sign_agreement"] > 0.99


def test_fit_is_deterministic_under_a_seed(actions):
    runs = []
    for _ in range(2):
        torch.manual_seed(3)
        tok = tiny_vq()
        result = fit_action_tokenizer(tok, actions, steps=5, batch_size=64, seed=7, progress=False)
        runs.append((result.losses, tok.encode(actions[:50])))
    assert runs[0][0] == runs[1][0]
    assert torch.equal(runs[0][1], runs[1][1])


# -- EMA codebook and dead codes -----------------------------------------------------------
def test_ema_updates_move_the_codebook_toward_the_data():
    torch.manual_seed(0)
    tok = tiny_vq(kmeans_init=False, dead_code_threshold=0.0)
    quantizer = tok.quantizer.train()
    data = 0.2 * torch.randn(512, 1, 8) + 3.0  # latents far from the initial codes

    def distance_to_codes() -> float:
        codes = quantizer.codebooks[0]  # (C, d_e)
        return torch.cdist(data[:, 0], codes).min(-1).values.mean().item()

    before = distance_to_codes()
    with torch.no_grad():
        for _ in range(5):
            quantizer(data)
    after = distance_to_codes()
    assert after < 0.2 * before, (before, after)


def test_dead_codes_are_restarted_and_counted(actions):
    torch.manual_seed(0)
    tok = tiny_vq(dead_code_threshold=0.5)
    fit_action_tokenizer(tok, actions, steps=5, batch_size=256, progress=False)
    codebook = tok.quantizer.layers[0]._codebook
    dead = torch.arange(8)
    with torch.no_grad():  # codes no input is near, and no usage
        codebook.embed[0, dead] = 1e3
        codebook.embed_avg[0, dead] = 0.0
        codebook.cluster_size[0, dead] = 0.0
    result = fit_action_tokenizer(tok, actions, steps=2, batch_size=256, progress=False)
    assert result.dead_codes_per_codebook[0] >= 8
    assert result.dead_codes_restarted == sum(result.dead_codes_per_codebook)
    restarted = tok.quantizer.codebooks[0, dead]  # (8, d_e), now data vectors
    latents = tok.encoder(tok.normalizer.normalize(actions))
    assert restarted.abs().max() < latents.abs().max() + 1e-4
    assert (tok.quantizer.layers[0]._codebook.cluster_size[0, dead] > 0).all()


def test_count_dead_code_restarts_on_a_plain_vector_quantizer():
    torch.manual_seed(0)
    vq = VectorQuantize(dim=4, codebook_size=64, threshold_ema_dead_code=2)
    with count_dead_code_restarts(vq) as counts:
        vq(torch.randn(1, 16, 4))
    assert counts[0] > 0
    assert "expire_codes_" not in vars(vq._codebook)  # wrapper removed


# -- images --------------------------------------------------------------------------
def test_image_round_trip_after_short_fit(fitted_image, images):
    tok, result = fitted_image
    tokens = tok.encode(images[:5])
    assert tokens.shape == (5, 4, 4) and tokens.dtype == torch.long
    decoded = tok.decode(tokens)
    assert decoded.dtype == torch.uint8 and decoded.shape == (5, 3, 16, 16)
    report = image_reconstruction_report(tok, scene_images(16, seed=1))["summary"]
    assert report["psnr_db"] > 15.0, report
    assert result.losses[-1] < 0.6 * result.losses[0]
    assert tok.encode(images[:6].reshape(2, 3, 3, 16, 16)).shape == (2, 3, 4, 4)


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.zeros(2, 3, 32, 32, dtype=torch.uint8), "16x16"),
        (torch.zeros(2, 4, 16, 16, dtype=torch.uint8), "3 channels"),
        (torch.zeros(2, 3, 16, 16), "uint8"),
    ],
)
def test_bad_images_raise_one_clear_error(fitted_image, bad, match):
    with pytest.raises(ValueError, match=match):
        fitted_image[0].encode(bad)


def test_image_report_and_grid(fitted_image, images, tmp_path):
    tok, result = fitted_image
    path = save_reconstruction_grid(tok, images, tmp_path / "grid.png", num_images=4)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = image_reconstruction_report(tok, images)["summary"]
    assert 0 < summary["code_usage"] <= 1 and 1 <= summary["code_perplexity"] <= 32
    assert result.seconds_per_step > 0 and result.steps == 60
    json.dumps(summary)
    assert markdown_table([summary]).count("\n") == 3


def small_object_images(n: int = 256, size: int = 16, seed: int = 0) -> torch.Tensor:
    """uint8 [n, 3, size, size]: a fixed textured table and one red pixel at a random place (PickCube's cube is
    about 4 of 4096 pixels at 64x64)."""
    g = torch.Generator().manual_seed(seed)
    table = PALETTE[1][:, None, None] + 0.05 * torch.rand(3, size, size, generator=g)  # the same texture in every frame
    images = table.expand(n, 3, size, size).clone()
    where = torch.randint(0, size, (n, 2), generator=g)
    images[torch.arange(n), :, where[:, 0], where[:, 1]] = PALETTE[2]
    return (images.clamp(0, 1) * 255).round().to(torch.uint8)


def test_foreground_weight_keeps_a_small_object_that_plain_mse_loses(tmp_path):
    images = small_object_images()
    fg = {}
    for weight in (1.0, 50.0):
        torch.manual_seed(0)
        tok = VQImageTokenizer(VQImageTokenizerConfig(**{**TINY_IMAGE, "foreground_weight": weight}))
        fit_image_tokenizer(tok, images, steps=300, batch_size=32, lr=3e-3, progress=False)
        fg[weight] = image_reconstruction_report(tok, small_object_images(64, seed=1))["summary"]
    # the background is the per-pixel median of the training frames: the table, without the red pixel
    torch.testing.assert_close(tok.background, images.float().median(0).values)
    assert fg[1.0]["foreground_fraction"] == pytest.approx(1 / 256)  # one pixel in 16x16 differs from the median
    # plain MSE spends the codes on the table's texture and decodes the red pixel as table (~9 dB there); weighted,
    # the codes keep it (~26 dB)
    assert fg[50.0]["psnr_foreground_db"] > fg[1.0]["psnr_foreground_db"] + 10.0, fg
    # the fitted background is part of the saved tokenizer
    tok.save(tmp_path / "image")
    loaded = load_tokenizer(tmp_path / "image")
    torch.testing.assert_close(loaded.background, tok.background)
    torch.testing.assert_close(loaded.encode(images[:8]), tok.encode(images[:8]))
    with pytest.raises(ValueError, match="foreground_weight must be >= 1"):
        VQImageTokenizerConfig(foreground_weight=0.5)


# -- text ----------------------------------------------------------------------------------
def test_text_round_trip(fitted_text):
    enc = fitted_text.encode(INSTRUCTIONS)
    assert enc.ids.shape == (3, 16) and enc.ids.dtype == torch.long
    assert enc.attention_mask.sum(-1).tolist() == [12, 8, 4]
    assert (enc.ids[~enc.attention_mask] == PAD_ID).all()
    assert fitted_text.decode(enc.ids) == [s.lower() for s in INSTRUCTIONS]
    unknown = fitted_text.encode(["pick up the blue cube"])
    assert unknown.ids[0, 3] == UNK_ID
    assert fitted_text.decode(unknown.ids) == ["pick up the [UNK] cube"]
    assert fitted_text.vocabulary[:2] == ("[PAD]", "[UNK]")


def test_text_rejects_empty_and_too_long_instructions(fitted_text):
    with pytest.raises(ValueError, match="empty instruction"):
        fitted_text.encode(["pick up the cube", "   "])
    with pytest.raises(ValueError, match="max_len=16"):
        fitted_text.encode([" ".join(["cube"] * 17)])


# -- TensorDict I/O -------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.normalize.ActionOutOfRangeWarning")
def test_td_forward_writes_the_declared_out_keys(fitted_vq, fitted_bins, fitted_image, fitted_text, actions, images):
    vq, _ = fitted_vq
    td = TensorDict({ACTION_CHUNK_KEY: actions[:20].reshape(4, 5, 7)}, batch_size=[4])
    for tok in (vq, fitted_bins):
        out = tok(td.clone())
        assert out.get(tok.out_keys[0]).shape == (4, 5, tok.tokens_per_action)
        assert torch.equal(out.get(ACTION_TOKENS_KEY), tok.encode(actions[:20]).reshape(4, 5, -1))

    goal = VQImageTokenizer(fitted_image[0].config, in_keys=[("goal", "image")], out_keys=[GOAL_TOKENS_KEY])
    goal.load_state_dict(fitted_image[0].state_dict())
    td = TensorDict({IMAGE_KEY: images[:4], ("goal", "image"): images[4:8]}, batch_size=[4])
    td = goal(fitted_image[0](td))
    assert td.get(IMAGE_TOKENS_KEY).shape == (4, 4, 4)
    assert torch.equal(td.get(GOAL_TOKENS_KEY), fitted_image[0].encode(images[4:8]))

    stack = NonTensorStack(*[NonTensorData(s) for s in INSTRUCTIONS])
    td = fitted_text(TensorDict({INSTRUCTION_KEY: stack}, batch_size=[3]))
    assert torch.equal(td.get(INSTRUCTION_TOKENS_KEY), fitted_text.encode(INSTRUCTIONS).ids)
    shared = TensorDict(batch_size=[2])
    shared.set_non_tensor(INSTRUCTION_KEY, INSTRUCTIONS[0])
    assert fitted_text(shared).get(INSTRUCTION_TOKENS_KEY).shape == (2, 16)


# -- save / load -------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["vq", "bins", "fsq", "image", "text"])
def test_save_load_gives_identical_outputs(which, request, tmp_path, actions, images):
    fixture = {"vq": "fitted_vq", "bins": "fitted_bins", "fsq": "fitted_fsq", "image": "fitted_image", "text": "fitted_text"}
    tok = request.getfixturevalue(fixture[which])
    tok = tok[0] if isinstance(tok, tuple) else tok
    inputs = {"image": images[:8], "text": INSTRUCTIONS}.get(which, actions[:100])
    tok.save(tmp_path)
    payload = json.loads((tmp_path / "config.json").read_text())
    assert payload["type"] == type(tok).__name__ and (tmp_path / "model.safetensors").is_file()
    loaded = load_tokenizer(tmp_path)
    assert type(loaded) is type(tok) and loaded.config == tok.config
    assert loaded.in_keys == tok.in_keys and loaded.out_keys == tok.out_keys
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ActionOutOfRangeWarning)
        before, after = tok.encode(inputs), loaded.encode(inputs)
    if which == "text":
        assert torch.equal(before.ids, after.ids)
        assert loaded.decode(after.ids) == tok.decode(before.ids)
    else:
        assert torch.equal(before, after)
        assert torch.equal(tok.decode(before), loaded.decode(after))
    if which in ("vq", "bins", "fsq"):
        assert payload["normalizer"]["low"] == tok.normalizer.low.tolist()
        assert type(tok).load(tmp_path).config == tok.config
    with pytest.raises(ValueError, match="holds a"):
        (TextTokenizer if which != "text" else VQImageTokenizer).load(tmp_path)


def test_action_report_is_json_ready(fitted_bins, actions):
    report = action_reconstruction_report(fitted_bins, actions)
    summary = report["summary"]
    assert summary["tokens_per_action"] == 7 and 0 < summary["clipped_fraction"] < 0.2
    assert summary["mae_m"] == pytest.approx(
        sum(r["mae_env"] for r in report["per_dim"][:3]) / 3
    ) and summary["mae_m"] < 0.002
    assert report["per_dim"][6] == {"dim": 6, "unit": "gripper", "sign_agreement": 1.0}
    assert len(report["codebook"]["perplexity"]) == 7
    json.dumps(report)
