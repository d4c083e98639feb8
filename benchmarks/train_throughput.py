"""Pretraining throughput: how many demonstration windows per second each policy configuration trains on.

    python benchmarks/train_throughput.py --demos data/dart/PickCube-v1-fov45 \\
        --variant 'paper layout=runs/tok100/tokenizers={}' \\
        --variant 'cnn only, 4x4 goal=runs/tok100_g4/tokenizers={"observation_tokens": false}' --bc

On these CPUs the masked-diffusion policy and the BC baseline fit the same
demonstrations about equally well per update (docs/results/pretraining.md, "Why PickCube-v1 fails"),
but one update of the policy costs many of BC's: the sequence length and the
width of the denoiser set the price. This measures one full training step —
``loss_inputs`` → masked-diffusion loss → backward → AdamW — of every
``--variant`` (a name, a fitted tokenizer directory and ``MMaDAConfig`` fields
as JSON; the denoiser's weights are freshly initialised, the cost does not
depend on them) on the same real windows of ``--demos`` (random-shifted as the
recipe trains them), and with ``--bc`` one step of the BC baseline on them.
With several ``--devices`` (``cpu cuda``) every variant runs on each, its
windows sampled on the CPU as the recipes sample them; a step on an accelerator
is timed to its end (synchronised). With ``--precisions fp32 bf16`` every variant
also trains with its forward pass under ``torch.autocast`` to bfloat16 (the
recipes' ``optim.precision=bf16``), on the same windows. The variants run
interleaved, ``--repeats`` rounds; each ratio is the median of the per-round
ratios to the first row.

Writes ``benchmarks/results/<name>.{json,md,png}`` (default ``train_throughput``).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, parse_devices, save_figure, synchronize, write_results  # noqa: E402

from mmada_rl import baselines  # noqa: E402
from mmada_rl.data import DemoBuffer, RandomShift, make_window_buffer  # noqa: E402
from mmada_rl.objectives import MaskedDiffusionLoss  # noqa: E402
from mmada_rl.policy import MMaDAConfig, MMaDAModel  # noqa: E402
from mmada_rl.tokenizers.bundle import Tokenizers  # noqa: E402
from mmada_rl.training import PRECISIONS, autocast, make_optimizer  # noqa: E402


def parse_variant(text: str) -> tuple[str, Path, dict]:
    """``NAME=TOKENIZERS_DIR=JSON`` -> (name, directory, MMaDAConfig fields)."""
    parts = text.split("=", 2)
    if len(parts) != 3 or not parts[0] or not parts[1]:
        raise argparse.ArgumentTypeError(f"expected NAME=TOKENIZERS_DIR=JSON, got {text!r}.")
    try:
        fields = json.loads(parts[2])
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"the MMaDAConfig fields of {parts[0]!r} are not JSON: {err}.") from None
    if not isinstance(fields, dict):
        raise argparse.ArgumentTypeError(f"the MMaDAConfig fields of {parts[0]!r} must be a JSON object.")
    return parts[0], Path(parts[1]), fields


#: What every variant starts from: the recipe's PickCube-v1 configuration (maniskill.yaml and the
#: random-shift runs of docs/results/pretraining.md): the small denoiser cross-attending to its own CNN features of the image.
BASE_FIELDS = {"chunk_size": 5, "denoiser": "small",
               "denoiser_overrides": {"cross_attention_to_visual": True, "visual_encoder_channels": [32, 64, 128]}}


def build_step(name: str, tokenizer_dir: Path, fields: dict, lr: float, device: torch.device, precision: str = "fp32"):
    """A closure running one training step of the variant on ``device`` at ``precision`` (the forward pass's, as
    ``optim.precision``) on a (CPU) window batch; and its description."""
    overrides = {**BASE_FIELDS["denoiser_overrides"], **fields.pop("denoiser_overrides", {})}
    model = MMaDAModel(MMaDAConfig(**{**BASE_FIELDS, **fields, "denoiser_overrides": overrides}),
                       Tokenizers.load(tokenizer_dir)).to(device).train()
    loss = MaskedDiffusionLoss(model.denoiser)
    optimizer = make_optimizer(model.denoiser.parameters(), lr=lr, weight_decay=0.01)

    def step(windows) -> None:
        with autocast(precision, device):
            losses = loss(model.loss_inputs(windows))
        total = sum(v for k, v in losses.items() if k.startswith("loss_"))
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()
        synchronize(device)

    info = {"name": name, "device": str(device), "precision": precision, "tokenizers": str(tokenizer_dir), "fields": {**fields, "denoiser_overrides": overrides},
            "sequence_length": model.layout.length, "parameters": model.denoiser.num_parameters()}
    return step, info


def build_bc_step(buffer: DemoBuffer, chunk_size: int, lr: float, device: torch.device):
    """One training step of the BC baseline (its recipe's default encoder and head) on ``device``."""
    meta = buffer.metadata
    policy = baselines.make_policy("bc", {"chunk_size": chunk_size, "action_dim": meta.action_dim,
                                          "state_dim": meta.state_dim, "image_size": meta.image_size,
                                          "obs_mode": meta.obs_mode, "camera_fov": meta.camera_fov},
                                   baselines.NormalizationStats.from_buffer(buffer)).to(device).train()
    loss = baselines.make_loss(policy)
    optimizer = make_optimizer(policy.parameters(), lr=lr, weight_decay=0.01)

    def step(windows) -> None:
        losses = loss(windows.clone().to(device))  # the loss writes into its input
        total = sum(v for k, v in losses.items() if k.startswith("loss_"))
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()
        synchronize(device)

    return step, {"name": "BC baseline", "device": str(device), "precision": "fp32", "tokenizers": "-", "fields": {}, "sequence_length": None,
                  "parameters": sum(p.numel() for p in policy.parameters())}


def plot_throughput(results: list[dict], by_device: bool, by_precision: bool, threads: int, batch_size: int,
                    path: Path) -> Path:
    """One bar per result, its windows per second (on a log axis when they span more than 10×), labelled."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 0.6 * len(results) + 1.4))
    names = [r["name"] + "".join(f" ({r[k]})" for k, shown in (("device", by_device), ("precision", by_precision))
                                 if shown) for r in results][::-1]
    rates = [r["windows_per_s"] for r in results][::-1]
    ax.barh(names, rates, color="tab:blue")
    for y, rate in enumerate(rates):
        ax.annotate(f" {rate:.1f}", (rate, y), va="center", fontsize=8)
    if max(rates) > 10 * min(rates):
        ax.set_xscale("log")
    ax.set_xlim(right=max(rates) * (2.0 if ax.get_xscale() == "log" else 1.15))
    ax.set_xlabel(f"training windows per second ({threads} thread(s), batch {batch_size})")
    ax.set_title("Pretraining throughput")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", type=Path, required=True, help="demonstration buffer (mmada-rl collect)")
    parser.add_argument("--variant", type=parse_variant, action="append", required=True, metavar="NAME=DIR=JSON",
                        help="a configuration: its name, a fitted tokenizer directory and MMaDAConfig fields "
                             "as JSON over the base (small denoiser + its own CNN); repeatable, the first is the reference")
    parser.add_argument("--bc", action="store_true", help="also time the BC baseline on the same windows")
    parser.add_argument("--batch-size", type=int, default=16, help="windows per step (default: 16, the recipe's)")
    parser.add_argument("--repeats", type=int, default=10, help="interleaved rounds (default: 10)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps per variant first (default: 2)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: 1, as the recipes train)")
    parser.add_argument("--devices", nargs="+", default=["cpu"], metavar="DEVICE",
                        help="torch devices each variant trains on, side by side (default: cpu; e.g. cpu cuda)")
    parser.add_argument("--precisions", nargs="+", default=["fp32"], choices=PRECISIONS, metavar="PRECISION",
                        help="forward-pass precisions each variant trains at, side by side: fp32 and/or bf16 "
                             "(torch.autocast, as the recipes' optim.precision; default: fp32)")
    parser.add_argument("--random-shift", type=int, default=4, help="image shift of the windows (default: 4)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="train_throughput", help="results file stem (default: train_throughput)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.batch_size < 1 or args.repeats < 1 or args.warmup < 0 or args.threads < 1:
        parser.error("--batch-size, --repeats and --threads must be >= 1, --warmup >= 0.")
    if not args.demos.exists():
        parser.error(f"no demonstration buffer at {args.demos}.")
    for name, directory, _ in args.variant:
        if not (directory / "action").exists():
            parser.error(f"variant {name!r}: no fitted tokenizers in {directory}.")
    devices = parse_devices(parser, "--devices", args.devices)

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    buffer = DemoBuffer.open(args.demos)
    windows = make_window_buffer(buffer, BASE_FIELDS["chunk_size"], args.batch_size, seed=args.seed)
    if args.random_shift:
        windows.append_transform(RandomShift(args.random_shift))
    steps, infos = [], []
    for device in devices:
        for name, directory, fields in args.variant:
            for precision in args.precisions:
                step, info = build_step(name, directory, dict(fields), lr=3e-4, device=device, precision=precision)
                steps.append(step)
                infos.append(info)
        if args.bc:
            step, info = build_bc_step(buffer, BASE_FIELDS["chunk_size"], lr=3e-4, device=device)
            steps.append(step)
            infos.append(info)

    batch = windows.sample()
    for step in steps:
        for _ in range(args.warmup):
            step(batch)
    times = [[] for _ in steps]
    for _ in range(args.repeats):
        batch = windows.sample()  # every variant trains on the same windows in a round
        for i, step in enumerate(steps):
            start = time.perf_counter()
            step(batch)
            times[i].append(time.perf_counter() - start)
    rows, results = [], []
    for info, t in zip(infos, times):
        median = statistics.median(t)
        ratio = statistics.median(a / b for a, b in zip(t, times[0]))
        results.append({**info, "step_s": t, "median_step_s": median, "windows_per_s": args.batch_size / median,
                        "step_time_vs_first": ratio})
        rows.append([info["name"], info["device"], info["precision"], info["sequence_length"] or "-", f"{info['parameters'] / 1e6:.2f}M",
                     f"{median:.3f}", f"{args.batch_size / median:.1f}", f"{ratio:.2f}×"])

    md = (f"# Pretraining throughput\n\nOne training step (loss, backward, AdamW) on {args.batch_size} "
          f"real windows of `{args.demos}`, {args.threads} torch CPU thread(s), {args.repeats} interleaved rounds; "
          f"the step-time ratio is the median of the per-round ratios to the first row.\n\n"
          + markdown_table(["configuration", "device", "precision", "sequence length", "parameters", "median step (s)", "windows/s",
                            "step time vs first"], rows) + "\n")
    accelerators = sorted({torch.cuda.get_device_name(d) for d in devices if d.type == "cuda"})
    write_results(args.name, {"batch_size": args.batch_size, "threads": args.threads, "devices": args.devices,
                              "precisions": args.precisions,
                              "accelerators": accelerators, "variants": results}, md, args.out)

    plot_throughput(results, len(devices) > 1, len(args.precisions) > 1, args.threads, args.batch_size,
                    args.out / f"{args.name}.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
