"""Decoding and training with a conditioning cache: block-causal attention against the paper's bidirectional attention.

    python benchmarks/decode_cache.py --layout-from runs/push_fov60_s0 --batch 1 8 --steps 2 5 10 --corruptions 1 2 4

With bidirectional attention every position reads every other, so each of the
``N`` decoding steps runs the whole sequence (conditioning included) through the
denoiser. With block-causal attention the conditioning reads only itself and
carries no noise level: :meth:`MaskedDiffusionDenoiser.cache_condition` computes
its keys and values once per chunk and every step runs the target positions
alone (the same logits; ``tests/test_diffusion.py`` checks it). The same
holds when path-likelihood PPO replays decoding steps: one conditioning pass
per path, with its gradient, then ``S`` target-only passes.

For the sequence layout of a saved policy (``--layout-from``; the denoiser
preset and weights are freshly initialised — the cost does not depend on the
weights) this measures, for each batch size ``B`` and step count ``N``:

* the wall time of one decoded chunk batch (no gradient) with a bidirectional
  denoiser, the block-causal one without its cache, and with it;
* the wall time of one path-likelihood replay, forward + backward, of ``S``
  steps of ``--replay-paths`` recorded paths, with and without the cache;
* the wall time of one pretraining step's loss, forward + backward, of
  ``--train-batch`` windows each corrupted ``C`` times (``--corruptions``;
  ``MaskedDiffusionLoss(corruptions_per_sample=C)``): bidirectional, block-causal
  without the cache, and with it (one conditioning pass per window, the targets of
  its ``C`` corruptions against it).

The three (two) variants run interleaved, ``--repeats`` times each, and the
ratios are medians of the side-by-side pairs. Writes
``benchmarks/results/decode_cache.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, parse_devices, save_figure, synchronize, write_results  # noqa: E402


def random_prompts(layout, batch: int, generator: torch.Generator) -> torch.Tensor:
    """Prompts ``[B, L]`` (targets masked) whose instruction, image and proprio codes are random."""
    cfg, vocab = layout.config, layout.vocab.config

    def codes(n: int, size: int):
        return torch.randint(0, size, (batch, n), generator=generator) if n else None

    return layout.assemble(codes(cfg.text_tokens, vocab.text_vocab_size),
                           codes(cfg.obs_tokens, vocab.image_codebook_size),
                           proprio_ids=codes(cfg.proprio_tokens, vocab.proprio_codebook_size))


def random_sequences(layout, batch: int, generator: torch.Generator) -> torch.Tensor:
    """Clean sequences ``[B, L]``: random prompts with random in-range goal and action tokens."""
    ids = random_prompts(layout, batch, generator)
    low, high = layout.logit_bounds()
    targets = layout.target_positions
    span = (high[targets] - low[targets]).clamp_min(1)
    ids[:, targets] = low[targets] + (torch.rand(batch, len(targets), generator=generator) * span).long()
    return ids


def interleaved(variants: dict, repeats: int, device: torch.device) -> dict[str, list[float]]:
    """Wall times of each variant's callable, ``repeats`` rounds run side by side after one warm-up round."""
    times = {name: [] for name in variants}
    for repeat in range(repeats + 1):
        for name, fn in variants.items():
            t = timed(fn, device)
            if repeat:
                times[name].append(t)
    return times


def paired_ratio(times: dict[str, list[float]], a: str, b: str) -> float:
    """Median of the side-by-side ratios ``a / b``."""
    return statistics.median(x / y for x, y in zip(times[a], times[b]))


def three_way(times: dict[str, list[float]], **setting) -> dict:
    """One record of the three variants: the setting, each variant's median ms, the cache's paired ratios."""
    record = {**setting, **{f"{name} ms": 1000 * statistics.median(t) for name, t in times.items()}}
    record["cache / block-causal"] = paired_ratio(times, "block-causal + cache", "block-causal")
    record["cache / bidirectional"] = paired_ratio(times, "block-causal + cache", "bidirectional")
    return record


