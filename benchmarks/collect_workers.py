"""Demonstration collection by several processes side by side (``mmada-rl collect --workers``) against one.

    python benchmarks/collect_workers.py                       # 20 PickCube-v1 DART episodes per run, 1 and 2 workers, 2 rounds
    python benchmarks/collect_workers.py --episodes 5 --rounds 1   # a smoke run

Each round collects the same ``--episodes`` motion-planner demonstrations into a
fresh buffer once per worker count, in alternating order, and times the whole
call (the workers' start-up included: what a user waits for). The speed-up is
the median over rounds of each round's ratio to one worker's time. The buffers
are then compared with one worker's: the seeds kept (the same when every
attempt succeeds or fails alike) and the episodes that are bit for bit the same
(a simulator carries a little state from one attempt to the next, so an
episode tried by another process can differ in the last digits;
``mmada_rl/data/collect_workers.py``). Writes
``benchmarks/results/collect_workers.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from common import RESULTS, markdown_table, save_figure, write_results
from mmada_rl.data import DemoBuffer
from mmada_rl.data.collect import collect
from mmada_rl.envs.maniskill import EnvConfig


def episodes_of(path: Path) -> dict[int, dict[str, torch.Tensor]]:
    """Each kept episode's tensors by its seed."""
    buf = DemoBuffer.open(path)
    data = buf.storage[: len(buf)]
    seeds = data["seed"].reshape(-1)
    return {int(s): {k: data.get(k)[seeds == s] for k in ("action", ("observation", "state"))} for s in seeds.unique()}


def compare(reference: dict, other: dict) -> dict:
    """How the episodes of ``other`` differ from those of ``reference`` (one worker's)."""
    shared = sorted(set(reference) & set(other))
    same = [s for s in shared if all(reference[s][k].shape == other[s][k].shape and torch.equal(reference[s][k], other[s][k])
                                     for k in reference[s])]
    gaps = [float((reference[s]["action"] - other[s]["action"]).abs().max()) for s in shared
            if reference[s]["action"].shape == other[s]["action"].shape]
    return {"same_seeds_kept": set(reference) == set(other), "episodes_compared": len(shared),
            "episodes_bit_identical": len(same), "max_action_difference": max(gaps, default=0.0)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="PickCube-v1")
    p.add_argument("--episodes", type=int, default=20, help="demonstrations per collection (default: %(default)s)")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts; the first is the reference")
    p.add_argument("--rounds", type=int, default=2, help="collections per worker count (default: %(default)s)")
    p.add_argument("--action-noise", type=float, default=0.1, help="DART noise (default: %(default)s, the recipes')")
    p.add_argument("--camera-fov", type=float, default=45.0, help="camera field of view (default: %(default)s)")
    p.add_argument("--name", default="collect_workers", help="result file name in benchmarks/results")
    args = p.parse_args(argv)
    if args.episodes < 1 or args.rounds < 1 or min(args.workers) < 1:
        p.error("--episodes, --rounds and every --workers value must be positive")
    cfg = EnvConfig(task=args.task, camera_fov=args.camera_fov)
    seconds: dict[int, list[float]] = {w: [] for w in args.workers}
    steps: dict[int, int] = {}
    tmp = Path(tempfile.mkdtemp())
    try:
        for r in range(args.rounds):
            order = args.workers if r % 2 == 0 else args.workers[::-1]
            for w in order:
                out = tmp / f"w{w}_r{r}"
                start = time.perf_counter()
                res = collect(out, cfg, episodes=args.episodes, action_noise=args.action_noise, workers=w, progress=False)
                seconds[w].append(time.perf_counter() - start)
                steps[w] = len(res.buffer)
                print(f"round {r}: {w} worker(s) {res.new_episodes} episodes from {res.attempts} attempts, "
                      f"{len(res.buffer)} steps in {seconds[w][-1]:.1f} s", flush=True)
        first = {w: episodes_of(tmp / f"w{w}_r0") for w in args.workers}  # each buffer read once
        same = {w: compare(first[args.workers[0]], first[w]) for w in args.workers}
        repeat = {w: compare(first[w], episodes_of(tmp / f"w{w}_r{args.rounds - 1}"))
                  for w in args.workers} if args.rounds > 1 else {}
    finally:
        shutil.rmtree(tmp)
    base = args.workers[0]
    speedup = {w: statistics.median(b / s for b, s in zip(seconds[base], seconds[w])) for w in args.workers}
    payload = {"task": args.task, "episodes": args.episodes, "action_noise": args.action_noise, "camera_fov": args.camera_fov,
               "seconds": seconds, "steps": steps, "speedup_over_first": speedup, "against_first": same,
               "first_round_against_last": repeat}
    rows = [[w, " / ".join(f"{s:.1f}" for s in seconds[w]), f"{60 * args.episodes / statistics.median(seconds[w]):.1f}",
             f"{speedup[w]:.2f}×", f"{same[w]['episodes_bit_identical']}/{same[w]['episodes_compared']}",
             "yes" if same[w]["same_seeds_kept"] else "no", f"{same[w]['max_action_difference']:.2g}",
             (f"{repeat[w]['episodes_bit_identical']}/{repeat[w]['episodes_compared']}" if repeat else "–")]
            for w in args.workers]
    markdown = (f"# Collection with worker processes: {args.episodes} {args.task} DART demonstrations (noise "
                f"{args.action_noise:g}, {args.camera_fov:g}° camera)\n\n"
                + markdown_table(["workers", "seconds per run", "episodes / min (median)", f"speed-up over {base}",
                                  f"episodes bit-identical to {base} worker(s)'", "same seeds kept",
                                  "largest action difference", "first round's bit-identical to the last's"], rows)
                + "\n\nEach run is the whole `collect` call, the workers' start-up included; the speed-up is the median of "
                  "each round's ratio.\n")
    write_results(args.name, payload, markdown)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 3))
    ax.bar([str(w) for w in args.workers], [60 * args.episodes / statistics.median(seconds[w]) for w in args.workers])
    ax.set_xlabel("worker processes")
    ax.set_ylabel("episodes / min (median)")
    ax.set_title(f"{args.task} DART collection")
    save_figure(fig, RESULTS / f"{args.name}.png")
    print(markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
