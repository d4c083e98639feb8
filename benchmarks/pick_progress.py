"""How far a PickCube-v1 policy gets: grasp, carry toward the goal, stop there.

    python benchmarks/pick_progress.py --checkpoint runs/bc_pick_fresh_state_noqvel_s0 --episodes 20

PickCube-v1 succeeds when the cube is within 2.5 cm of a goal point in the air
and the arm is still. For each fixed evaluation seed (greedy decoding, the same
seeds as ``mmada-rl eval``) this reads the simulator before every decision:
whether the gripper holds the cube, and the cube's offset from the goal. It
reports per episode whether and when the cube was grasped, the closest the cube
came to the goal, how far **above** the goal it went (a policy that does not
stop keeps lifting past it), where it ended, and how far the gripper tilted:
the largest angle between its pointing axis and the one it started the episode
with (the planner keeps the gripper pointing down and turns it only about that
axis, so the demonstrations tilt by a few degrees at most; ``--demo-tilt DIR``
measures theirs from the TCP pose in their recorded states). Works with any
policy ``mmada-rl eval`` loads (MMaDA-VLA, BC, Diffusion Policy; RGB or state).

Each failed episode is sorted into one failure mode (:func:`failure_mode`, the
first that applies): ``never grasped``; ``dropped`` (the gripper lost the cube
at least once after the first grasp, wherever the cube was then: a grasp
that slipped, or fingers that opened on it; ``released`` counts the drops in which
the policy itself commanded the gripper open while it held the cube, before the
first loss); ``stalled`` (held, but the cube never came
:data:`STALL_CM` nearer the goal than it was at the grasp: the arm stays
still, or nearly, with the cube in its fingers); ``near miss`` (within
:data:`NEAR_CM` of the goal at the closest); ``short`` (carried toward the goal,
never within :data:`NEAR_CM`).

With ``--demos DIR`` it also checks the open-loop fit where it matters: on the
demonstrations' own states after the grasp, the first predicted action's
vertical component against the demonstrated one, near the goal (cube within
5 cm of it, where the planner slows down) and farther away. A policy that fits
these well and still overshoots in closed loop fails from compounding errors,
not from underfitting.

Writes ``benchmarks/results/pick_progress.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import markdown_table, probe_parser, probed_episode, run_probe, save_figure, write_results  # noqa: E402

TASK = "PickCube-v1"
#: The TCP's orientation (quaternion, w x y z) in PickCube-v1's observation state, privileged or proprio alike:
#: qpos (9), qvel (9), is_grasped (1), then the TCP pose: position (3) and this quaternion.
TCP_QUATERNION = slice(22, 26)


def tilt_deg(start: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Angle (degrees) between the pointing (local z) axes of orientations ``q [..., 4]`` and ``start [..., 4]``
    (quaternions w x y z): how far the gripper tilted, whatever it turned about that axis."""
    def z_axis(quat):
        w, x, y, z = quat.unbind(-1)
        return torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)

    a, b = z_axis(start), z_axis(q)
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def probe(task) -> tuple[bool, list[float], torch.Tensor]:
    """(the gripper holds the cube, cube - goal in cm, the TCP's orientation)."""
    offset = 100 * (task.cube.pose.p - task.goal_site.pose.p).reshape(-1)[:3]
    quaternion = torch.as_tensor(task.agent.tcp.pose.q).reshape(-1)[:4].float()
    return bool(task.agent.is_grasping(task.cube).any()), [round(float(v), 2) for v in offset], quaternion


#: A cube that never comes this much nearer the goal than it was at the grasp has "stalled" (cm).
STALL_CM = 2.0
#: "Near the goal": the near-miss radius of :func:`failure_mode`, and the open-loop fit's split (cm).
NEAR_CM = 5.0
FAILURE_MODES = ("never grasped", "dropped", "stalled", "near miss", "short")


def failure_mode(episode: dict) -> str | None:
    """Why a probed episode failed, one of :data:`FAILURE_MODES` (the first that applies); None if it succeeded."""
    if episode["success"]:
        return None
    grasped_at = episode["grasped_at_decision"]
    if grasped_at is None:
        return "never grasped"
    if episode["grasp_lost"]:
        return "dropped"
    if episode["closest_cm"] > episode["distance_cm"][grasped_at] - STALL_CM:
        return "stalled"
    return "near miss" if episode["closest_cm"] < NEAR_CM else "short"


