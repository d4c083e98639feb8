"""Environment throughput: raw ManiSkill loop vs TorchRL env vs ParallelEnv vs demo collection.

Every variant runs the same task, control mode and observation settings with
uniform random actions; the raw loop and the TorchRL env alternate in rounds
in one process so that the ratio between them is measured side by side. In
both loops a clock around the gym env's ``step`` and ``reset`` separates the
simulator's time from the loop's own: what the TorchRL env adds per step
(specs, tensordicts, transforms, ``rollout``) is the difference of the two
loops' own times, a figure that depends less on the machine's load than the ratio.
The TorchRL env's base (TorchRL's ``GymWrapper``, without the transforms of the
canonical schema) runs in the same rounds, to tell the two costs apart.

    python benchmarks/env_throughput.py            # ~5 minutes on 2 cores
    python benchmarks/env_throughput.py --quick    # fewer steps, for a smoke run
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time

import gymnasium as gym
import numpy as np
import torch
from torchrl.envs.utils import RandomPolicy

from common import RESULTS, markdown_table, save_figure, write_results
from mmada_rl.data.collect import collect
from mmada_rl.envs.maniskill import EnvConfig, make_env, make_gym_env


class SimulatorClock(gym.Wrapper):
    """Adds up the seconds spent inside the wrapped env's ``step`` and ``reset``."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.seconds = 0.0

    def _timed(self, call, *args, **kwargs):
        start = time.perf_counter()
        try:
            return call(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start

    def step(self, action):
        return self._timed(self.env.step, action)

    def reset(self, **kwargs):
        return self._timed(self.env.reset, **kwargs)


def raw_loop(env: SimulatorClock, steps: int, rng: np.random.Generator) -> tuple[float, float]:
    """A plain gymnasium loop over the same wrapped ManiSkill env: steps per second, and the loop's
    own milliseconds per step (outside the simulator's ``step`` and ``reset``)."""
    low, high = env.action_space.low, env.action_space.high
    env.reset(seed=int(rng.integers(1 << 30)))
    env.seconds = 0.0
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(np.float32))
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    return steps / elapsed, 1e3 * (elapsed - env.seconds) / steps


def torchrl_loop(env, steps: int, clock: SimulatorClock | None = None) -> tuple[float, float]:
    """``env.rollout`` with a random policy (auto-reset on done): frames per second, and with the
    ``clock`` around its gym env the rollout's own milliseconds per frame (NaN without one)."""
    policy = RandomPolicy(env.action_spec)
    env.reset()
    if clock is not None:
        clock.seconds = 0.0
    start = time.perf_counter()
    td = env.rollout(steps, policy, break_when_any_done=False)
    elapsed = time.perf_counter() - start
    own = float("nan") if clock is None else 1e3 * (elapsed - clock.seconds) / td.numel()
    return td.numel() / elapsed, own


def measure(obs_mode: str, steps: int, rounds: int, workers: int) -> dict:
    cfg = EnvConfig(task="PickCube-v1", obs_mode=obs_mode)
    rng = np.random.default_rng(0)
    raw_env = SimulatorClock(make_gym_env(cfg))
    trl_env = make_env(cfg)
    clock = trl_env.base_env._env = SimulatorClock(trl_env.base_env._env)  # GymWrapper's gym env
    raw, trl, wrapper = [], [], []
    for _ in range(rounds):  # interleaved: all see the same machine load
        raw.append(raw_loop(raw_env, steps, rng))
        trl.append(torchrl_loop(trl_env, steps, clock))
        wrapper.append(torchrl_loop(trl_env.base_env, steps, clock))
    raw_env.close()
    trl_env.close()
    par_env = make_env(cfg, num_workers=workers)
    par_env.reset()
    par = [torchrl_loop(par_env, steps // workers)[0] for _ in range(max(1, rounds - 1))]
    par_env.close()
    tmp = tempfile.mkdtemp()
    try:
        res = collect(f"{tmp}/demos", cfg, episodes=3, progress=False)
        demo = res.steps / res.seconds
        demo_success = res.success_rate
    finally:
        shutil.rmtree(tmp)
    (raw, raw_own), (trl, trl_own), (wrapper, wrapper_own) = zip(*raw), zip(*trl), zip(*wrapper)
    return {
        "obs_mode": obs_mode,
        "raw_steps_per_s": list(raw),
        "torchrl_steps_per_s": list(trl),
        "torchrl_over_raw": [t / r for t, r in zip(trl, raw)],
        "raw_own_ms_per_step": list(raw_own),
        "torchrl_own_ms_per_step": list(trl_own),
        "gym_wrapper_steps_per_s": list(wrapper),
        "gym_wrapper_over_raw": [w / r for w, r in zip(wrapper, raw)],
        "gym_wrapper_own_ms_per_step": list(wrapper_own),
        f"parallel_{workers}_workers_frames_per_s": par,
        "parallel_over_raw": statistics.median(par) / statistics.median(raw),
        "demo_collection_steps_per_s": demo,
        "demo_planner_success_rate": demo_success,
    }


def plot(results: list[dict], workers: int, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["raw ManiSkill", "GymWrapper alone", "TorchRL env", f"ParallelEnv ×{workers}", "demo collection"]
    fig, axes = plt.subplots(1, len(results), figsize=(5.5 * len(results), 3.8))
    for ax, r in zip(np.atleast_1d(axes), results):
        vals = [statistics.median(r["raw_steps_per_s"]), statistics.median(r["gym_wrapper_steps_per_s"]),
                statistics.median(r["torchrl_steps_per_s"]),
                statistics.median(r[f"parallel_{workers}_workers_frames_per_s"]), r["demo_collection_steps_per_s"]]
        ax.bar(labels, vals, color=["#888", "#9ecae1", "#1f77b4", "#2ca02c", "#d62728"])
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
            f"{med(r['gym_wrapper_over_raw']):.2f}×",
            f"{med(r[f'parallel_{args.workers}_workers_frames_per_s']):.1f} ({r['parallel_over_raw']:.2f}×)",
            f"{med(r['raw_own_ms_per_step']):.2f} / {med(r['gym_wrapper_own_ms_per_step']):.2f} / "
            f"{med(r['torchrl_own_ms_per_step']):.2f}",
            f"{r['demo_collection_steps_per_s']:.1f}",
        ])
    md = "## Environment throughput (PickCube-v1, pd_ee_delta_pose, 64×64 RGB or state)\n\n" + markdown_table(
        ["obs", "raw ManiSkill steps/s", "TorchRL env steps/s", "TorchRL / raw", "GymWrapper alone / raw", f"ParallelEnv ×{args.workers} frames/s",
         "own ms per step outside the simulator: raw loop / GymWrapper alone / TorchRL env", "planner demo collection steps/s"],
        rows,
    )
    md += ("\n\nMedians over interleaved rounds; ratios are per round. Demo collection includes motion planning "
           "and the closed-loop conversion of the planner's pd_joint_pos actions to pd_ee_delta_pose "
           "(two simulators step per recorded step). A loop's own time per step is its time outside the gym env's "
           "`step` and `reset` (random actions, specs, tensordicts, transforms, `rollout`); the TorchRL env's cost "
           "is the difference between the two. GymWrapper alone: the TorchRL env's base, without the transforms "
           "that nest the observation keys, add the instruction and count the steps.")
    write_results("env_throughput", {"steps": args.steps, "rounds": args.rounds, "workers": args.workers, "results": results}, md)
    plot(results, args.workers, RESULTS / "env_throughput.png")
    print(md)


if __name__ == "__main__":
    main()
