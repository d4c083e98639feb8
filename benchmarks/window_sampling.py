"""Window sampling: what one training batch costs before the model sees it, the random shift's and the instruction's share.

    python benchmarks/window_sampling.py --demos data/dart/PickCube-v1-fov45 --batch-sizes 32 128

The pretraining recipes draw each batch of chunk windows from the demonstration
buffer on the CPU (``make_window_buffer``) and shift its observation and goal
images together (``RandomShift``, 4 pixels) before ``loss_inputs`` tokenizes
them. With the model on a GPU that is most of a step: nine pretraining runs
side by side on an H200 were each bound by it (docs/results/measured.md, "On a GPU"). This times,
on real windows of ``--demos``, one ``sample()`` of the recipe's pipeline with
the shift as :func:`mmada_rl.data.random_shift` crops it (a slice copy per
image) and the instruction text as :class:`~mmada_rl.data.buffer.InstructionLookup`
sets it (one element per distinct text, on the batch's device); with the
lookup as it was before (a text per window, each converted to the batch's
device when set); with both that and the single indexed gather over four index
tensors that the crop used before (the reference: the pipeline before either
change); and without a shift; then the two crops alone on the sampled images,
and the two lookups alone on the sampled windows. Rows run interleaved,
``--repeats`` rounds, each round starting one row further on (the pipelines
draw the same windows, which the first to read them reads cold); each ratio is
the median of the per-round ratios to the reference. Both crops give the same
images for the same random offsets, and both lookups the same texts (checked
before timing).

Writes ``benchmarks/results/<name>.{json,md,png}`` (default ``window_sampling``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402

from tensordict import NonTensorStack  # noqa: E402

from mmada_rl.data import DemoBuffer, RandomShift, make_window_buffer, random_shift  # noqa: E402
from mmada_rl.data.buffer import InstructionLookup  # noqa: E402
from mmada_rl.keys import GOAL_IMAGE_KEY, IMAGE_KEY, INSTRUCTION_KEY  # noqa: E402


REFERENCE = "sample(), gather crop, a text per window (before)"


def gather_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """The crop :func:`random_shift` replaced: the same offsets, read with one gather over four index tensors."""
    B, C, H, W = images.shape
    padded = F.pad(images.float(), (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, B, 1), generator=generator)
    rows = (dy + torch.arange(H))[:, None, :, None]
    cols = (dx + torch.arange(W))[:, None, None, :]
    return padded[torch.arange(B)[:, None, None, None], torch.arange(C)[None, :, None, None], rows, cols].to(images.dtype)


class GatherShift(RandomShift):
    """``RandomShift`` with the earlier crop."""

    def shift(self, images: torch.Tensor) -> torch.Tensor:
        return gather_shift(images, self.pad)


class PerWindowLookup(InstructionLookup):
    """``InstructionLookup`` as it was: a stack of one text per window, converted to the batch's device when set."""

    def forward(self, tensordict):
        ids = tensordict.get(self.in_keys[0])
        texts = [self.instructions[i] for i in ids.reshape(-1).tolist()]
        tensordict.set(INSTRUCTION_KEY, NonTensorStack(*texts).reshape(ids.shape))
        return tensordict


