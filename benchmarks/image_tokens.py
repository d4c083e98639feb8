"""What do the image tokens keep? Whole-frame and foreground PSNR of fitted image tokenizers.

    python benchmarks/image_tokens.py \\
        --tokenizers runs/pick_bins_s0=PickCube-v1 --tokenizers runs/pick_bins_fg20_s0=PickCube-v1

Each ``DIR=TASK`` names fitted tokenizers (a tokenizers directory, or a run
directory with one under ``tokenizers/``) and the task whose demonstration
frames (``--demos``, ``{task}`` filled in; every ``--every``-th frame) they are
scored on. The policy sees the observation only through these tokens, so an
object the VQ-VAE decodes away is an object the policy cannot see.

Reported per tokenizer: its ``foreground_weight``, the PSNR over whole frames,
and the PSNR over *foreground* pixels only (those differing from the frames'
per-pixel median by more than 32/255 in a channel: robot, objects, goal
markers), with the foreground's share of the pixels. The PNG shows the same
frames of each task above every tokenizer's reconstruction of them.

Writes ``benchmarks/results/image_tokens.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402

from mmada_rl.data import DemoBuffer  # noqa: E402
from mmada_rl.tokenizers import Tokenizers  # noqa: E402
from mmada_rl.tokenizers.report import image_reconstruction_report  # noqa: E402


def parse_pair(text: str) -> tuple[Path, str]:
    """``DIR=TASK`` -> (tokenizers directory, task)."""
    directory, sep, task = text.partition("=")
    if not sep or not directory or not task:
        raise argparse.ArgumentTypeError(f"expected DIR=TASK, got {text!r}.")
    path = Path(directory)
    return (path / "tokenizers" if (path / "tokenizers").is_dir() else path), task


def frames_of(demos: DemoBuffer, every: int) -> torch.Tensor:
    """uint8 ``[N, 3, H, W]``: every ``every``-th frame of every demonstration."""
    return torch.cat([episode["observation", "image"] for episode in demos.episodes()])[::every]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tokenizers", type=parse_pair, action="append", required=True, metavar="DIR=TASK",
                        help="fitted tokenizers (or a run directory holding them) and the task to score them on; repeatable")
    parser.add_argument("--demos", default="data/{task}", help="demonstration buffer per task (default: data/{task})")
    parser.add_argument("--every", type=int, default=7, help="score every N-th demonstration frame (default: 7)")
    parser.add_argument("--grid-frames", type=int, default=6, help="frames per task in the PNG (default: 6)")
    parser.add_argument("--name", default="image_tokens", help="results file stem (default: image_tokens)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.every < 1 or args.grid_frames < 1:
        parser.error("--every and --grid-frames must be >= 1.")
    for directory, task in args.tokenizers:
        if not (directory / "image").is_dir():
            parser.error(f"{directory} holds no image tokenizer (expected {directory / 'image'}).")
        if not Path(args.demos.format(task=task)).exists():
            parser.error(f"no demonstration buffer for {task} at {args.demos.format(task=task)}.")
    torch.set_num_threads(1)

    frames: dict[str, torch.Tensor] = {}
    shown: dict[str, torch.Tensor] = {}  # the frames of each task in the PNG
    rows, grid_rows = [], {}
    for directory, task in args.tokenizers:
        if task not in frames:
            frames[task] = frames_of(DemoBuffer.open(args.demos.format(task=task)), args.every)
            shown[task] = frames[task][torch.linspace(0, len(frames[task]) - 1, args.grid_frames).long()]
            grid_rows[task] = [(f"{task}\ninput", shown[task])]
        image = Tokenizers.load(directory).image
        summary = image_reconstruction_report(image, frames[task])["summary"]
        rows.append({"tokenizers": str(directory), "task": task, "foreground_weight": image.config.foreground_weight,
                     **summary})
        run = directory.parent.name if directory.name == "tokenizers" else directory.name
        grid_rows[task].append((f"{run}\nw={image.config.foreground_weight:g}", image.reconstruct(shown[task]).images))

    header = ["tokenizers", "task", "foreground weight", "PSNR (dB)", "foreground PSNR (dB)", "foreground pixels",
              "code usage"]
    table = markdown_table(header, [[r["tokenizers"], r["task"], f"{r['foreground_weight']:g}", f"{r['psnr_db']:.1f}",
                                     f"{r['psnr_foreground_db']:.1f}", f"{100 * r['foreground_fraction']:.1f}%",
                                     f"{r['code_usage']:.2f}"] for r in rows])

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = [line for lines in grid_rows.values() for line in lines]  # each task's input row, then its tokenizers'
    fig, axes = plt.subplots(len(order), args.grid_frames, figsize=(1.3 * args.grid_frames, 1.4 * len(order)), squeeze=False)
    for row, (label, images) in enumerate(order):
        for col in range(args.grid_frames):
            ax = axes[row][col]
            ax.imshow(images[col].permute(1, 2, 0).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
        axes[row][0].set_ylabel(label, fontsize=7)
    save_figure(fig, args.out / f"{args.name}.png")

    command = "python benchmarks/image_tokens.py " + " ".join(f"--tokenizers {d}={t}" for d, t in args.tokenizers)
    write_results(args.name, {"demos": args.demos, "every": args.every, "results": rows},
                  f"# What the image tokens keep\n\n`{command}`\n\nEvery {args.every}th demonstration frame; foreground: "
                  f"pixels that differ from the frames' per-pixel median by more than 32/255 in a channel.\n\n{table}\n\n"
                  f"![reconstructions]({args.name}.png)\n", directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
