"""Environment throughput: raw ManiSkill loop vs TorchRL env vs ParallelEnv vs demo collection.

Every variant runs the same task, control mode and observation settings with
uniform random actions; the raw loop and the TorchRL env alternate in rounds
in one process so that the ratio between them is measured side by side.

    python benchmarks/env_throughput.py            # ~5 minutes on 2 cores
    python benchmarks/env_throughput.py --quick    # fewer steps, for a smoke run
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time

import numpy as np
import torch
from torchrl.envs.utils import RandomPolicy

from common import RESULTS, markdown_table, save_figure, write_results
from mmada_rl.data.collect import collect
from mmada_rl.envs.maniskill import EnvConfig, make_env, make_gym_env


def raw_loop(env, steps: int, rng: np.random.Generator) -> float:
    """Steps per second of a plain gymnasium loop over the same wrapped ManiSkill env."""
    low, high = env.action_space.low, env.action_space.high
    env.reset(seed=int(rng.integers(1 << 30)))
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(np.float32))
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def torchrl_loop(env, steps: int) -> float:
    """Frames per second of ``env.rollout`` with a random policy (auto-reset on done)."""
    policy = RandomPolicy(env.action_spec)
    env.reset()
    start = time.perf_counter()
    td = env.rollout(steps, policy, break_when_any_done=False)
    return td.numel() / (time.perf_counter() - start)


def measure(obs_mode: str, steps: int, rounds: int, workers: int) -> dict:
    cfg = EnvConfig(task="PickCube-v1", obs_mode=obs_mode)
    rng = np.random.default_rng(0)
    raw_env = make_gym_env(cfg)
    trl_env = make_env(cfg)
    raw, trl = [], []
    for _ in range(rounds):  # interleaved: both see the same machine load
        raw.append(raw_loop(raw_env, steps, rng))
        trl.append(torchrl_loop(trl_env, steps))
    raw_env.close()
    trl_env.close()
    par_env = make_env(cfg, num_workers=workers)
    par_env.reset()
    par = [torchrl_loop(par_env, steps // workers) for _ in range(max(1, rounds - 1))]
    par_env.close()
    tmp = tempfile.mkdtemp()
    try:
        res = collect(f"{tmp}/demos", cfg, episodes=3, progress=False)
        demo = res.steps / res.seconds
        demo_success = res.success_rate
    finally:
        shutil.rmtree(tmp)
    ratios = [t / r for t, r in zip(trl, raw)]
    return {
        "obs_mode": obs_mode,
        "raw_steps_per_s": raw,
        "torchrl_steps_per_s": trl,
        "torchrl_over_raw": ratios,
        f"parallel_{workers}_workers_frames_per_s": par,
        "parallel_over_raw": statistics.median(par) / statistics.median(raw),
        "demo_collection_steps_per_s": demo,
        "demo_planner_success_rate": demo_success,
    }


def plot(results: list[dict], workers: int, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["raw ManiSkill", "TorchRL env", f"ParallelEnv ×{workers}", "demo collection"]
    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 3.5))
    for ax, r in zip(np.atleast_1d(axes), results):
        vals = [statistics.median(r["raw_steps_per_s"]), statistics.median(r["torchrl_steps_per_s"]),
                statistics.median(r[f"parallel_{workers}_workers_frames_per_s"]), r["demo_collection_steps_per_s"]]
        ax.bar(labels, vals, color=["#888", "#1f77b4", "#2ca02c", "#d62728"])
        ax.set_title(f"PickCube-v1, obs_mode={r['obs_mode']}")
        ax.set_ylabel("env steps / s")
        ax.tick_params(axis="x", rotation=20)
    save_figure(fig, path)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=300, help="env steps per measurement round (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved raw/TorchRL rounds (default: %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="ParallelEnv workers (default: %(default)s)")
    parser.add_argument("--quick", action="store_true", help="60 steps, 2 rounds")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.rounds = 60, 2
    torch.manual_seed(0)
    results = [measure(mode, args.steps, args.rounds, args.workers) for mode in ("state", "rgb")]
    rows = []
    for r in results:
        med = statistics.median
        rows.append([
            r["obs_mode"],
            f"{med(r['raw_steps_per_s']):.1f}",
            f"{med(r['torchrl_steps_per_s']):.1f}",
            f"{med(r['torchrl_over_raw']):.2f}× (min {min(r['torchrl_over_raw']):.2f})",
            f"{med(r[f'parallel_{args.workers}_workers_frames_per_s']):.1f} ({r['parallel_over_raw']:.2f}×)",
            f"{r['demo_collection_steps_per_s']:.1f}",
        ])
    md = "## Environment throughput (PickCube-v1, pd_ee_delta_pose, 64×64 RGB or state)\n\n" + markdown_table(
        ["obs", "raw ManiSkill steps/s", "TorchRL env steps/s", "TorchRL / raw", f"ParallelEnv ×{args.workers} frames/s", "planner demo collection steps/s"],
        rows,
    )
    md += ("\n\nMedians over interleaved rounds; ratios are per round. Demo collection includes motion planning "
           "and the closed-loop conversion of the planner's pd_joint_pos actions to pd_ee_delta_pose "
           "(two simulators step per recorded step).")
    write_results("env_throughput", {"steps": args.steps, "rounds": args.rounds, "workers": args.workers, "results": results}, md)
    plot(results, args.workers, RESULTS / "env_throughput.png")
    print(md)


if __name__ == "__main__":
    main()
