"""Sub-commands ``collect``, ``info`` and ``import-h5``."""
from __future__ import annotations

import argparse
import sys

from mmada_rl.envs.maniskill import EnvConfig


def add_env_arguments(parser: argparse.ArgumentParser, *, task_required: bool = True) -> None:
    """The :class:`EnvConfig` fields as command-line options (shared by every env-using command)."""
    d = EnvConfig.__dataclass_fields__
    parser.add_argument("--task", required=task_required, default=d["task"].default, help="ManiSkill3 task id, e.g. PickCube-v1.")
    parser.add_argument("--control-mode", default=d["control_mode"].default, help="ManiSkill controller the actions are recorded in (default: %(default)s).")
    parser.add_argument("--obs-mode", default=d["obs_mode"].default, choices=["rgb", "state"], help="rgb: camera image + proprioception; state: privileged state vector (default: %(default)s).")
    parser.add_argument("--image-size", type=int, default=d["image_size"].default, help="camera image side in pixels (default: %(default)s).")
    parser.add_argument("--camera-fov", type=float, default=None, help="field of view of the task's camera in degrees "
                        "(default: the task's own, 90 for the tabletop tasks; 45 puts ~6x the pixels on a cube).")
    parser.add_argument("--reward", default=d["reward"].default, choices=["dense", "sparse"], help="reward recorded with each step (default: %(default)s).")
    parser.add_argument("--max-episode-steps", type=int, default=None, help="episode length limit (default: the task registry's).")


def env_config_from_args(args: argparse.Namespace) -> EnvConfig:
    return EnvConfig(
        task=args.task,
        control_mode=args.control_mode,
        obs_mode=args.obs_mode,
        image_size=args.image_size,
        camera_fov=args.camera_fov,
        reward=args.reward,
        max_episode_steps=args.max_episode_steps,
    )


def _run_collect(args: argparse.Namespace) -> int:
    from mmada_rl.data.collect import collect
    from mmada_rl.data.collect_workers import CollectionWorkerError

    try:
        result = collect(
            args.out,
            env_config_from_args(args),
            episodes=args.episodes,
            policy=args.policy,
            checkpoint=args.checkpoint or (),
            only_success=args.only_success,
            keep_after_success=args.keep_after_success,
            action_noise=args.action_noise,
            seed=args.seed,
            max_attempts=args.max_attempts,
            workers=args.workers,
        )
    except KeyboardInterrupt:
        from mmada_rl.data.buffer import DemoBuffer

        buf = DemoBuffer.open(args.out)
        print(f"\ninterrupted: {buf.metadata.num_episodes} finished episodes are kept in {args.out}; "
              "run the same command again to resume.", file=sys.stderr)
        return 130
    except (FileNotFoundError, ValueError, CollectionWorkerError) as err:
        print(f"mmada-rl collect: error: {err}", file=sys.stderr)
        return 2
    print(result.buffer.summary())
    print(f"this run        {result.new_episodes} new episodes from {result.attempts} attempts "
          f"({100 * result.success_rate:.1f}% {args.policy} success), {result.steps} steps in {result.seconds:.1f} s")
    for reason, count in sorted(result.failures.items()):
        print(f"  not kept: {count} × {reason}")
    if result.buffer.metadata.num_episodes < args.episodes:
        print(f"stopped after {result.attempts} attempts with {result.buffer.metadata.num_episodes}/{args.episodes} "
              "episodes; run again to continue, or raise --max-attempts.", file=sys.stderr)
        return 1
    return 0


def _run_merge(args: argparse.Namespace) -> int:
    from mmada_rl.data.buffer import merge_buffers

    try:
        merged = merge_buffers(args.out, args.buffers)
    except (FileExistsError, FileNotFoundError, ValueError) as err:
        print(f"mmada-rl merge: error: {err}", file=sys.stderr)
        return 2
    print(merged.summary())
    return 0


def _run_relabel(args: argparse.Namespace) -> int:
    from mmada_rl.data.relabel import relabel_buffer

    try:
        relabelled = relabel_buffer(args.demos, args.checkpoint, args.out, batch_size=args.batch_size, device=args.device)
    except (FileExistsError, FileNotFoundError, ValueError) as err:
        print(f"mmada-rl relabel: error: {err}", file=sys.stderr)
        return 2
    print(relabelled.summary())
    return 0


def _run_info(args: argparse.Namespace) -> int:
    from mmada_rl.data.buffer import DemoBuffer

    try:
        buffer = DemoBuffer.open(args.path)
    except (FileNotFoundError, ValueError) as err:
        print(f"mmada-rl info: error: {err}", file=sys.stderr)
        return 2
    print(buffer.summary())
    return 0