def pipeline(buffer, args, batch_size: int, shift: RandomShift | None, per_window_lookup: bool = False):
    """The recipes' window buffer with ``shift`` appended, optionally with the earlier instruction lookup."""
    windows = make_window_buffer(buffer, args.chunk_size, batch_size, seed=args.seed)
    if per_window_lookup:
        lookups = windows.transform.transforms
        (position,) = [i for i, t in enumerate(lookups) if isinstance(t, InstructionLookup)]
        lookups[position] = PerWindowLookup(lookups[position].instructions)
    if shift is not None:
        windows.append_transform(shift)
    return windows


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", type=Path, required=True, help="demonstration buffer (mmada-rl collect)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[32, 128], help="windows per batch (default: 32 128)")
    parser.add_argument("--chunk-size", type=int, default=5, help="K, actions per window (default: 5)")
    parser.add_argument("--pad", type=int, default=4, help="largest shift in pixels (default: 4, the recipes')")
    parser.add_argument("--repeats", type=int, default=20, help="interleaved rounds (default: 20)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: 1, as the recipes train)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="window_sampling", help="results file stem (default: window_sampling)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if min(args.batch_sizes) < 1 or args.repeats < 1 or args.threads < 1 or args.pad < 1 or args.chunk_size < 1:
        parser.error("--batch-sizes, --chunk-size, --pad, --repeats and --threads must be >= 1.")
    if not args.demos.exists():
        parser.error(f"no demonstration buffer at {args.demos}.")

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    buffer = DemoBuffer.open(args.demos)
    keys = [IMAGE_KEY, GOAL_IMAGE_KEY]
    results, rows = [], []
    for batch_size in args.batch_sizes:
        pipelines = {
            "sample(), slice crop, one text element (now)": pipeline(buffer, args, batch_size, RandomShift(args.pad, keys)),
            "sample(), slice crop, a text per window": pipeline(buffer, args, batch_size, RandomShift(args.pad, keys), True),
            REFERENCE: pipeline(buffer, args, batch_size, GatherShift(args.pad, keys), True),
            "sample(), no shift, one text element": pipeline(buffer, args, batch_size, None),
        }
        images = pipelines["sample(), no shift, one text element"].sample()[IMAGE_KEY]
        for a, b in ((random_shift(images, args.pad, torch.Generator().manual_seed(s)),
                      gather_shift(images, args.pad, torch.Generator().manual_seed(s))) for s in range(3)):
            if not torch.equal(a, b):
                raise RuntimeError("the two crops disagree on the same offsets")
        texts = [pipeline(buffer, args, batch_size, None, per_window).sample().get(INSTRUCTION_KEY).tolist()
                 for per_window in (False, True)]
        if texts[0] != texts[1]:
            raise RuntimeError("the two instruction lookups disagree on the same windows")
        batch = pipelines["sample(), no shift, one text element"].sample().exclude(INSTRUCTION_KEY)
        lookups = {"lookup alone, one text element": InstructionLookup(buffer.metadata.instructions),
                   "lookup alone, a text per window (before)": PerWindowLookup(buffer.metadata.instructions)}
        jobs = {**{name: windows.sample for name, windows in pipelines.items()},
                "crop alone, slice": lambda: random_shift(images, args.pad),
                "crop alone, gather (before)": lambda: gather_shift(images, args.pad),
                **{name: (lambda lookup=lookup: lookup(batch.clone(False))) for name, lookup in lookups.items()}}
        for job in jobs.values():  # warm-up
            job()
        times = {name: [] for name in jobs}
        names = list(jobs)
        for round_ in range(args.repeats):
            # the pipelines draw the same windows (one sampler seed): whichever runs first in a round reads
            # them cold, so each round starts one row further on
            start = round_ % len(names)
            for name in names[start:] + names[:start]:
                times[name].append(timed(jobs[name]))
        for name, t in times.items():
            reference = times[{"crop": "crop alone, gather (before)",
                               "lookup": "lookup alone, a text per window (before)"}.get(name.split()[0], REFERENCE)]
            median = statistics.median(t)
            ratio = statistics.median(r / x for x, r in zip(t, reference))
            results.append({"batch_size": batch_size, "name": name, "seconds": t, "median_s": median,
                            "speedup_vs_before": ratio})
            rows.append([batch_size, name, f"{1000 * median:.1f}", f"{ratio:.2f}×"])

    md = (f"# Window sampling\n\nOne batch of chunk windows (K = {args.chunk_size}) of `{args.demos}` drawn as the "
          f"pretraining recipes draw it, the observation and goal images shifted together by up to {args.pad} px; "
          f"{args.threads} torch thread(s), {args.repeats} interleaved rounds, each starting one row further on; "
          f"the last column is the median of the per-round ratios of the reference's time (`{REFERENCE}`: the "
          f"pipeline before the slice crop and the shared instruction element) to the row's (the crop rows: of the "
          f"gather crop alone; the lookup rows: of the earlier lookup alone).\n\n"
          + markdown_table(["batch", "what", "median (ms)", "reference time / this"], rows) + "\n")
    write_results(args.name, {"demos": str(args.demos), "chunk_size": args.chunk_size, "pad": args.pad,
                              "threads": args.threads, "repeats": args.repeats, "rows": results}, md, args.out)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(args.batch_sizes), figsize=(5.5 * len(args.batch_sizes), 3.2), squeeze=False)
    for ax, batch_size in zip(axes[0], args.batch_sizes):
        mine = [r for r in results if r["batch_size"] == batch_size]
        ax.barh([r["name"] for r in mine][::-1], [1000 * r["median_s"] for r in mine][::-1], color="tab:blue")
        ax.set_xlabel("median time (ms)")
        ax.set_title(f"batch {batch_size}")
    save_figure(fig, args.out / f"{args.name}.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
