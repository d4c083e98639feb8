"""The model code on an accelerator: the same numbers as on the CPU.

Skipped where no CUDA device is present (CI). On a GPU machine:

    pytest tests/test_cuda.py                            # CUDA against the CPU
    MMADA_RL_TEST_DEVICE=cpu pytest tests/test_cuda.py   # the same checks, CPU against CPU

A copy of each tiny model runs on the device beside the CPU original: the
masked-diffusion loss and its gradients agree, training on the device lowers the
loss, the sampler commits every target in range and its decoding path replays
exactly there, greedy decoding picks the same tokens (and the mean read-out the
same actions), the actor takes CPU
observations and returns its chunk where the env reads it, and both fine-tuning
losses run forward and backward on the device.
"""
from __future__ import annotations

import copy
import os
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mmada_rl.diffusion import MaskedDiffusionSampler, SamplerConfig, path_log_prob
from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_KEY,
    ACTION_TOKENS_KEY,
    ADVANTAGE_KEY,
    GOAL_IMAGE_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    SEQUENCE_KEY,
    STATE_KEY,
)
from mmada_rl.objectives import MaskedDiffusionLoss, PathPPOLoss, RewardWeightedDiffusionLoss
from mmada_rl.policy import DECODING_PATH_KEY, MMaDAActor
from test_actor import CHUNK, LOG_PROBS_KEY, build_tiny_model
from test_diffusion import make_batch, make_layout, prompt_of, tiny

DEVICE = torch.device(os.environ.get("MMADA_RL_TEST_DEVICE", "cuda"))
pytestmark = [
    pytest.mark.skipif(DEVICE.type == "cuda" and not torch.cuda.is_available(), reason="needs a CUDA device"),
    # a tokenizer fitted on a few random vectors clips most others: expected here
    pytest.mark.filterwarnings("ignore::mmada_rl.tokenizers.ActionOutOfRangeWarning"),
]
INSTRUCTION = "pick up the red cube and move it to the goal"


@pytest.fixture(autouse=True)
def full_float32_precision():
    """Float32 matrix products and convolutions without TF32, so the device computes what the CPU does."""
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


def grads_of(module) -> list[torch.Tensor]:
    return [p.grad.detach().cpu() for p in module.parameters() if p.grad is not None]


@pytest.mark.parametrize("attention", ["bidirectional", "block_causal"])
def test_loss_and_gradients_match_the_cpu(attention):
    layout = make_layout(interleave=True)
    cpu_loss = MaskedDiffusionLoss(tiny(layout, attention=attention))
    dev_loss = copy.deepcopy(cpu_loss).to(DEVICE)
    clean = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=8)}, batch_size=[8])
    corrupted = cpu_loss.corrupt(clean, generator=torch.Generator().manual_seed(1))  # the same masks on both
    outs = {}
    for name, loss_fn, td in (("cpu", cpu_loss, corrupted), ("dev", dev_loss, corrupted.to(DEVICE))):
        out = loss_fn(td)
        (out["loss_action"] + out["loss_goal"]).backward()
        outs[name] = out
    for key in ("loss_action", "loss_goal"):
        torch.testing.assert_close(outs["dev"][key].cpu(), outs["cpu"][key], rtol=1e-4, atol=1e-5)
    assert outs["dev"]["loss_action"].device.type == DEVICE.type
    cpu_grads, dev_grads = grads_of(cpu_loss), grads_of(dev_loss)
    assert len(cpu_grads) == len(dev_grads) > 0
    for a, b in zip(dev_grads, cpu_grads):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-5)


def test_training_on_the_device_lowers_the_loss():
    """The forward process draws its masks on the device (a device generator) while training."""
    layout = make_layout()
    loss_fn = MaskedDiffusionLoss(tiny(layout)).to(DEVICE)
    loss_fn.generator = torch.Generator(device=DEVICE).manual_seed(0)
    train = TensorDict({SEQUENCE_KEY: make_batch(layout, batch=16)}, batch_size=[16]).to(DEVICE)
    probe = loss_fn.corrupt(train.clone(), generator=torch.Generator(device=DEVICE).manual_seed(123))
    assert probe.device.type == DEVICE.type

    def total(out):
        return float(out["loss_action"] + out["loss_goal"])

    with torch.no_grad():
        before = total(loss_fn(probe))
    optim = torch.optim.Adam(loss_fn.parameters(), lr=3e-3)
    for _ in range(50):
        out = loss_fn(train)
        optim.zero_grad()
        (out["loss_action"] + out["loss_goal"]).backward()
        optim.step()
    with torch.no_grad():
        after = total(loss_fn(probe))
    assert after < 0.7 * before, (before, after)