def _run_import(args: argparse.Namespace) -> int:
    from mmada_rl.data.h5_import import import_h5, read_trajectory_json

    try:
        args.task = args.task or read_trajectory_json(args.h5)["env_info"]["env_id"]
        result = import_h5(args.h5, args.out, env_config_from_args(args), only_success=not args.keep_failures)
    except (FileNotFoundError, ValueError) as err:
        print(f"mmada-rl import-h5: error: {err}", file=sys.stderr)
        return 2
    print(result.buffer.summary())
    print(f"imported {result.imported} trajectories" + "".join(f"; skipped {n} × {r}" for r, n in result.skipped.items()))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "collect",
        help="record demonstrations (motion planner) or rollouts (random or trained policy) into a buffer directory",
        description="Record episodes into a TorchRL replay buffer on disk. Re-running the same command resumes; "
        "an interrupted run keeps every finished episode.",
    )
    add_env_arguments(p)
    p.add_argument("--episodes", type=int, required=True, help="number of episodes the buffer should hold in the end.")
    p.add_argument("--out", required=True, help="buffer directory (created, or resumed if it already holds one; a buffer is "
                   "allocated for the --episodes it was created with, so grow one by collecting anew with more).")
    p.add_argument("--policy", default="planner", choices=["planner", "scripted", "random", "checkpoint"],
                   help="planner: ManiSkill's motion-planning solution converted to --control-mode; scripted: a state-based "
                   "expert (PickCube, PushCube, PullCube; pd_ee_delta_pose); random: uniform actions; checkpoint: the "
                   "trained policy of --checkpoint, decoding greedily and executing whole chunks as `mmada-rl eval` does, "
                   "each episode ending at its first success or the time limit (default: %(default)s).")
    p.add_argument("--checkpoint", nargs="+", default=None, metavar="PATH",
                   help="with --policy checkpoint: the policy's run, checkpoint or model directory; two or more act as "
                   "one ensemble. The buffer takes the policy's camera, image size and observation mode.")
    p.add_argument("--only-success", default=None, action=argparse.BooleanOptionalAction,
                   help="keep only episodes reaching the task's success (default: yes for planner and scripted, no for "
                   "random and checkpoint).")
    p.add_argument("--keep-after-success", action="store_true",
                   help="planner only: record each demonstration to the end of the planner's path (the arm slowing "
                   "down to a stop at the goal) instead of ending it at the first success.")
    p.add_argument("--action-noise", type=float, default=0.0, metavar="STD",
                   help="planner only: execute every action with Gaussian noise of this std on the arm (normalised "
                   "units) and record the exact one; the closed-loop conversion steers back at the next step, so the "
                   "demonstrations show recoveries (DART; default: %(default)s, no noise).")
    p.add_argument("--seed", type=int, default=0, help="first env seed of a new buffer (default: %(default)s).")
    p.add_argument("--max-attempts", type=int, default=None, help="give up after this many attempts (default: 3 × missing episodes + 10).")
    p.add_argument("--workers", type=int, default=1,
                   help="processes trying episodes side by side, each with its own simulator (about one per CPU core). "
                        "The seeds are tried and kept in the order one process takes them; an episode can differ from "
                        "one process's in the last digits, since a simulator carries a little state from one attempt "
                        "to the next, and a given number of workers records the same buffer every time "
                        "(default: %(default)s).")
    p.set_defaults(func=_run_collect)

    p = sub.add_parser(
        "merge",
        help="concatenate buffers of one task and setting into a new buffer",
        description="Write a new buffer holding every episode of the given buffers, in order, with their seeds and "
        "instructions (e.g. planner demonstrations and a trained policy's rollouts, for one pretraining run's "
        "data.dir). The buffers must share task, control mode, observation mode, image size, camera and reward.",
    )
    p.add_argument("buffers", nargs="+", help="buffer directories, two or more")
    p.add_argument("--out", required=True, help="new buffer directory (must not hold a buffer)")
    p.set_defaults(func=_run_merge)

    p = sub.add_parser(
        "relabel",
        help="copy a buffer with a teacher policy's predicted chunk stored for every step (to distil it)",
        description="Write a new buffer holding every episode of --demos and, for each step, the action chunk the "
        "teacher (--checkpoint: one policy, or several as one ensemble) predicts from that step's observation, "
        "decoding greedily as it does in evaluation. A student trained on it with data.teacher_labels=true learns "
        "the teacher's chunks on the demonstrations' own observations; no episode is added and nothing is simulated.",
    )
    p.add_argument("--checkpoint", nargs="+", required=True, metavar="PATH",
                   help="the teacher's run, checkpoint or model directory; two or more act as one ensemble.")
    p.add_argument("--demos", required=True, help="the buffer to relabel")
    p.add_argument("--out", required=True, help="new buffer directory (must not hold a buffer)")
    p.add_argument("--batch-size", type=int, default=64, help="observations decoded per forward pass (default: %(default)s).")
    p.add_argument("--device", default="cpu", help="where the teacher runs (default: %(default)s).")
    p.set_defaults(func=_run_relabel)

    p = sub.add_parser("info", help="print a buffer's summary", description="Print what a buffer directory holds.")
    p.add_argument("path", help="buffer directory")
    p.set_defaults(func=_run_info)

    p = sub.add_parser(
        "import-h5",
        help="import ManiSkill .h5/.json trajectories into a buffer",
        description="Re-simulate ManiSkill RecordEpisode trajectories (.h5 + .json) from their seeds and record them in our buffer format.",
    )
    p.add_argument("h5", help="path of the .h5 file (its .json must sit beside it)")
    add_env_arguments(p, task_required=False)
    p.set_defaults(task=None)
    p.add_argument("--out", required=True, help="buffer directory")
    p.add_argument("--keep-failures", action="store_true", help="also import trajectories that do not succeed after replay.")
    p.set_defaults(func=_run_import)