#: The gripper entry of a pd_ee_delta_pose action: > 0 opens, < 0 closes.
GRIPPER_DIM = -1


def released(held: list[bool], executed: list) -> bool:
    """Whether the policy commanded the gripper open (:data:`GRIPPER_DIM` > 0 in an executed action) at a decision
    that began with the cube held, before the first decision at which the cube was no longer held."""
    grasped = False
    for hold, actions in zip(held, executed):
        if grasped and not hold:
            return False  # lost before any release: it slipped
        grasped = grasped or hold
        if hold and bool((actions[:, GRIPPER_DIM] > 0).any()):
            return True
    return False


def rollout(penv, seed: int, max_decisions: int) -> dict:
    executed = []
    probes, success = probed_episode(penv, seed, max_decisions, probe, executed)
    held = [h for h, _, _ in probes]
    grasped_at = next((i for i, h in enumerate(held) if h), None)
    distance = [float(torch.tensor(o).norm()) for _, o, _ in probes]
    after = range(grasped_at, len(probes)) if grasped_at is not None else range(0)
    orientation = torch.stack([q for _, _, q in probes])  # (decisions, 4)
    episode = {
        "seed": seed, "success": success, "grasped_at_decision": grasped_at,
        "grasp_lost": sum(a and not b for a, b in zip(held, held[1:])),  # held -> not held, decision to decision
        "closest_cm": round(min(distance[i] for i in after), 2) if after else None,
        "max_above_goal_cm": round(max(probes[i][1][2] for i in after), 2) if after else None,
        "final_cm": round(distance[-1], 2), "distance_cm": [round(d, 2) for d in distance],
        "max_tilt_deg": round(float(tilt_deg(orientation[:1], orientation).max()), 2),
    }
    episode["failure_mode"] = failure_mode(episode)
    episode["released"] = episode["failure_mode"] == "dropped" and released(held, executed)
    return episode


