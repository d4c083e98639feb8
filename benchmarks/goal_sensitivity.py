"""Does a PickCube-v1 policy read where the goal is?

    python benchmarks/goal_sensitivity.py --checkpoint runs/bc_pick_dart_fov45_10k_s0/checkpoints/step_00005000 \\
        --demos data/dart/PickCube-v1-fov45 --episodes 20

PickCube-v1's goal, a point in the air, is hidden from the camera: a policy
learns where it is only from the goal position in the proprioceptive state (its
last three entries). On the demonstrations' own observations after the grasp
(the state's ``is_grasped`` entry set), this moves that goal by ``±--shift-cm``
along each axis in turn, leaves the image and the rest of the state as they
are, and decodes the first action of the greedy chunk for each. The
**sensitivity** along an axis is the change of the action's translation
component on that axis per centimetre of goal shift, ``(a(+s) - a(-s)) / 2s``,
in the environment's action units (``pd_ee_delta_pose``: 1 = the controller's
largest step). A policy that carries the cube toward the goal answers with a
positive sensitivity on every axis; ``positive`` is the fraction of states where
it does and ``unmoved`` where the action did not change at all. A policy that
ignores the goal gets zeros. Several ``--checkpoint`` are compared on the same
states.

Works for any policy ``mmada-rl eval`` loads that reads the state (MMaDA-VLA
with proprio tokens, BC, Diffusion Policy), on demonstrations recorded with RGB
observations (the 29-entry proprioceptive state).

Writes ``benchmarks/results/goal_sensitivity.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, load_policy, markdown_table, save_figure, write_results  # noqa: E402

TASK = "PickCube-v1"
#: PickCube-v1's proprioceptive state (RGB observations): qpos (9), qvel (9), is_grasped (1), TCP pose (7), goal (3).
STATE_DIM, IS_GRASPED, GOAL_POSITION = 29, 18, slice(26, 29)
AXES = ("x", "y", "z")


def grasped_observations(demos: Path, episodes: int):
    """The observations (with their demonstrated actions) of the first ``episodes`` demonstrations after the grasp."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.keys import STATE_KEY

    buffer = DemoBuffer.open(demos, task=TASK)
    if buffer.metadata.obs_mode != "rgb":
        raise SystemExit(f"--demos needs demonstrations recorded with RGB observations (the goal is read from the "
                         f"{STATE_DIM}-entry proprioceptive state); {demos} holds {buffer.metadata.obs_mode!r} ones.")
    if buffer.metadata.num_episodes < episodes:
        raise SystemExit(f"--episodes {episodes}: {demos} holds only {buffer.metadata.num_episodes} demonstrations.")
    out = []
    for index, episode in enumerate(buffer.episodes()):
        if index == episodes:
            break
        state = episode.get(STATE_KEY)
        if state.shape[-1] != STATE_DIM:
            raise SystemExit(f"{demos}: states have {state.shape[-1]} entries, expected PickCube-v1's {STATE_DIM}.")
        held = state[:, IS_GRASPED] > 0.5
        if held.any():
            out.append(episode.exclude("next")[held])
    if not out:
        raise SystemExit(f"no grasped state in the first {episodes} demonstrations of {demos}.")
    return out