def timed(fn, device: torch.device) -> float:
    """Wall time of ``fn()``; work queued on a CUDA device is timed to its end, not its launch."""
    start = time.perf_counter()
    fn()
    synchronize(device)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--layout-from", required=True,
                        help="a saved policy (pretraining run, checkpoint or model directory) whose sequence layout to use")
    parser.add_argument("--preset", default="small", choices=["tiny", "small", "base"], help="denoiser size")
    parser.add_argument("--batch", nargs="+", type=int, default=[1, 8], help="prompts decoded together")
    parser.add_argument("--steps", nargs="+", type=int, default=[2, 5, 10], help="decoding steps N")
    parser.add_argument("--replay-paths", type=int, default=16, help="paths in one PPO replay (the recipe's minibatch)")
    parser.add_argument("--replay-steps", type=int, default=2, help="decoding steps S replayed per path")
    parser.add_argument("--train-batch", type=int, default=16, help="windows per pretraining step (maniskill.yaml's)")
    parser.add_argument("--corruptions", nargs="+", type=int, default=[1, 2, 4],
                        help="corruptions per window C of the pretraining loss")
    parser.add_argument("--repeats", type=int, default=10, help="side-by-side timings per setting")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--device", default="cpu", help="torch device the denoisers run on (default: cpu; e.g. cuda)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="decode_cache")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if min(args.batch + args.steps + args.corruptions + [args.replay_paths, args.repeats, args.train_batch]) < 1:
        parser.error("--batch, --steps, --replay-paths, --train-batch, --corruptions and --repeats must be positive.")
    if not 0 < args.replay_steps <= max(args.steps):
        parser.error(f"--replay-steps must lie in [1, {max(args.steps)}].")
    (device,) = parse_devices(parser, "--device", [args.device])
    torch.set_num_threads(args.threads)

    from mmada_rl.diffusion import DenoiserConfig, MaskedDiffusionDenoiser, MaskedDiffusionSampler, SamplerConfig
    from mmada_rl.diffusion.path import path_log_prob, sample_steps
    from mmada_rl.evaluation import resolve_model_dir
    from mmada_rl.keys import SEQUENCE_KEY
    from mmada_rl.objectives import MaskedDiffusionLoss
    from mmada_rl.policy import MMaDAModel
    from tensordict import TensorDict

    layout = MMaDAModel.load(resolve_model_dir(args.layout_from)).layout
    nets = {}
    for attention in ("bidirectional", "block_causal"):
        torch.manual_seed(args.seed)
        nets[attention] = MaskedDiffusionDenoiser(DenoiserConfig.preset(args.preset, attention=attention), layout).eval().to(device)
    variants = {  # name: (denoiser, cache the conditioning)
        "bidirectional": (nets["bidirectional"], False),
        "block-causal": (nets["block_causal"], False),
        "block-causal + cache": (nets["block_causal"], True),
    }
    generator = torch.Generator().manual_seed(args.seed)
    conditioning = int(layout.is_condition.sum())
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{args.threads} CPU thread(s)"
    print(f"layout: L={layout.length} ({conditioning} conditioning, {layout.num_targets} targets); "
          f"{args.preset} denoiser, {where}", flush=True)

    decode = []
    for batch in args.batch:
        prompts = random_prompts(layout, batch, generator).to(device)
        for steps in args.steps:
            samplers = {name: MaskedDiffusionSampler(SamplerConfig(num_steps=steps, cache_condition=cache))
                        for name, (_, cache) in variants.items()}
            times = interleaved({name: (lambda name=name, net=net: samplers[name].sample(net, prompts, greedy=True))
                                 for name, (net, _) in variants.items()}, args.repeats, device)
            decode.append(three_way(times, batch=batch, num_steps=steps))
            print(decode[-1], flush=True)

    net = nets["block_causal"]
    prompts = random_prompts(layout, args.replay_paths, generator).to(device)
    path = MaskedDiffusionSampler(SamplerConfig(num_steps=max(args.steps))).sample(
        net, prompts, greedy=False, generator=torch.Generator(device=device).manual_seed(args.seed)).path
    steps = sample_steps(path.committed.cpu(), args.replay_steps, generator).to(device)  # as PathPPOLoss draws them

    def replay(cache: bool) -> None:
        net.zero_grad(set_to_none=True)
        path_log_prob(net, path, steps=steps, cache_condition=cache).sum().backward()

    replay_times = interleaved({"block-causal": lambda: replay(False), "block-causal + cache": lambda: replay(True)},
                               args.repeats, device)
    replay_record = {
        "paths": args.replay_paths, "replayed_steps": args.replay_steps, "num_steps": path.num_steps,
        "block-causal ms": 1000 * statistics.median(replay_times["block-causal"]),
        "block-causal + cache ms": 1000 * statistics.median(replay_times["block-causal + cache"]),
        "cache / block-causal": paired_ratio(replay_times, "block-causal + cache", "block-causal"),
    }
    print(replay_record, flush=True)

    windows = TensorDict({SEQUENCE_KEY: random_sequences(layout, args.train_batch, generator)},
                         batch_size=[args.train_batch]).to(device)

    def train_step(loss_fn) -> None:
        loss_fn.zero_grad(set_to_none=True)
        out = loss_fn(windows)
        (out["loss_action"] + out["loss_goal"]).backward()

    training = []
    for copies in args.corruptions:
        losses = {name: MaskedDiffusionLoss(denoiser.train(), schedule="cosine", corruptions_per_sample=copies,
                                            cache_condition=cache) for name, (denoiser, cache) in variants.items()}
        times = interleaved({name: (lambda fn=fn: train_step(fn)) for name, fn in losses.items()}, args.repeats, device)
        training.append(three_way(times, windows=args.train_batch, corruptions=copies))
        print(training[-1], flush=True)
    one = training[0]["block-causal + cache ms"] if args.corruptions[0] == 1 else None

    header = ["B", "N", "bidirectional (ms)", "block-causal (ms)", "block-causal + cache (ms)",
              "cache / block-causal", "cache / bidirectional"]
    rows = [[r["batch"], r["num_steps"], f"{r['bidirectional ms']:.1f}", f"{r['block-causal ms']:.1f}",
             f"{r['block-causal + cache ms']:.1f}", f"{r['cache / block-causal']:.2f}",
             f"{r['cache / bidirectional']:.2f}"] for r in decode]
    markdown = (
        f"# Decoding with a conditioning cache ({args.preset} denoiser, layout of `{args.layout_from}`)\n\n"
        f"Sequence of {layout.length} positions: {conditioning} conditioning, {layout.num_targets} targets. "
        f"Greedy decoding of one chunk batch, no gradient, {where}; medians of {args.repeats} "
        "interleaved timings, ratios are medians of the side-by-side pairs.\n\n"
        + markdown_table(header, rows)
        + f"\n\nPath-likelihood PPO replay (forward + backward) of {args.replay_steps} of {path.num_steps} steps "
        f"for {args.replay_paths} paths: {replay_record['block-causal ms']:.0f} ms without the cache, "
        f"{replay_record['block-causal + cache ms']:.0f} ms with it (ratio {replay_record['cache / block-causal']:.2f}).\n"
        f"\n## Pretraining loss, forward + backward, {args.train_batch} windows each corrupted C times\n\n"
        + markdown_table(["C", "bidirectional (ms)", "block-causal (ms)", "block-causal + cache (ms)",
                          "cache / block-causal", "cache / bidirectional"] + (["cache: cost vs C = 1"] if one else []),
                         [[r["corruptions"], f"{r['bidirectional ms']:.0f}", f"{r['block-causal ms']:.0f}",
                           f"{r['block-causal + cache ms']:.0f}", f"{r['cache / block-causal']:.2f}",
                           f"{r['cache / bidirectional']:.2f}"]
                          + ([f"{r['block-causal + cache ms'] / one:.2f}"] if one else []) for r in training])
        + "\n"
    )
    payload = {"layout_from": args.layout_from, "preset": args.preset, "device": str(device), "where": where,
               "length": layout.length,
               "conditioning": conditioning, "targets": layout.num_targets, "repeats": args.repeats,
               "decode": decode, "replay": replay_record, "training": training}
    json_path, md_path = write_results(args.name, payload, markdown, args.out)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = len(args.batch) + 1
    fig, axes = plt.subplots(1, panels, figsize=(4.5 * panels, 3.5), squeeze=False)
    for ax, batch in zip(axes[0], args.batch):
        records = [r for r in decode if r["batch"] == batch]
        for name, style in zip(variants, ("o-", "s--", "^-")):
            ax.plot([r["num_steps"] for r in records], [r[f"{name} ms"] for r in records], style, label=name)
        ax.set(xlabel="decoding steps N", ylabel="ms per decoded chunk batch", title=f"decoding, batch {batch}")
        ax.legend()
    ax = axes[0][-1]
    for name, style in zip(variants, ("o-", "s--", "^-")):
        ax.plot([r["corruptions"] for r in training], [r[f"{name} ms"] for r in training], style, label=name)
    ax.set(xlabel="corruptions per window C", ylabel="ms per loss forward + backward",
           title=f"pretraining loss, {args.train_batch} windows")
    ax.legend()
    save_figure(fig, args.out / f"{args.name}.png")
    print(f"wrote {json_path}, {md_path} and {args.out / f'{args.name}.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