def demo_tilt(demos: Path) -> dict:
    """Largest tilt of the gripper in each demonstration (from the TCP pose in its states), summarised."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.keys import STATE_KEY

    buffer = DemoBuffer.open(demos, task=TASK)
    tilts = [float(tilt_deg(q[:1], q).max()) for q in (e.get(STATE_KEY)[:, TCP_QUATERNION] for e in buffer.episodes())]
    return {"demos": str(demos), "episodes": len(tilts), "median_max_tilt_deg": round(statistics.median(tilts), 2),
            "max_tilt_deg": round(max(tilts), 2)}


def demo_fit(actor, demos: Path) -> dict:
    """Open-loop vertical-action error on the demonstrations' grasped states, near / far from the goal."""
    from mmada_rl.data import DemoBuffer
    from mmada_rl.keys import ACTION_CHUNK_KEY, ACTION_KEY, STATE_KEY

    buffer = DemoBuffer.open(demos, task=TASK)
    if buffer.metadata.obs_mode != "state":
        raise ValueError(f"--demos needs demonstrations recorded with --obs-mode state (the cube's offset from the goal "
                         f"is read from the state); {demos} holds {buffer.metadata.obs_mode!r} observations.")
    rows = {"near": [], "far": []}
    with torch.no_grad():
        for episode in buffer.episodes():
            obs = episode.exclude("next", ACTION_KEY)
            predicted = actor(obs.clone()).get(ACTION_CHUNK_KEY)[:, 0, 2]  # (T,) first action, z
            state, demonstrated = episode.get(STATE_KEY), episode.get(ACTION_KEY)[:, 2]
            near = 100 * state[:, -3:].norm(dim=-1) < NEAR_CM  # PickCube's state ends with goal - cube
            held = state[:, 18] > 0.5  # is_grasped
            for name, mask in (("near", held & near), ("far", held & ~near)):
                rows[name] += torch.stack([demonstrated[mask], predicted[mask]], -1).tolist()
    out = {}
    for name, pairs in rows.items():
        t = torch.tensor(pairs).reshape(-1, 2)
        out[name] = {"states": len(pairs), "demo_z_mean": round(float(t[:, 0].mean()), 4) if pairs else None,
                     "predicted_z_mean": round(float(t[:, 1].mean()), 4) if pairs else None,
                     "abs_error_z": round(float((t[:, 1] - t[:, 0]).abs().mean()), 4) if pairs else None}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = probe_parser(__doc__, "pick_progress", TASK)
    parser.add_argument("--demos", type=Path, default=None, help="also measure the open-loop fit on these "
                        "PickCube-v1 demonstrations (state observations; for a policy that reads the state)")
    parser.add_argument("--demo-tilt", type=Path, default=None, help="also report how far the gripper tilts in "
                        "these PickCube-v1 demonstrations (any observation mode)")
    args = parser.parse_args(argv)

    episodes, penv = run_probe(args, TASK, rollout, show=lambda e: {k: v for k, v in e.items() if k != "distance_cm"})

    held = [e for e in episodes if e["grasped_at_decision"] is not None]
    median = lambda key: statistics.median(e[key] for e in held) if held else None  # noqa: E731
    summary = {"episodes": len(episodes), "successes": sum(e["success"] for e in episodes), "grasped": len(held),
               "median_closest_cm": median("closest_cm"), "median_max_above_goal_cm": median("max_above_goal_cm"),
               "median_final_cm": median("final_cm"),
               "median_max_tilt_deg": statistics.median(e["max_tilt_deg"] for e in episodes),
               "failures": {mode: sum(e["failure_mode"] == mode for e in episodes) for mode in FAILURE_MODES},
               "dropped_released": sum(bool(e.get("released")) for e in episodes)}
    payload = {"checkpoint": str(args.checkpoint), "task": TASK, "action_readout": args.action_readout,
               "demo_seeds": args.demo_seeds, "summary": summary, "episodes": episodes}
    readout = f" ({args.action_readout} read-out)" if args.action_readout else ""
    seeds = (f"{args.episodes} evaluation seeds" if args.demo_seeds is None
             else f"the initial states of the first {args.episodes} demonstrations in `{args.demo_seeds}`")
    fit_table = ""
    if args.demos is not None:
        payload["demo_fit"] = fit = demo_fit(penv.actor, args.demos)
        fit_table = "\n\nOpen loop on the demonstrations' grasped states (`{}`), vertical action:\n\n{}\n".format(
            args.demos, markdown_table(["cube–goal", "states", "demonstrated z (mean)", "predicted z (mean)", "mean abs error"],
                                       [[f"< {NEAR_CM:g} cm" if k == "near" else f">= {NEAR_CM:g} cm", v["states"],
                                         v["demo_z_mean"], v["predicted_z_mean"], v["abs_error_z"]] for k, v in fit.items()]))
    if args.demo_tilt is not None:
        payload["demo_tilt"] = tilt = demo_tilt(args.demo_tilt)
        fit_table += (f"\n\nThe demonstrations (`{args.demo_tilt}`, {tilt['episodes']} episodes) tilt the gripper by a "
                      f"median {tilt['median_max_tilt_deg']:.1f} degrees at most per episode, "
                      f"{tilt['max_tilt_deg']:.1f} in the worst.\n")
    fmt = lambda v: "–" if v is None else f"{v:.1f}"  # noqa: E731
    table = markdown_table(
        ["episodes", "successes", "grasped", "median closest cube–goal (cm)", "median max height above goal (cm)",
         "median final cube–goal (cm)", "median max tilt (degrees, all episodes)"],
        [[summary["episodes"], summary["successes"], summary["grasped"], fmt(summary["median_closest_cm"]),
          fmt(summary["median_max_above_goal_cm"]), fmt(summary["median_final_cm"]), fmt(summary["median_max_tilt_deg"])]])
    modes = markdown_table([*FAILURE_MODES, "of the drops, released by the policy"],
                           [[*(summary["failures"][m] for m in FAILURE_MODES), summary["dropped_released"]]])
    markdown = (f"# How far the policy gets on PickCube-v1: `{args.checkpoint}`\n\n"
                f"{seeds}, greedy decoding{readout}; distances after the first grasp, "
                f"medians over the episodes that grasped.\n\n{table}\n\n"
                f"The failures by mode (dropped: the grasp lost after it was made, released when the policy opened "
                f"the gripper on the held cube before it was lost; stalled: held, the cube never "
                f"{STALL_CM:g} cm nearer the goal than at the grasp; near miss: within {NEAR_CM:g} cm at the "
                f"closest; short: neither):\n\n{modes}{fit_table}\n")
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
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