@pytest.mark.parametrize("kernel", ["absorbing", "uniform"])
@pytest.mark.parametrize("remasking", [False, True])
def test_sampling_on_the_device_commits_in_range_and_replays_exactly(kernel, remasking):
    layout = make_layout(interleave=True)
    net = tiny(layout).eval().to(DEVICE)
    prompt = prompt_of(layout, batch=4).to(DEVICE)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=5, kernel=kernel, remasking=remasking, temperature=0.8))
    with set_exploration_type(ExplorationType.RANDOM):
        out = sampler.sample(net, prompt, generator=torch.Generator(device=DEVICE).manual_seed(0))
    assert out.ids.device.type == DEVICE.type
    low, high = layout.logit_bounds()
    targets = layout.target_positions
    assert bool(((out.ids.cpu() >= low) & (out.ids.cpu() < high))[:, targets].all())
    assert torch.equal(out.ids[:, layout.is_condition.to(DEVICE)], prompt[:, layout.is_condition.to(DEVICE)])
    assert bool((out.path.committed.sum(1) >= 1).all())
    replay = path_log_prob(net, out.path)
    torch.testing.assert_close(replay, out.path.log_prob, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("attention", ["bidirectional", "block_causal"])
def test_greedy_decoding_picks_the_cpu_tokens(attention):
    layout = make_layout(interleave=True)
    cpu_net = tiny(layout, attention=attention).eval()
    dev_net = copy.deepcopy(cpu_net).to(DEVICE)
    prompt = prompt_of(layout, batch=6)
    sampler = MaskedDiffusionSampler(SamplerConfig(num_steps=4, cache_condition=attention == "block_causal"))
    cpu = sampler.sample(cpu_net, prompt, greedy=True)
    dev = sampler.sample(dev_net, prompt.to(DEVICE), greedy=True)
    assert torch.equal(dev.ids.cpu(), cpu.ids)
    torch.testing.assert_close(dev.path.log_prob.cpu(), cpu.path.log_prob, rtol=1e-4, atol=1e-4)


@pytest.fixture(scope="module")
def models():
    """One tiny policy with fitted tokenizers on the CPU and its copy on the device (random 64x64 data)."""
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (16, 3, 64, 64), dtype=torch.uint8, generator=g)
    states = torch.randn(16, 9, generator=g)
    actions = torch.rand(64, 7, generator=g) * 2 - 1
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cpu = build_tiny_model(images, states, actions, INSTRUCTION, action_tokens="bins")
    return cpu, copy.deepcopy(cpu).to(DEVICE)


def observations(batch: int) -> TensorDict:
    """Observations as a CPU env returns them: uint8 images, float state, the instruction."""
    g = torch.Generator().manual_seed(1)
    td = TensorDict({IMAGE_KEY: torch.randint(0, 256, (batch, 3, 64, 64), dtype=torch.uint8, generator=g),
                     STATE_KEY: torch.randn(batch, 9, generator=g)}, batch_size=[batch])
    td.set(INSTRUCTION_KEY, [INSTRUCTION] * batch)
    return td


def test_actor_on_the_device_reads_cpu_observations_and_returns_cpu_actions(models):
    cpu_model, dev_model = models
    obs = observations(3)
    dev = MMaDAActor(dev_model)(obs.clone())
    assert dev[ACTION_KEY].device.type == "cpu" and dev[ACTION_CHUNK_KEY].shape == (3, CHUNK, 7)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy_dev = MMaDAActor(dev_model)(obs.clone())
        greedy_cpu = MMaDAActor(cpu_model)(obs.clone())
    assert torch.equal(greedy_dev[ACTION_TOKENS_KEY].cpu(), greedy_cpu[ACTION_TOKENS_KEY])
    torch.testing.assert_close(greedy_dev[ACTION_KEY].cpu(), greedy_cpu[ACTION_KEY], rtol=1e-5, atol=1e-5)
    with set_exploration_type(ExplorationType.RANDOM):
        td = MMaDAActor(dev_model)(obs.clone(), generator=torch.Generator(device=DEVICE).manual_seed(0))
    with torch.no_grad():
        replayed = path_log_prob(dev_model.denoiser, td[DECODING_PATH_KEY].to(DEVICE))
    torch.testing.assert_close(replayed.cpu(), td[LOG_PROBS_KEY].cpu(), rtol=1e-4, atol=1e-3)


