"""Decoding with a conditioning cache: block-causal attention against the paper's bidirectional attention.

    python benchmarks/decode_cache.py --layout-from runs/push_fov60_s0 --batch 1 8 --steps 2 5 10

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
  steps of ``--replay-paths`` recorded paths, with and without the cache.

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
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402


def random_prompts(layout, batch: int, generator: torch.Generator) -> torch.Tensor:
    """Prompts ``[B, L]`` (targets masked) whose instruction, image and proprio codes are random."""
    cfg, vocab = layout.config, layout.vocab.config

    def codes(n: int, size: int):
        return torch.randint(0, size, (batch, n), generator=generator) if n else None

    return layout.assemble(codes(cfg.text_tokens, vocab.text_vocab_size),
                           codes(cfg.obs_tokens, vocab.image_codebook_size),
                           proprio_ids=codes(cfg.proprio_tokens, vocab.proprio_codebook_size))


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
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
    parser.add_argument("--repeats", type=int, default=10, help="side-by-side timings per setting")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="decode_cache")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if min(args.batch + args.steps + [args.replay_paths, args.repeats]) < 1:
        parser.error("--batch, --steps, --replay-paths and --repeats must be positive.")
    if not 0 < args.replay_steps <= max(args.steps):
        parser.error(f"--replay-steps must lie in [1, {max(args.steps)}].")
    torch.set_num_threads(args.threads)

    from mmada_rl.diffusion import DenoiserConfig, MaskedDiffusionDenoiser, MaskedDiffusionSampler, SamplerConfig
    from mmada_rl.diffusion.path import path_log_prob, sample_steps
    from mmada_rl.evaluation import resolve_model_dir
    from mmada_rl.policy import MMaDAModel

    layout = MMaDAModel.load(resolve_model_dir(args.layout_from)).layout
    nets = {}
    for attention in ("bidirectional", "block_causal"):
        torch.manual_seed(args.seed)
        nets[attention] = MaskedDiffusionDenoiser(DenoiserConfig.preset(args.preset, attention=attention), layout).eval()
    variants = {  # name: (denoiser, cache the conditioning)
        "bidirectional": (nets["bidirectional"], False),
        "block-causal": (nets["block_causal"], False),
        "block-causal + cache": (nets["block_causal"], True),
    }
    generator = torch.Generator().manual_seed(args.seed)
    conditioning = int(layout.is_condition.sum())
    print(f"layout: L={layout.length} ({conditioning} conditioning, {layout.num_targets} targets); "
          f"{args.preset} denoiser, {args.threads} thread(s)", flush=True)

    decode = []
    for batch in args.batch:
        prompts = random_prompts(layout, batch, generator)
        for steps in args.steps:
            samplers = {name: MaskedDiffusionSampler(SamplerConfig(num_steps=steps, cache_condition=cache))
                        for name, (_, cache) in variants.items()}
            times = {name: [] for name in variants}
            for repeat in range(args.repeats + 1):  # the first round warms up
                for name, (net, _) in variants.items():
                    t = timed(lambda: samplers[name].sample(net, prompts, greedy=True))
                    if repeat:
                        times[name].append(t)
            record = {"batch": batch, "num_steps": steps}
            for name in variants:
                record[f"{name} ms"] = 1000 * statistics.median(times[name])
            record["cache / block-causal"] = statistics.median(
                [a / b for a, b in zip(times["block-causal + cache"], times["block-causal"])])
            record["cache / bidirectional"] = statistics.median(
                [a / b for a, b in zip(times["block-causal + cache"], times["bidirectional"])])
            decode.append(record)
            print(record, flush=True)

    net = nets["block_causal"]
    prompts = random_prompts(layout, args.replay_paths, generator)
    path = MaskedDiffusionSampler(SamplerConfig(num_steps=max(args.steps))).sample(
        net, prompts, greedy=False, generator=generator).path
    steps = sample_steps(path.committed, args.replay_steps, generator)  # as PathPPOLoss draws them

    def replay(cache: bool) -> None:
        net.zero_grad(set_to_none=True)
        path_log_prob(net, path, steps=steps, cache_condition=cache).sum().backward()

    replay_times = {True: [], False: []}
    for repeat in range(args.repeats + 1):
        for cache in (False, True):
            t = timed(lambda: replay(cache))
            if repeat:
                replay_times[cache].append(t)
    replay_record = {
        "paths": args.replay_paths, "replayed_steps": args.replay_steps, "num_steps": path.num_steps,
        "block-causal ms": 1000 * statistics.median(replay_times[False]),
        "block-causal + cache ms": 1000 * statistics.median(replay_times[True]),
        "cache / block-causal": statistics.median([a / b for a, b in zip(replay_times[True], replay_times[False])]),
    }
    print(replay_record, flush=True)

    header = ["B", "N", "bidirectional (ms)", "block-causal (ms)", "block-causal + cache (ms)",
              "cache / block-causal", "cache / bidirectional"]
    rows = [[r["batch"], r["num_steps"], f"{r['bidirectional ms']:.1f}", f"{r['block-causal ms']:.1f}",
             f"{r['block-causal + cache ms']:.1f}", f"{r['cache / block-causal']:.2f}",
             f"{r['cache / bidirectional']:.2f}"] for r in decode]
    markdown = (
        f"# Decoding with a conditioning cache ({args.preset} denoiser, layout of `{args.layout_from}`)\n\n"
        f"Sequence of {layout.length} positions: {conditioning} conditioning, {layout.num_targets} targets. "
        f"Greedy decoding of one chunk batch, no gradient, {args.threads} thread(s); medians of {args.repeats} "
        "interleaved timings, ratios are medians of the side-by-side pairs.\n\n"
        + markdown_table(header, rows)
        + f"\n\nPath-likelihood PPO replay (forward + backward) of {args.replay_steps} of {path.num_steps} steps "
        f"for {args.replay_paths} paths: {replay_record['block-causal ms']:.0f} ms without the cache, "
        f"{replay_record['block-causal + cache ms']:.0f} ms with it (ratio {replay_record['cache / block-causal']:.2f}).\n"
    )
    payload = {"layout_from": args.layout_from, "preset": args.preset, "length": layout.length,
               "conditioning": conditioning, "targets": layout.num_targets, "repeats": args.repeats,
               "decode": decode, "replay": replay_record}
    json_path, md_path = write_results(args.name, payload, markdown, args.out)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(args.batch), figsize=(4.5 * len(args.batch), 3.5), squeeze=False)
    for ax, batch in zip(axes[0], args.batch):
        records = [r for r in decode if r["batch"] == batch]
        for name, style in zip(variants, ("o-", "s--", "^-")):
            ax.plot([r["num_steps"] for r in records], [r[f"{name} ms"] for r in records], style, label=name)
        ax.set(xlabel="decoding steps N", ylabel="ms per decoded chunk batch", title=f"batch {batch}")
        ax.legend()
    save_figure(fig, args.out / f"{args.name}.png")
    print(f"wrote {json_path}, {md_path} and {args.out / f'{args.name}.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