def first_actions(actor, obs, seed: int) -> torch.Tensor:
    """First action ``[B, A]`` of the greedy chunk for each observation (the same sampling seed every call);
    the actor writes its outputs into ``obs``."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mmada_rl.keys import ACTION_CHUNK_KEY

    torch.manual_seed(seed)  # a stochastic decoder (Diffusion Policy) sees the same noise for every shifted goal
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        return actor(obs).get(ACTION_CHUNK_KEY)[:, 0]


def sensitivity(actor, episodes: list, shift_cm: float, seed: int = 0) -> dict:
    """Per axis: the mean response of the action's translation to a goal shift, and how often it is positive."""
    from mmada_rl.keys import ACTION_KEY, STATE_KEY

    shift = shift_cm / 100.0
    responses = {axis: [] for axis in AXES}
    for episode in tqdm(episodes, desc="goal shifts", unit="demo"):
        obs = episode.exclude(ACTION_KEY)
        for i, axis in enumerate(AXES):
            moved = []
            for sign in (1.0, -1.0):
                shifted = obs.clone()
                shifted.get(STATE_KEY)[:, GOAL_POSITION.start + i] += sign * shift
                moved.append(first_actions(actor, shifted, seed)[:, i])
            responses[axis].append((moved[0] - moved[1]) / (2 * shift_cm))
    out = {"states": sum(len(e) for e in episodes), "shift_cm": shift_cm, "axes": {}}
    for axis in AXES:
        r = torch.cat(responses[axis])
        out["axes"][axis] = {"mean_per_cm": round(float(r.mean()), 5), "median_per_cm": round(float(r.median()), 5),
                             "positive": round(float((r > 0).float().mean()), 3),
                             "unmoved": round(float((r == 0).float().mean()), 3)}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, action="append",
                        help="PickCube-v1 policy (a pretraining or imitation run, checkpoint or saved model); repeat "
                        "to compare several on the same states")
    parser.add_argument("--demos", type=Path, required=True, help="PickCube-v1 demonstrations with RGB observations")
    parser.add_argument("--episodes", type=int, default=20, help="how many demonstrations (the first ones) to use")
    parser.add_argument("--shift-cm", type=float, default=2.0, help="how far the goal moves each way along an axis")
    parser.add_argument("--threads", type=int, default=1)
    from mmada_rl.policy import ACTION_READOUTS

    parser.add_argument("--action-readout", choices=ACTION_READOUTS, default=None,
                        help="MMaDA-VLA only, as mmada-rl eval's option (default: each policy's own)")
    parser.add_argument("--name", default="goal_sensitivity")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    if args.shift_cm <= 0:
        raise SystemExit(f"--shift-cm must be > 0, got {args.shift_cm}")
    torch.set_num_threads(args.threads)
    episodes = grasped_observations(args.demos, args.episodes)
    results = {}
    for checkpoint in args.checkpoint:
        results[checkpoint] = sensitivity(load_policy(checkpoint, args.action_readout), episodes, args.shift_cm)
        print(checkpoint, results[checkpoint], flush=True)
    first = next(iter(results.values()))
    readout = f" ({args.action_readout} read-out)" if args.action_readout else ""
    rows = [[f"`{c}`"] + [f"{r['axes'][a]['mean_per_cm']:+.4f} ({r['axes'][a]['positive']:.0%} / "
                          f"{r['axes'][a]['unmoved']:.0%})" for a in AXES] for c, r in results.items()]
    table = markdown_table(["policy"] + [f"{a}: per cm (positive / unmoved)" for a in AXES], rows)
    markdown = (f"# Does the policy read the goal? PickCube-v1\n\n{first['states']} grasped states of the first "
                f"{args.episodes} demonstrations in `{args.demos}`; the goal in the state moved by ±{args.shift_cm:g} cm "
                f"along each axis{readout}. Change of the first action's translation on that axis per cm of goal shift "
                f"(mean over the states; in brackets, the fractions of states where it is positive / where the "
                f"action did not move at all).\n\n{table}\n")
    write_results(args.name, {"task": TASK, "demos": str(args.demos), "episodes": args.episodes,
                              "action_readout": args.action_readout, "results": results}, markdown, args.out)
    plot(results, args.out / f"{args.name}.png")
    print(markdown)
    return 0


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    width = 0.8 / len(results)
    for j, (checkpoint, r) in enumerate(results.items()):
        ax.bar([i + j * width for i in range(len(AXES))], [r["axes"][a]["mean_per_cm"] for a in AXES], width,
               label=checkpoint.removeprefix("runs/"))
    ax.set_xticks([i + width * (len(results) - 1) / 2 for i in range(len(AXES))], AXES)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_ylabel("action change per cm of goal shift")
    ax.set_title("PickCube-v1: response of the first action to the goal", fontsize=9)
    ax.legend(fontsize=7)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
