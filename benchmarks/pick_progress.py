"""How far a PickCube-v1 policy gets: grasp, carry toward the goal, stop there.

    python benchmarks/pick_progress.py --checkpoint runs/bc_pick_fresh_state_noqvel_s0 --episodes 20

PickCube-v1 succeeds when the cube is within 2.5 cm of a goal point in the air
and the arm is still. For each fixed evaluation seed (greedy decoding, the same
seeds as ``mmada-rl eval``) this reads the simulator before every decision:
whether the gripper holds the cube, and the cube's offset from the goal. It
reports per episode whether and when the cube was grasped, the closest the cube
came to the goal, how far **above** the goal it went (a policy that does not
stop keeps lifting past it) and where it ended. Works with any policy
``mmada-rl eval`` loads (MMaDA-VLA, BC, Diffusion Policy; RGB or state).

Writes ``benchmarks/results/pick_progress.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, eval_policy_env, markdown_table, probed_episode, write_results  # noqa: E402

TASK = "PickCube-v1"


def probe(task) -> tuple[bool, list[float]]:
    """(the gripper holds the cube, cube - goal in cm)."""
    offset = 100 * (task.cube.pose.p - task.goal_site.pose.p).reshape(-1)[:3]
    return bool(task.agent.is_grasping(task.cube).any()), [round(float(v), 2) for v in offset]


def rollout(penv, seed: int, max_decisions: int) -> dict:
    probes, success = probed_episode(penv, seed, max_decisions, probe)
    grasped_at = next((i for i, (held, _) in enumerate(probes) if held), None)
    distance = [float(torch.tensor(o).norm()) for _, o in probes]
    after = range(grasped_at or 0, len(probes)) if grasped_at is not None else range(0)
    return {
        "seed": seed, "success": success, "grasped_at_decision": grasped_at,
        "closest_cm": round(min(distance[i] for i in after), 2) if after else None,
        "max_above_goal_cm": round(max(probes[i][1][2] for i in after), 2) if after else None,
        "final_cm": round(distance[-1], 2), "distance_cm": [round(d, 2) for d in distance],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="PickCube-v1 policy: a pretraining or imitation run, "
                        "checkpoint or saved model directory")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--max-episode-steps", type=int, default=None, help="default: the task's own length")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--name", default="pick_progress")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    torch.set_num_threads(args.threads)

    from mmada_rl.evaluation import eval_seeds

    penv, max_decisions = eval_policy_env(args.checkpoint, TASK, args.max_episode_steps)
    episodes = []
    for seed in eval_seeds(args.episodes):
        episodes.append(rollout(penv, seed, max_decisions))
        print({k: v for k, v in episodes[-1].items() if k != "distance_cm"}, flush=True)
    penv.env.close()

    held = [e for e in episodes if e["grasped_at_decision"] is not None]
    median = lambda key: statistics.median(e[key] for e in held) if held else None  # noqa: E731
    summary = {"episodes": len(episodes), "successes": sum(e["success"] for e in episodes), "grasped": len(held),
               "median_closest_cm": median("closest_cm"), "median_max_above_goal_cm": median("max_above_goal_cm"),
               "median_final_cm": median("final_cm")}
    payload = {"checkpoint": str(args.checkpoint), "task": TASK, "summary": summary, "episodes": episodes}
    fmt = lambda v: "–" if v is None else f"{v:.1f}"  # noqa: E731
    table = markdown_table(
        ["episodes", "successes", "grasped", "median closest cube–goal (cm)", "median max height above goal (cm)",
         "median final cube–goal (cm)"],
        [[summary["episodes"], summary["successes"], summary["grasped"], fmt(summary["median_closest_cm"]),
          fmt(summary["median_max_above_goal_cm"]), fmt(summary["median_final_cm"])]])
    markdown = (f"# How far the policy gets on PickCube-v1: `{args.checkpoint}`\n\n"
                f"{args.episodes} evaluation seeds, greedy decoding; distances after the first grasp, "
                f"medians over the episodes that grasped.\n\n{table}\n")
    write_results(args.name, payload, markdown, args.out)
    plot(episodes, args.out / f"{args.name}.png", str(args.checkpoint))
    print(markdown)
    return 0


def plot(episodes: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for e in episodes:
        colour = "tab:green" if e["success"] else ("tab:orange" if e["grasped_at_decision"] is not None else "tab:red")
        ax.plot(e["distance_cm"], color=colour, alpha=0.7, lw=1)
    ax.axhline(2.5, color="k", ls="--", lw=0.8, label="success radius 2.5 cm")
    for colour, label in (("tab:green", "success"), ("tab:orange", "grasped, failed"), ("tab:red", "never grasped")):
        ax.plot([], [], color=colour, label=label)
    ax.set_xlabel("decision")
    ax.set_ylabel("cube – goal distance (cm)")
    ax.set_title(f"PickCube-v1 progress\n{title}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
