"""Sub-command ``tasks``: the task registry, and every ManiSkill3 task id this install can build."""
from __future__ import annotations

import argparse

from mmada_rl.envs.tasks import SUPPORTED_TASKS, TASKS, TaskSpec, registered_maniskill_ids, task_spec


def task_rows(include_all: bool = False) -> list[tuple[str, ...]]:
    """One row per task: id, status, episode steps, planner, progress flags, instruction.

    The registry's tasks first (the tested ones, then those with an instruction of their own); with
    ``include_all`` every other task id ManiSkill registers after them, with the generic instruction
    :func:`~mmada_rl.envs.tasks.task_spec` gives it.
    """
    specs = [TASKS[t] for t in SUPPORTED_TASKS] + [s for t, s in TASKS.items() if t not in SUPPORTED_TASKS]
    if include_all:
        specs += [task_spec(t) for t in registered_maniskill_ids() if t not in TASKS]
    return [_row(spec) for spec in specs]


def _row(spec: TaskSpec) -> tuple[str, ...]:
    status = "tested" if spec.task_id in SUPPORTED_TASKS else "registry" if spec.registered else "generic"
    steps = str(spec.max_episode_steps) if spec.max_episode_steps else "ManiSkill's"
    return (spec.task_id, status, steps, "yes" if spec.planner else "no", ", ".join(spec.stages) or "-", spec.instruction)


_HEADER = ("task", "status", "episode steps", "planner", "progress flags", "instruction")


def _run(args: argparse.Namespace) -> int:
    rows = [_HEADER, *task_rows(args.all)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_HEADER) - 1)]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[-1])
    if not args.all:
        print("\n`mmada-rl tasks --all` also lists every other ManiSkill3 task id (generic instruction, ManiSkill's "
              "episode length; those needing asset downloads fail when built).")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tasks",
        help="list the tasks: instruction, episode length, planner demonstrations, progress flags",
        description="List the task registry (mmada_rl/envs/tasks.py). status: 'tested' tasks are built and rolled "
        "out by the test suite; 'registry' tasks have an instruction and episode length of their own; 'generic' "
        "(with --all) are other ManiSkill3 ids, given a generic instruction. planner: `mmada-rl collect` can record "
        "motion-planner demonstrations. Progress flags: what `mmada-rl eval` reports beside success.",
    )
    p.add_argument("--all", action="store_true",
                   help="also list every other task id ManiSkill3 registers (imports ManiSkill, a few seconds).")
    p.set_defaults(func=_run)