def test_mean_read_out_on_the_device_acts_as_on_the_cpu(models):
    """``action_readout="mean"`` (each action token's expected bin) decodes through the bins' centres on the
    device, as validation and evaluation run it."""
    cpu_model, dev_model = models
    try:
        for model in models:
            model.set_action_readout("mean")
        obs = observations(3)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            dev, cpu = MMaDAActor(dev_model)(obs.clone()), MMaDAActor(cpu_model)(obs.clone())
        torch.testing.assert_close(dev[ACTION_CHUNK_KEY].cpu(), cpu[ACTION_CHUNK_KEY], rtol=1e-4, atol=1e-4)
    finally:
        for model in models:
            model.set_action_readout("token")


@pytest.mark.parametrize("options", [{}, {"action_mean_weight": 1.0}, {"action_label_sigma": 2.0}],
                         ids=["plain", "action_mean", "soft_labels"])
def test_training_windows_on_the_cpu_feed_a_model_on_the_device(models, options):
    """The recipes sample windows from CPU buffers and build the loss on the model already on its device
    (never moving the loss module): the inputs and the loss's own tables land there."""
    cpu_model, dev_model = models
    windows = observations(4)
    windows.set(ACTION_CHUNK_KEY, torch.rand(4, CHUNK, 7) * 2 - 1)
    windows.set(GOAL_IMAGE_KEY, observations(4)[IMAGE_KEY].flip(0))
    windows.set(ACTION_IS_PAD_KEY, torch.zeros(4, CHUNK, dtype=torch.bool))
    rows = dev_model.loss_inputs(windows.clone())
    assert rows[SEQUENCE_KEY].device.type == DEVICE.type
    assert torch.equal(rows[SEQUENCE_KEY].cpu(), cpu_model.loss_inputs(windows.clone())[SEQUENCE_KEY])
    losses = MaskedDiffusionLoss(dev_model.denoiser, **options)(rows)
    assert ("loss_action_mean" in losses.keys()) == ("action_mean_weight" in options)
    sum(value for key, value in losses.items() if key.startswith("loss_")).backward()
    assert grads_of(dev_model.denoiser)


def test_fine_tuning_losses_run_on_the_device(models):
    _, dev_model = models
    net = copy.deepcopy(dev_model.denoiser).train()
    with set_exploration_type(ExplorationType.RANDOM):
        td = MMaDAActor(dev_model)(observations(3), generator=torch.Generator(device=DEVICE).manual_seed(0))
    td = td.to(DEVICE).set(ADVANTAGE_KEY, torch.tensor([1.0, -0.5, 0.25], device=DEVICE))
    ppo = PathPPOLoss(net)(td)
    assert float(ppo["ratio_mean"]) == pytest.approx(1.0, abs=1e-4)  # unchanged weights: ratio 1
    ppo["loss_objective"].backward()
    windows = observations(3)
    windows.set(ACTION_CHUNK_KEY, td[ACTION_CHUNK_KEY].cpu())
    windows.set(GOAL_IMAGE_KEY, observations(3)[IMAGE_KEY])
    windows.set(ACTION_IS_PAD_KEY, torch.zeros(3, CHUNK, dtype=torch.bool))
    rows = dev_model.loss_inputs(windows).set(ADVANTAGE_KEY, td[ADVANTAGE_KEY])
    weighted = RewardWeightedDiffusionLoss(net, weighting="signed", temperature=1.0)(rows)
    (weighted["loss_action"] + weighted["loss_goal"]).backward()
    assert all(torch.isfinite(g).all() for g in grads_of(net))
