"""Imitation baselines: BC (TorchRL BCLoss) and Diffusion Policy (TorchRL DiffusionBCLoss), their recipe and evaluation."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mmada_rl.baselines import (
    ALGOS,
    ChunkDiffusionBCLoss,
    DiffusionPolicyConfig,
    EncoderConfig,
    NormalizationStats,
    ObservationEncoder,
    RandomShift,
    is_policy_dir,
    load_policy,
    make_bc_loss,
    make_loss,
    make_policy,
)
from mmada_rl.data import StateDropout
from mmada_rl.evaluation import evaluate, load_actor, resolve_model_dir
from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_IS_PAD_KEY, ACTION_KEY, IMAGE_KEY, STATE_KEY
from mmada_rl.training import WeightEMA, autocast, optimizer_step
from recipe_runs import run_in_one_process

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "baselines" / "imitation.py"
K, A, S = 4, 7, 29
TINY = {"chunk_size": K, "action_dim": A, "state_dim": S, "image_size": 64,
        "encoder": {"channels": [8, 16, 16, 16], "image_features": 32, "state_features": 16}}
TINY_HEADS = {"bc": {"hidden_sizes": [64]},
              "diffusion_policy": {"num_train_steps": 50, "num_inference_steps": 5, "hidden_size": 64, "num_blocks": 2,
                                   "time_embed_dim": 16}}
STATS = NormalizationStats(
    action_min=torch.tensor([-0.2, -0.3, -0.3, -0.1, -0.2, -1.0, -1.0]),
    action_max=torch.tensor([0.2, 0.3, 0.4, 0.1, 0.2, 1.0, 1.0]),
    state_mean=torch.zeros(S),
    state_std=torch.ones(S),
)


def tiny_policy(algo: str, seed: int = 0, **kwargs):
    torch.manual_seed(seed)
    return make_policy(algo, {**TINY, **TINY_HEADS[algo]}, STATS, **kwargs)


def window_batch(batch: int = 8, seed: int = 0) -> TensorDict:
    """A fixed batch shaped like make_window_buffer's: the last two windows run past their episode's end."""
    gen = torch.Generator().manual_seed(seed)
    pad = torch.zeros(batch, K, dtype=torch.bool)
    pad[-2:, 2:] = True
    low, high = STATS.action_min, STATS.action_max
    return TensorDict({
        IMAGE_KEY: torch.randint(0, 256, (batch, 3, 64, 64), dtype=torch.uint8, generator=gen),
        STATE_KEY: torch.randn(batch, S, generator=gen),
        ACTION_CHUNK_KEY: low + (high - low) * torch.rand(batch, K, A, generator=gen),
        ACTION_IS_PAD_KEY: pad,
    }, batch_size=[batch])  # fmt: skip


# -- the actor contract ------------------------------------------------------------
@pytest.mark.parametrize("algo", sorted(ALGOS))
@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_policy_writes_the_chunk_and_its_first_actions(algo, batch):
    policy = tiny_policy(algo, execute_steps=2)
    assert policy.in_keys == [IMAGE_KEY, STATE_KEY]  # single-task: no instruction
    assert policy.out_keys == [ACTION_CHUNK_KEY, ACTION_KEY]
    td = TensorDict({IMAGE_KEY: torch.zeros(*batch, 3, 64, 64, dtype=torch.uint8), STATE_KEY: torch.zeros(*batch, S)}, batch_size=batch)
    out = policy(td)
    assert out.get(ACTION_CHUNK_KEY).shape == (*batch, K, A)
    assert out.get(ACTION_KEY).shape == (*batch, 2, A)
    torch.testing.assert_close(out.get(ACTION_KEY), out.get(ACTION_CHUNK_KEY)[..., :2, :])
    assert policy.last_decode_seconds > 0
    assert policy.get_new_version(execute_steps=K).execute_steps == K and policy.execute_steps == 2
    with pytest.raises(ValueError, match=r"execute_steps must be an int in \[1, chunk_size=4\]"):
        policy.get_new_version(execute_steps=K + 1)


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_saved_policy_describes_itself_and_reloads(algo, tmp_path):
    policy = tiny_policy(algo)
    policy.save(tmp_path / "model")
    assert is_policy_dir(tmp_path / "model") and resolve_model_dir(tmp_path) == tmp_path / "model"
    payload = json.loads((tmp_path / "model" / "policy.json").read_text())
    assert payload["kind"] == algo and payload["config"]["chunk_size"] == K
    loaded = load_policy(tmp_path / "model")
    assert type(loaded) is type(policy) and loaded.config == policy.config
    torch.testing.assert_close(loaded.normalizer.half_range, policy.normalizer.half_range)  # statistics travel with the weights
    td = window_batch(2).select(IMAGE_KEY, STATE_KEY)
    torch.testing.assert_close(loaded(td.clone()).get(ACTION_CHUNK_KEY), policy(td.clone()).get(ACTION_CHUNK_KEY))


def test_bad_configs_fail_with_a_sentence():
    with pytest.raises(ValueError, match="image_size=60 is not a multiple of 2\\*\\*len\\(channels\\)=16"):
        make_policy("bc", {**TINY, "image_size": 60})
    with pytest.raises(ValueError, match="num_inference_steps <= num_train_steps"):
        DiffusionPolicyConfig(num_train_steps=10, num_inference_steps=20)
    with pytest.raises(ValueError, match="pool must be one of"):
        EncoderConfig(pool="mean")
    with pytest.raises(ValueError, match="unknown baseline 'ppo'"):
        make_policy("ppo", TINY)
    with pytest.raises(ValueError, match="num_denoise_steps=3 does not apply"):
        tiny_policy("bc").get_new_version(num_denoise_steps=3)
    with pytest.raises(ValueError, match="num_inference_steps must lie in \\[1, num_steps=50\\]"):
        tiny_policy("diffusion_policy").get_new_version(num_denoise_steps=51)


# -- losses ---------------------------------------------------------------------------
def test_bc_loss_is_torchrl_bcloss_and_ignores_padded_steps():
    policy = tiny_policy("bc")
    loss = make_bc_loss(policy)
    batch = window_batch()
    value = loss(batch.clone())["loss_bc"]
    # the mean L1 error, in normalised units, over the unpadded elements only
    with torch.no_grad():
        pred = policy.normalizer.normalize(policy(batch.clone()).get(ACTION_CHUNK_KEY))
    target = policy.normalizer.normalize(batch.get(ACTION_CHUNK_KEY))
    keep = ~batch.get(ACTION_IS_PAD_KEY)
    torch.testing.assert_close(value.detach(), (pred - target).abs()[keep].mean())
    changed = batch.clone()
    changed.get(ACTION_CHUNK_KEY)[changed.get(ACTION_IS_PAD_KEY)] += 100.0  # padded targets only
    assert loss(changed)["loss_bc"].item() == pytest.approx(value.item(), rel=1e-6)
    changed.get(ACTION_CHUNK_KEY)[0, 0] += 1.0  # a real step
    assert loss(changed)["loss_bc"].item() > value.item() + 1e-3
    assert batch.get(ACTION_CHUNK_KEY).equal(window_batch().get(ACTION_CHUNK_KEY))  # the loss leaves its input alone


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_loss_falls_on_a_fixed_batch_and_trains_the_encoder(algo):
    policy = tiny_policy(algo)
    loss = make_loss(policy)
    assert isinstance(loss, ChunkDiffusionBCLoss if algo == "diffusion_policy" else type(make_bc_loss(policy)))
    key = "loss_diffusion_bc" if algo == "diffusion_policy" else "loss_bc"
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    conv = policy.encoder.cnn[0].weight.detach().clone()
    batch, history = window_batch(), []
    torch.manual_seed(0)
    for _ in range(80):  # the diffusion loss draws new timesteps and noise at every step: average over 10
        value = loss(batch)[key]
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        history.append(value.item())
    first, last = sum(history[:10]) / 10, sum(history[-10:]) / 10
    assert last < 0.6 * first, history
    assert not torch.equal(conv, policy.encoder.cnn[0].weight)  # gradients reach the image encoder


def test_diffusion_sampler_stays_in_the_demonstrated_range():
    policy = tiny_policy("diffusion_policy")
    assert policy.module.alphas_cumprod[-1] < 1e-3  # the last training step is (almost) pure noise
    assert policy.module.inference_timesteps(5) == [49, 37, 24, 12, 0]
    td = window_batch(16).select(IMAGE_KEY, STATE_KEY)
    low, high = STATS.action_min - 1e-5, STATS.action_max + 1e-5
    greedy = policy(td.clone()).get(ACTION_CHUNK_KEY)
    assert ((greedy >= low) & (greedy <= high)).all()
    torch.testing.assert_close(policy(td.clone()).get(ACTION_CHUNK_KEY), greedy)  # deterministic by default
    with set_exploration_type(ExplorationType.RANDOM):
        a = policy(td.clone(), generator=torch.Generator().manual_seed(1)).get(ACTION_CHUNK_KEY)
        b = policy(td.clone(), generator=torch.Generator().manual_seed(1)).get(ACTION_CHUNK_KEY)
        c = policy.get_new_version(num_denoise_steps=2)(td.clone()).get(ACTION_CHUNK_KEY)
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a, greedy)
    for chunk in (a, c):
        assert ((chunk >= low) & (chunk <= high)).all()


@pytest.mark.parametrize("pool", ["spatial_softmax", "flatten"])
def test_encoder_pools_to_one_feature_vector(pool):
    encoder = ObservationEncoder(EncoderConfig(channels=(8, 16), pool=pool, num_keypoints=4, image_features=12, state_features=5),
                                 image_size=64, state_dim=S)
    batch = window_batch(3)
    assert encoder(batch.get(IMAGE_KEY), batch.get(STATE_KEY)).shape == (3, 17)
    if pool == "spatial_softmax":
        keypoints = encoder.cnn[-4](encoder.cnn[:-4](batch.get(IMAGE_KEY).float()))  # (B, 2 * 4) expected x-y
        assert keypoints.shape == (3, 8) and keypoints.abs().max() <= 1.0


def test_dropped_state_dims_are_not_read():
    config = EncoderConfig(channels=(8,), image_features=4, state_features=6, num_keypoints=2, drop_state_dims=[12, 9, 9])
    assert config.drop_state_dims == (9, 12)
    encoder = ObservationEncoder(config, image_size=None, state_dim=S)
    assert encoder.state_mlp[0].in_features == S - 2 and encoder.out_features == 6
    state = torch.randn(4, S)
    changed = state.clone()
    changed[:, [9, 12]] += 100.0
    torch.testing.assert_close(encoder(None, changed), encoder(None, state))  # what it does not read cannot move it
    changed[:, 10] += 1.0
    assert not torch.allclose(encoder(None, changed), encoder(None, state))
    with pytest.raises(ValueError, match=r"drop_state_dims=\[29\] must name some, not all"):
        ObservationEncoder(EncoderConfig(drop_state_dims=[29]), image_size=None, state_dim=S)
    with pytest.raises(ValueError, match="not all"):
        ObservationEncoder(EncoderConfig(drop_state_dims=range(S)), image_size=None, state_dim=S)


def test_random_shift_moves_images_by_at_most_pad_pixels():
    torch.manual_seed(0)
    image = torch.zeros(4, 3, 16, 16, dtype=torch.uint8)
    image[:, :, 8, 8] = 255
    shifted = RandomShift(2)(TensorDict({IMAGE_KEY: image.clone()}, [4])).get(IMAGE_KEY)
    assert shifted.dtype == torch.uint8 and shifted.shape == image.shape
    for img in shifted:
        ys, xs = torch.nonzero(img[0], as_tuple=True)
        assert len(ys) == 1 and abs(int(ys) - 8) <= 2 and abs(int(xs) - 8) <= 2


# -- the moving average of the weights (Diffusion Policy's EMA) ---------------------------
def test_weight_ema_follows_diffusion_policys_schedule_and_swaps_weights_in_and_out():
    module = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))  # an int64 buffer: num_batches_tracked
    ema = WeightEMA(module, power=0.75, max_decay=0.9)
    assert [ema.decay(n) for n in (1, 2, 32)] == [0.0, pytest.approx(1 - 2 ** -0.75), 0.9]  # warm-up, then the cap
    weight, values = module[0].weight, [1.0, 3.0, 5.0]
    expected = None
    for n, value in enumerate(values, start=1):
        with torch.no_grad():
            weight.fill_(value)
        module[1].num_batches_tracked.fill_(n)
        ema.update()
        d = ema.decay(n)
        expected = value if expected is None else d * expected + (1 - d) * value  # first update: a copy
    assert ema.updates == 3
    torch.testing.assert_close(ema.shadow["0.weight"], torch.full((2, 2), expected))
    assert 1.0 < expected < 5.0 and int(ema.shadow["1.num_batches_tracked"]) == 3  # averaged floats, copied counters
    with ema.applied():
        torch.testing.assert_close(module[0].weight, torch.full((2, 2), expected))
    torch.testing.assert_close(module[0].weight, torch.full((2, 2), 5.0))  # the trained weights come back
    with pytest.raises(RuntimeError, match="boom"), ema.applied():
        raise RuntimeError("boom")
    torch.testing.assert_close(module[0].weight, torch.full((2, 2), 5.0))  # even after an error
    with pytest.raises(ValueError, match="max_decay"):
        WeightEMA(module, max_decay=1.0)


def test_optimizer_step_sums_the_loss_entries_clips_and_reports_the_step():
    torch.manual_seed(0)
    layer = torch.nn.Linear(3, 1)
    x = torch.randn(8, 3)
    before = {k: v.detach().clone() for k, v in layer.named_parameters()}

    def outputs() -> dict:
        y = layer(x).squeeze(-1)
        return {"loss_a": (y**2).mean(), "loss_b": 3 * y.mean(), "accuracy": torch.tensor(0.25)}  # accuracy: not a loss

    expected = torch.autograd.grad(outputs()["loss_a"] + outputs()["loss_b"], list(layer.parameters()))
    norm = torch.cat([g.reshape(-1) for g in expected]).norm()
    optimizer = torch.optim.SGD(layer.parameters(), lr=1.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0 if step == 0 else 0.5)
    ema = WeightEMA(layer, max_decay=0.9)
    clip = float(norm) / 4  # the step is the gradient scaled down to norm `clip`
    scalars = optimizer_step(outputs(), layer.parameters(), optimizer, grad_clip=clip, scheduler=scheduler, ema=ema)
    assert scalars["grad_norm"] == pytest.approx(float(norm), rel=1e-5)  # reported before clipping
    assert scalars["accuracy"] == 0.25 and scalars["lr"] == 0.5 and scalars["ema_decay"] == 0.0 and ema.updates == 1
    assert scalars["loss"] == pytest.approx(scalars["loss_a"] + scalars["loss_b"])
    for (name, param), grad in zip(layer.named_parameters(), expected):  # SGD at lr 1 for this step (the factor: next)
        torch.testing.assert_close(param.detach(), before[name] - grad * clip / norm, rtol=1e-4, atol=1e-6)
    assert "lr" not in optimizer_step(outputs(), layer.parameters(), optimizer, grad_clip=1.0)
    with pytest.raises(ValueError, match="no loss_"):
        optimizer_step({"accuracy": torch.tensor(1.0)}, layer.parameters(), optimizer, grad_clip=1.0)



def test_autocast_runs_the_forward_pass_in_bfloat16_and_keeps_float32_weights_and_gradients():
    """``optim.precision``: ``fp32`` changes nothing; ``bf16`` computes the layer in bfloat16 (close to float32)
    while the parameters and their gradients stay float32, so AdamW and the saved weights are untouched."""
    torch.manual_seed(0)
    layer = torch.nn.Linear(64, 32)
    x = torch.randn(16, 64)
    with autocast("fp32"):
        exact = layer(x)
    assert exact.dtype == torch.float32
    torch.testing.assert_close(exact, layer(x), rtol=0, atol=0)
    with autocast("bf16", "cpu"):
        low = layer(x)
    assert low.dtype == torch.bfloat16
    torch.testing.assert_close(low.float(), exact, rtol=0.02, atol=0.05)  # bfloat16 keeps ~3 significant digits
    low.float().square().mean().backward()
    assert layer.weight.dtype == layer.weight.grad.dtype == torch.float32
    assert torch.isfinite(layer.weight.grad).all() and layer.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="precision must be one of fp32, bf16, got 'fp16'"):
        autocast("fp16")

# -- the recipe, as users run it --------------------------------------------------------
def run_recipe(*overrides, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(RECIPE), *map(str, overrides)], cwd=REPO, capture_output=True, text=True, timeout=timeout)


def common(run_dir, demos) -> list[str]:
    return [f"run_dir={run_dir}", f"data.dir={demos}", "data.collect_episodes=0", "optim.total_steps=4", "checkpoint.interval=2",
            "checkpoint.keep=5", "logger.log_interval=1", "num_threads=1"]


@pytest.fixture(scope="module")
def toy_runs(pick_demos, tmp_path_factory) -> dict[str, Path]:
    """Four toy steps of each algo, all in one process: checkpoints at 2 and 4, a one-episode evaluation at the end."""
    runs = {algo: tmp_path_factory.mktemp(algo) / "run" for algo in sorted(ALGOS)}
    done = run_in_one_process(RECIPE, [[f"algo={algo}", *common(run_dir, pick_demos), "eval.episodes=1",
                                        "eval.max_episode_steps=6"] for algo, run_dir in runs.items()])
    for proc in done:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return runs


def test_demo_fit_sets_the_baselines_chunks_beside_the_policys(toy_runs, toy_pretrain_run, pick_demos, tmp_path):
    """``benchmarks/demo_fit.py`` with a BC / Diffusion Policy run: its chunk error on the same windows
    (no token accuracies: a baseline has no tokens), beside a masked-diffusion policy's."""
    from script_loader import load_script

    bench = load_script("benchmarks/demo_fit.py", "demo_fit")
    runs = [f"{toy_runs['bc']}=PickCube-v1", f"{toy_pretrain_run}=PickCube-v1"]
    args = [*(a for r in runs for a in ("--run", r)), "--demos", str(pick_demos), "--ratios", "1.0",
            "--minibatches", "1", "--batch-size", "2", "--decode-minibatches", "2"]
    assert bench.main([*args, "--out", str(tmp_path / "a")]) == 0
    assert bench.main([*args, "--out", str(tmp_path / "b")]) == 0
    a, b = (json.loads((tmp_path / d / "demo_fit.json").read_text()) for d in "ab")
    assert [r["run"] for r in a["results"]] == [str(toy_pretrain_run)]  # token accuracies: the policy's only
    bc, ours = a["decoded"]
    assert bc["num_denoise_steps"] is None and ours["num_denoise_steps"] >= 1
    assert len(bc["chunk_mae_per_dim"]) == 7 and bc["chunk_mae"] > 0
    assert a["decoded"] == b["decoded"]  # the same windows, the same (deterministic) predictions
    assert f"| {toy_runs['bc']} | PickCube-v1 | - |" in (tmp_path / "a" / "demo_fit.md").read_text()
    # --decode READOUT:N: one row per decoding of the policy; the baseline's row as before
    assert bench.main([*args, "--decode", "token:1", "--decode", "token:3", "--out", str(tmp_path / "c")]) == 0
    c = json.loads((tmp_path / "c" / "demo_fit.json").read_text())
    assert c["decode"] == ["token:1", "token:3"] and c["decoded"][0] == bc
    assert [(d["action_readout"], d["num_denoise_steps"]) for d in c["decoded"][1:]] == [("token", 1), ("token", 3)]
    with pytest.raises(SystemExit):
        bench.main([*args, "--decode", "median:1"])
    # --swap image / state: one more row per swapped input and run, on the same windows
    assert bench.main([*args, "--swap", "image", "--swap", "state", "--out", str(tmp_path / "d")]) == 0
    d = json.loads((tmp_path / "d" / "demo_fit.json").read_text())
    assert d["swap"] == ["image", "state"]
    assert [(r["run"], r["swapped"]) for r in d["decoded"]] == [
        (str(run), swap) for run in (toy_runs["bc"], toy_pretrain_run) for swap in (None, "image", "state")]
    assert d["decoded"][0] == bc and d["decoded"][3] == ours  # unswapped: as before
    assert all(r["chunk_mae"] != bc["chunk_mae"] for r in d["decoded"][1:3])  # BC reads both inputs
    with pytest.raises(SystemExit):
        bench.main([*args, "--swap", "instruction"])
    # each window gets the next window's input of its minibatch, the other inputs untouched
    from mmada_rl.keys import IMAGE_KEY, STATE_KEY
    from mmada_rl.training.validation import fixed_windows

    batch = fixed_windows(pick_demos, 3, 1, 4, seed=0)[0]
    (image_swapped,) = bench.swapped([batch], "image")
    assert torch.equal(image_swapped[IMAGE_KEY][1:], batch[IMAGE_KEY][:-1])
    assert torch.equal(image_swapped[IMAGE_KEY][0], batch[IMAGE_KEY][-1])
    assert torch.equal(image_swapped[STATE_KEY], batch[STATE_KEY])
    (state_swapped,) = bench.swapped([batch], "state")
    assert torch.equal(state_swapped[STATE_KEY], batch[STATE_KEY].roll(1, 0))
    assert torch.equal(state_swapped[IMAGE_KEY], batch[IMAGE_KEY])


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_recipe_trains_logs_checkpoints_and_evaluates(toy_runs, algo):
    run_dir = toy_runs[algo]
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["step_00000002", "step_00000004"]
    ckpt = run_dir / "checkpoints" / "step_00000004"
    assert (ckpt / "trainer.pt").exists() and (ckpt / "model" / "policy.safetensors").exists()
    assert json.loads((ckpt / "model" / "policy.json").read_text())["kind"] == algo
    assert json.loads((ckpt / "config.json").read_text())["algo"] == algo
    history = json.loads((run_dir / "history.json").read_text())
    key = "train/loss_diffusion_bc" if algo == "diffusion_policy" else "train/loss_bc"
    assert [h["step"] for h in history] == [1, 2, 3, 4] and all(h[key] > 0 for h in history)
    final = json.loads((run_dir / "final.json").read_text())
    assert final["step"] == 4 and final["eval/episodes"] == 1 and 0.0 <= final["eval/success_once"] <= 1.0
    assert final["eval/num_denoise_steps"] == (10 if algo == "diffusion_policy" else 1)
    recorded = json.loads((run_dir / "final_eval" / "eval.json").read_text())  # the same, episode by episode
    assert recorded["eval/success_once"] == final["eval/success_once"] and len(recorded["per_episode"]) == 1
    assert recorded["checkpoint"] == str(ckpt)
    assert (run_dir / "logs" / "scalars" / "train" / f"{key.split('/')[1]}.csv").exists()  # TorchRL CSV logger
    # Diffusion Policy evaluates and saves the moving average of its weights; the optimizer's own are kept to resume
    extra = torch.load(ckpt / "trainer.pt", weights_only=False)["extra"]
    assert extra.pop("history") == history  # the rows logged so far travel with the checkpoint, for a resume
    if algo == "diffusion_policy":
        saved = load_file(str(ckpt / "model" / "policy.safetensors"))
        assert extra["ema_updates"] == 4 and [h["train/ema_decay"] for h in history] == [0.0] + [1 - n ** -0.75 for n in (2, 3, 4)]
        assert any(not torch.equal(saved[k], extra["train_weights"][k]) for k in saved)
        own = load_actor(run_dir, own_weights=True)  # evaluation can load the own weights instead (--own-weights)
        for key, value in own.state_dict().items():
            torch.testing.assert_close(value, extra["train_weights"][key], rtol=0, atol=0)
    else:
        assert extra == {} and "train/ema_decay" not in history[0]
        with pytest.raises(ValueError, match="kept no moving average"):
            load_actor(run_dir, own_weights=True)


