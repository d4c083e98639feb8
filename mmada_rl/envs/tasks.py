"""Registry of ManiSkill3 tasks: natural-language instruction, episode length, planner.

One place for per-task facts. Any other ManiSkill task id still works with
:func:`task_spec`; it gets a generic instruction and ManiSkill's own defaults.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class TaskSpec:
    """Facts about one ManiSkill3 task.

    Attributes:
        task_id: the ManiSkill environment id, e.g. ``"PickCube-v1"``.
        instruction: the natural-language instruction given to the policy.
        max_episode_steps: episode length used for collection and evaluation.
            ManiSkill's own limit (50 for PickCube-v1) is shorter than its motion
            planner's solutions (70-120 steps); we use the lengths of ManiSkill's
            imitation-learning baselines instead.
        planner: name of the ``mani_skill.examples.motionplanning.panda.solutions``
            function that solves the task, or ``None`` when there is none.
        registered: False for tasks outside the registry (generic instruction).
        stages: ManiSkill's own progress flags of the task (entries of its
            ``evaluate()`` info), in the order a successful episode reaches them;
            evaluation reports the share of episodes that reach each
            (``EnvConfig.stage_flags``).
    """

    task_id: str
    instruction: str
    max_episode_steps: int | None
    planner: str | None
    registered: bool = True
    stages: tuple[str, ...] = ()


TASKS: dict[str, TaskSpec] = {
    spec.task_id: spec
    for spec in (
        TaskSpec("PickCube-v1", "pick up the red cube and move it to the green goal", 100, "solvePickCube",
                 stages=("is_grasped", "is_obj_placed")),
        TaskSpec("PushCube-v1", "push the cube to the red and white target", 100, "solvePushCube"),
        TaskSpec("StackCube-v1", "stack the red cube on top of the green cube", 200, "solveStackCube",
                 stages=("is_cubeA_grasped", "is_cubeA_on_cubeB")),
        TaskSpec("PullCube-v1", "pull the cube back to the red and white target", 100, "solvePullCube"),
        TaskSpec("PegInsertionSide-v1", "insert the peg into the hole in the box from the side", 200, "solvePegInsertionSide"),
        TaskSpec("LiftPegUpright-v1", "lift the peg lying on the table upright", 200, "solveLiftPegUpright"),
        TaskSpec("PlaceSphere-v1", "place the sphere into the shallow bin", 100, "solvePlaceSphere"),
        TaskSpec("PushT-v1", "push the T-shaped block onto the T-shaped goal", 100, None),
    )
}

#: Tasks the test suite builds and rolls out.
SUPPORTED_TASKS = ("PickCube-v1", "PushCube-v1", "StackCube-v1", "PullCube-v1", "PegInsertionSide-v1")


class UnknownTaskError(ValueError):
    """A task id that ManiSkill does not register."""


def registered_maniskill_ids() -> list[str]:
    """All environment ids ManiSkill registers (imports ``mani_skill.envs``)."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    from mani_skill.utils.registration import REGISTERED_ENVS

    return sorted(set(REGISTERED_ENVS) & set(gym.registry))


def task_spec(task_id: str) -> TaskSpec:
    """Return the :class:`TaskSpec` of ``task_id``.

    Registered tasks return their entry; any other id that ManiSkill registers
    returns a spec with a generic instruction. Unknown ids raise
    :class:`UnknownTaskError` listing the supported ones.
    """
    if task_id in TASKS:
        return TASKS[task_id]
    if task_id in registered_maniskill_ids():
        name = task_id.rsplit("-v", 1)[0]
        return TaskSpec(task_id, f"complete the {name} task", None, None, registered=False)
    raise UnknownTaskError(
        f"Unknown task {task_id!r}. Supported and tested: {', '.join(SUPPORTED_TASKS)}; "
        f"also registered with an instruction: "
        f"{', '.join(t for t in TASKS if t not in SUPPORTED_TASKS)}. Any other ManiSkill3 "
        "task id that builds without asset downloads works too (`mmada-rl tasks --all` lists them)."
    )


def task_option(value, task: str, option: str, what: str, hint: str):
    """``task``'s value of a per-task option: ``value`` itself (one value for every task), or its entry when
    ``value`` maps each task to its own (a multi-task run whose tasks differ, e.g. in camera or buffer).

    Raises:
        ValueError: ``value`` is a mapping without ``task`` (naming ``option``, the ``what`` it gives, and
            ``hint``, what to add).
    """
    if isinstance(value, Mapping):
        if task not in value:
            raise ValueError(f"{option} gives the {what} of {sorted(value)} but not of {task!r}; add {task}: {hint}.")
        return value[task]
    return value
