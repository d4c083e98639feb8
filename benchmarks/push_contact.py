"""Where a PushCube-v1 policy puts its gripper down, relative to the cube, and whether the push succeeds.

    python benchmarks/push_contact.py --checkpoint runs/push_bins_s0 --episodes 20

PushCube-v1 asks for the cube to be pushed along +x into a goal region; the
planner comes down behind the cube (x < 0 relative to it), centred on it
(y = 0), and pushes. For each fixed evaluation seed (greedy decoding, the same
seeds as ``mmada-rl eval``) this records the TCP's offset from the cube, in cm,
at the first decision at which the TCP is less than 1.5 cm above the cube's
centre, and whether the episode succeeds. A policy that localises the cube
badly lands beside it (large ``|dy|``) and pushes past it.

Writes ``benchmarks/results/push_contact.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import statistics
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import markdown_table, probe_parser, probed_episode, run_probe, save_figure, write_results  # noqa: E402

TASK = "PushCube-v1"
DOWN_CM = 1.5  # the TCP counts as "down" below this height above the cube's centre


def rollout(penv, seed: int, max_decisions: int) -> dict:
    """One episode: the TCP's (dx, dy) from the cube at the first decision it is down at the cube's height."""
    offsets, success = probed_episode(
        penv, seed, max_decisions, lambda task: 100 * (task.agent.tcp.pose.p - task.obj.pose.p).reshape(-1)[:3])
    down = next(([round(float(o[0]), 2), round(float(o[1]), 2)] for o in offsets if float(o[2]) < DOWN_CM), None)
    return {"seed": seed, "success": success, "down_dx_dy_cm": down}


def main(argv: list[str] | None = None) -> int:
    parser = probe_parser(__doc__, "push_contact", TASK)
    args = parser.parse_args(argv)

    episodes, _ = run_probe(args, TASK, rollout)

    def summary(group: list[dict]) -> dict:
        landed = [e["down_dx_dy_cm"] for e in group if e["down_dx_dy_cm"] is not None]
        return {"episodes": len(group), "came_down": len(landed),
                "median_abs_dy_cm": statistics.median(abs(d[1]) for d in landed) if landed else None,
                "median_dx_cm": statistics.median(d[0] for d in landed) if landed else None}

    groups = {"success": summary([e for e in episodes if e["success"]]),
              "failure": summary([e for e in episodes if not e["success"]])}
    payload = {"checkpoint": str(args.checkpoint), "task": TASK, "down_below_cm": DOWN_CM, "groups": groups,
               "episodes": episodes}
    fmt = lambda v: "–" if v is None else f"{v:.1f}"  # noqa: E731
    table = markdown_table(
        ["episodes", "count", "TCP came down near the cube", "median abs(dy) (cm)", "median dx (cm)"],
        [[name, g["episodes"], g["came_down"], fmt(g["median_abs_dy_cm"]), fmt(g["median_dx_cm"])] for name, g in groups.items()])
    markdown = (f"# Where the gripper comes down on PushCube-v1: `{args.checkpoint}`\n\n"
                f"TCP offset from the cube at the first decision with the TCP < {DOWN_CM} cm above the cube's centre "
                f"({args.episodes} evaluation seeds, greedy decoding).\n\n{table}\n")
    write_results(args.name, payload, markdown, args.out)
    plot(episodes, args.out / f"{args.name}.png", str(args.checkpoint))
    print(markdown)
    return 0


def plot(episodes: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    for ok, colour, label in ((True, "tab:green", "success"), (False, "tab:red", "failure")):
        pts = [e["down_dx_dy_cm"] for e in episodes if e["success"] == ok and e["down_dx_dy_cm"] is not None]
        if pts:
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], c=colour, label=label)
    ax.add_patch(plt.Rectangle((-2, -2), 4, 4, fill=False, ls="--", color="k"))  # the 4 cm cube
    ax.axhline(0, color="0.8", lw=0.8)
    ax.set_xlabel("TCP - cube, x (cm; push direction +x)")
    ax.set_ylabel("TCP - cube, y (cm)")
    ax.set_title(f"where the gripper comes down\n{title}", fontsize=9)
    if ax.collections:
        ax.legend()
    ax.set_aspect("equal")
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