def test_recipe_resumes_with_the_same_batches_and_noise(toy_runs, pick_demos, tmp_path):
    original = toy_runs["diffusion_policy"]  # its loss draws timesteps and noise: the RNG state must come back
    resumed = tmp_path / "resumed"
    (resumed / "checkpoints").mkdir(parents=True)
    shutil.copytree(original / "checkpoints" / "step_00000002", resumed / "checkpoints" / "step_00000002")
    proc = run_recipe("algo=diffusion_policy", *common(resumed, pick_demos), "eval.episodes=0", "checkpoint.resume=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resumed from" in proc.stdout and "at step 2" in proc.stdout
    history = json.loads((resumed / "history.json").read_text())
    assert [h["step"] for h in history] == [1, 2, 3, 4]  # the rows before the checkpoint came back with it
    for a, b in zip(history, json.loads((original / "history.json").read_text())):
        assert a["train/loss"] == pytest.approx(b["train/loss"], rel=1e-5)
    weights = [load_file(str(run / "checkpoints" / "step_00000004" / "model" / "policy.safetensors")) for run in (resumed, original)]
    for key in weights[1]:
        torch.testing.assert_close(weights[0][key], weights[1][key], rtol=1e-5, atol=1e-6)


def test_recipe_trains_a_state_observation_reference_and_evaluates_it_on_the_state(state_demos, tmp_path):
    run_dir = tmp_path / "bc_state"
    proc, mismatch = run_in_one_process(RECIPE, [
        ["algo=bc", "env.obs_mode=state", *common(run_dir, state_demos), "eval.episodes=1", "eval.max_episode_steps=4",
         "model.encoder.drop_state_dims=[9,10,11,12,13,14,15,16,17]"],
        ["algo=bc", *common(tmp_path / "mismatch", state_demos), "eval.episodes=0"]])
    assert proc.returncode == 0, proc.stderr[-3000:]
    policy = load_policy(run_dir / "checkpoints" / "step_00000004" / "model")
    assert policy.obs_mode == "state" and policy.image_size is None and policy.encoder.cnn is None
    assert policy.config.encoder.drop_state_dims == tuple(range(9, 18))  # saved with the policy: joint velocities unread
    assert IMAGE_KEY not in policy.in_keys and STATE_KEY in policy.in_keys
    state_dim = json.loads((state_demos / "metadata.json").read_text())["state_dim"]
    assert policy.config.state_dim == state_dim != S  # the privileged vector, not the 29-d proprio
    final = json.loads((run_dir / "final.json").read_text())
    assert final["eval/episodes"] == 1 and final["eval/max_episode_steps"] == 4
    # reads no image: a state tensordict alone is enough
    td = TensorDict({STATE_KEY: torch.randn(3, state_dim)}, batch_size=[3])
    assert policy(td)[ACTION_CHUNK_KEY].shape == (3, 5, A)  # the toy config's K
    # an rgb policy on a state buffer is one clear error (the buffer's mode must match env.obs_mode)
    assert mismatch.returncode != 0 and "obs_mode" in mismatch.error


def test_recipe_rejects_an_unknown_algo(pick_demos, tmp_path):
    proc = run_recipe("algo=ppo", *common(tmp_path / "bad", pick_demos), "eval.episodes=0")
    assert proc.returncode != 0 and "algo='ppo' is not a baseline" in proc.stderr


def test_recipe_refuses_windows_scored_on_the_gripper_alone(pick_demos):
    """``data.grasp_hold_gripper_only`` is for the MMaDA-VLA losses; the regression losses would score the whole chunk."""
    from omegaconf import OmegaConf
    from script_loader import load_script

    from mmada_rl.data import DemoBuffer

    utils = load_script("recipes/baselines/utils.py", "baselines_utils")
    cfg = OmegaConf.create({"seed": 0, "model": {"chunk_size": 5}, "replay_buffer": {"batch_size": 4, "random_shift": 0},
                            "data": {"skip_grasp_hold": 0.05, "grasp_hold_gripper_only": True}})
    with pytest.raises(ValueError, match="data.grasp_hold_gripper_only scores only the gripper tokens of some windows"):
        utils.make_data(cfg, DemoBuffer.open(pick_demos))


def test_state_dropout_replaces_whole_windows_states_by_the_mean_except_the_kept_dims():
    torch.manual_seed(0)
    state = torch.randn(2000, 5) + 3.0
    mean = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    out = StateDropout(0.25, mean, keep_dims=[4])(TensorDict({STATE_KEY: state.clone()}, [2000])).get(STATE_KEY)
    dropped = (out[:, :4] == mean[:4]).all(-1)  # a window is dropped whole: all four dims take the mean at once
    assert ((out[:, :4] == mean[:4]).any(-1) == dropped).all()
    assert abs(dropped.float().mean().item() - 0.25) < 0.04
    torch.testing.assert_close(out[~dropped], state[~dropped])  # the others are untouched
    torch.testing.assert_close(out[:, 4], state[:, 4])  # the kept dimension, in every window
    assert torch.equal(StateDropout(0.0, mean)(TensorDict({STATE_KEY: state.clone()}, [2000])).get(STATE_KEY), state)
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        StateDropout(1.5, mean)
    with pytest.raises(ValueError, match=r"keep_dims=\[5\] must name some, not all"):
        StateDropout(0.3, mean, keep_dims=[5])
    with pytest.raises(ValueError, match="built for 5-d states, got 3-d"):
        StateDropout(0.3, mean)(TensorDict({STATE_KEY: torch.zeros(2, 3)}, [2]))


def test_recipe_state_dropout_drops_sampled_windows_states_and_refuses_a_state_policy(pick_demos, state_demos):
    """``replay_buffer.state_drop_prob``: the sampled windows' states take the demonstrations' mean (the goal kept);
    an ``obs_mode=state`` policy has nothing else to read, so it is refused."""
    from omegaconf import OmegaConf
    from script_loader import load_script

    from mmada_rl.data import DemoBuffer

    utils = load_script("recipes/baselines/utils.py", "baselines_utils")
    buffer = DemoBuffer.open(pick_demos)
    mean = NormalizationStats.from_buffer(buffer).state_mean
    cfg = OmegaConf.create({"seed": 0, "model": {"chunk_size": 5}, "data": {},
                            "replay_buffer": {"batch_size": 64, "random_shift": 0, "state_drop_prob": 0.5,
                                              "state_drop_keep_dims": [26, 27, 28]}})
    torch.manual_seed(0)
    states = utils.make_data(cfg, buffer).sample().get(STATE_KEY)  # (64, 29)
    dropped = torch.isclose(states[:, :26], mean[:26]).all(-1)
    assert 0 < int(dropped.sum()) < 64  # some windows dropped, some not
    assert not torch.isclose(states[dropped, 26:], mean[26:]).all()  # the goal stays readable
    with pytest.raises(ValueError, match="replay_buffer.state_drop_prob=0.5 drops the state, the only input"):
        utils.make_data(cfg, DemoBuffer.open(state_demos))
    bad = OmegaConf.merge(cfg, {"replay_buffer": {"state_drop_keep_dims": list(range(29))}})
    with pytest.raises(ValueError, match="state_drop_keep_dims: keep_dims=.* must name some, not all"):
        utils.make_data(bad, buffer)


# -- evaluation of a baseline ------------------------------------------------------------
def test_evaluate_runs_a_saved_diffusion_policy_and_an_in_memory_bc_policy(toy_runs, tmp_path):
    result = evaluate(toy_runs["diffusion_policy"] / "checkpoints" / "step_00000004", "PickCube-v1", 1, max_episode_steps=4,
                      execute_steps=2, num_denoise_steps=2, out_dir=tmp_path, progress=False)
    assert result.num_denoise_steps == 2 and result.execute_steps == 2
    assert [r.steps for r in result.per_episode] == [4] and [len(r.decode_ms) for r in result.per_episode] == [2]
    assert json.loads((tmp_path / "eval.json").read_text())["eval/num_denoise_steps"] == 2
    bc = load_policy(toy_runs["bc"] / "checkpoints" / "step_00000004" / "model")
    result = evaluate(bc, "PickCube-v1", 1, max_episode_steps=3, execute_steps=1, progress=False)
    assert [len(r.decode_ms) for r in result.per_episode] == [3] and result.num_denoise_steps == 1
    assert bc.execute_steps == bc.chunk_size  # evaluate left the policy as it was
    with pytest.raises(ValueError, match="does not apply"):
        evaluate(bc, "PickCube-v1", 1, num_denoise_steps=3)
    with pytest.raises(ValueError, match=r"image_size=32 .* fitted on 64x64"):
        evaluate(bc, "PickCube-v1", 1, image_size=32)


def test_bc_image_cnn_initialises_the_denoisers_own(toy_runs, toy_pretrain_run, pick_demos, tmp_path):
    """``model.visual_encoder_init``: the pretraining recipe copies BC's image CNN into the denoiser's;
    frozen it stays BC's through training, unfrozen it trains on from there; other widths are one clear error."""
    pretrain = REPO / "recipes" / "pretrain" / "pretrain.py"
    bc_cnn = load_policy(resolve_model_dir(toy_runs["bc"])).encoder.cnn.state_dict()  # [16, 32, 64]: conv_stack first
    common = [f"data.dir={pick_demos}", "data.collect_episodes=0", f"tokenizers.dir={toy_pretrain_run / 'tokenizers'}",
              "optim.total_steps=2", "optim.warmup_steps=1", "eval.episodes=0", "checkpoint.interval=2",
              "model.denoiser_overrides.cross_attention_to_visual=true", f"model.visual_encoder_init={toy_runs['bc']}"]

    runs = {"frozen": ["model.denoiser_overrides.visual_encoder_channels=[16,32,64]", "model.visual_encoder_freeze=true"],
            "trained": ["model.denoiser_overrides.visual_encoder_channels=[16,32,64]"],
            "widths": ["model.denoiser_overrides.visual_encoder_channels=[32,64,128]"],
            "ours": ["model.denoiser_overrides.visual_encoder_channels=[16,32,64]",
                     f"model.visual_encoder_init={toy_pretrain_run}"]}  # a masked-diffusion run, not a baseline
    done = dict(zip(runs, run_in_one_process(pretrain, [[f"run_dir={tmp_path / name}", *common, *overrides]
                                                          for name, overrides in runs.items()])))

    def denoiser_cnn(name) -> dict:
        saved = load_file(str(resolve_model_dir(tmp_path / name) / "denoiser.safetensors"))
        return {k.removeprefix("visual_encoder.cnn."): v for k, v in saved.items() if k.startswith("visual_encoder.cnn.")}

    proc = done["frozen"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    frozen = denoiser_cnn("frozen")
    assert "the denoiser's CNN starts from" in proc.stdout and "(frozen)" in proc.stdout
    assert len(frozen) == 12  # 3 convolutions and 3 GroupNorms, weight and bias each
    for key, value in frozen.items():
        torch.testing.assert_close(value, bc_cnn[key], rtol=0, atol=0)
    proc = done["trained"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    trained = denoiser_cnn("trained")
    moved = [float((trained[key] - bc_cnn[key]).abs().max()) for key in trained]
    assert 0 < max(moved) < 0.01  # two small steps away from BC's weights, not from a fresh initialisation
    assert done["widths"].returncode != 0 and done["ours"].returncode != 0
    widths = done["widths"].error
    assert "does not begin with this encoder's conv_stack (convolution widths [32, 64, 128]" in widths
    assert "the source CNN (convolution widths [16, 32, 64]" in widths
    assert "is not a baseline policy (BC or Diffusion Policy)" in done["ours"].error
