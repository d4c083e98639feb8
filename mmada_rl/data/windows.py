"""Chunk windows from stored episodes: state at ``t``, actions ``t..t+K-1``, goal frame ``t+K``.

A window of a ``K``-step chunk covers the ``K + 1`` stored transitions
``t .. t+K`` of one episode. :class:`ChunkWindowSampler` (a TorchRL
``SliceSampler``) draws ``t`` uniformly over *every* step of every episode —
also the last ``K`` steps, whose windows run past the episode end — and never
mixes two episodes: positions past the end repeat the episode's last transition
and are flagged invalid. :class:`ChunkWindowTransform` then turns each window
into one training sample:

* ``observation`` (image, state), ``instruction_id``, ``episode``, ``step_count`` at ``t``;
* ``("vla_action", "chunk")`` ``[K, A]`` built by TorchRL's ``ActionChunkTransform``,
  which repeats the last action past the episode end, and ``action_is_pad`` ``[K]``;
* ``("goal", "image")``: the frame ``o_{t+K}``. Past the episode end it is
  **clipped to the episode's final frame** (the observation after the last
  action, i.e. ``("next", "observation", "image")`` of the last transition), and
  ``("goal", "is_clipped")`` is True exactly when ``t + K`` lies beyond that
  final frame.

``skip_idle_start=True`` (:func:`make_window_buffer`) draws no window that
starts in an episode's leading run of hold actions (every entry but the last,
the gripper, ~0): ManiSkill's PushCube-v1 planner records 7 such steps before
it moves, so a short chunk taken there teaches the policy to hold still in the
start pose, which it then never leaves (see the chunk-size ablation in docs/results/pretraining.md).
``skip_pauses=ε`` draws no window that starts at *any* step whose arm action is
within ``ε`` of 0: the PickCube-v1 planner also nearly stops (arm actions
~0.01) for the ~6 steps in which it closes the gripper and between its motion
segments, and a policy that learns "still arm here → stay still" copies the
pause instead of the motion after it (the copycat problem). Those steps still
appear inside windows that start before them.

``skip_grasp_hold=ε`` draws no window that starts in the hold after a grasp:
from an episode's first gripper close (the last action entry turning negative
after a non-negative one) up to its lift: the first step from which
:data:`LIFT_RUN` consecutive actions move the end effector up (action entry 2,
its z) by more than ``ε`` (one such label alone may be DART's correction).
The PickCube-v1 planner closes the gripper, whose fingers stop after ~3 steps,
then keeps the arm near still for a median 9 more steps before it lifts; with
DART's noise its labels there are small corrections (often downwards), so
``skip_pauses`` cannot find them. The state does not change in that hold, so a
policy that learns "grasped, cube on the table → hold" has nothing to leave it
by. Episodes that never close the gripper after
opening it (PushCube-v1's planner keeps it closed) or never lift lose nothing.
With ``grasp_hold_gripper_only=True`` those windows are drawn after all, flagged
(:data:`~mmada_rl.keys.ACTION_GRIPPER_ONLY_KEY`) so that a loss scores only their
gripper entries: the hold's arm labels still teach nothing, but its gripper labels
are the only ones that say "keep the fingers closed" in the states just after a
grasp, where a policy trained without them may open the gripper again.

``teacher_labels=True`` takes each window's chunk from what a teacher policy
predicted at its first step (:data:`~mmada_rl.keys.TEACHER_CHUNK_KEY`, stored by
``mmada-rl relabel``) instead of the demonstrated actions ``t..t+K-1``: a student
distilled from the teacher on the demonstrations' own observations. The window
starts, pads, goal frame and every skip above still follow the demonstration.
"""
from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer
from torchrl.data.replay_buffers.samplers import SliceSampler
from torchrl.envs.transforms import ActionChunkTransform, Compose, Transform

from mmada_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_GRIPPER_ONLY_KEY,
    ACTION_IS_PAD_KEY,
    EPISODE_KEY,
    GOAL_IMAGE_KEY,
    GOAL_IS_CLIPPED_KEY,
    IMAGE_KEY,
    STATE_KEY,
    STEP_KEY,
    TASK_INDEX_KEY,
    TEACHER_CHUNK_KEY,
)

class ChunkWindowSampler(SliceSampler):
    """Samples ``K + 1``-step windows starting at any step of any episode.

    TorchRL's ``SliceSampler`` finds the episodes (from ``traj_key``) and caches
    them; this subclass replaces only how slices are drawn: the start ``t`` is
    uniform over all stored steps (not only those with ``K`` steps after them),
    and positions past the episode end repeat its last index (the transform
    recognises them by their stalled ``step_count``). ``batch_size`` counts transitions, as for
    ``SliceSampler``: it must be a multiple of ``chunk_size + 1``.

    Args:
        chunk_size: ``K``, the number of actions per chunk.
        traj_key: the episode-id key. Defaults to ``"episode"``.
        cache_values: cache episode boundaries (static buffers). Defaults to ``True``.
        no_start: optional bool ``[storage size]``: True steps are never a
            window start (they still appear inside windows that start before
            them). An episode that is all True keeps its last step as a start.
    """

    def __init__(self, chunk_size: int, *, traj_key=EPISODE_KEY, cache_values: bool = True,
                 no_start: torch.Tensor | None = None):
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}.")
        super().__init__(
            slice_len=chunk_size + 1,
            traj_key=traj_key,
            strict_length=False,
            truncated_key=None,
            cache_values=cache_values,
        )
        self.chunk_size = chunk_size
        self.no_start = None if no_start is None else torch.as_tensor(no_start, dtype=torch.bool).reshape(-1)
        self._starts_cache: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    def _window_starts(self, starts: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The allowed start steps of every episode, concatenated, and their per-episode counts;
        computed once per set of episodes."""
        cached = self._starts_cache
        if cached is not None and torch.equal(cached[0], starts) and torch.equal(cached[1], lengths):
            return cached[2], cached[3]
        if self.no_start is None:
            counts = lengths.clone()
            steps = torch.cat([torch.arange(n) for n in lengths.tolist()])
        else:
            per_episode = []
            for start, length in zip(starts.tolist(), lengths.tolist()):
                index = (start + torch.arange(length)) % self.no_start.numel()
                allowed = (~self.no_start[index]).nonzero().reshape(-1)
                per_episode.append(allowed if allowed.numel() else torch.tensor([length - 1]))
            counts = torch.tensor([a.numel() for a in per_episode], dtype=lengths.dtype)
            steps = torch.cat(per_episode)
        self._starts_cache = (starts.clone(), lengths.clone(), steps.to(lengths.device), counts.to(lengths.device))
        return self._starts_cache[2], self._starts_cache[3]

    def sample(self, storage, batch_size: int):
        window = self.chunk_size + 1
        if batch_size % window:
            raise ValueError(
                f"batch_size={batch_size} transitions is not a multiple of the window length "
                f"{window} (chunk_size + 1); ask for num_windows * {window}."
            )
        num_windows = batch_size // window
        start_idx, _, lengths = self._get_stop_and_length(storage)
        starts, lengths = start_idx[:, 0], lengths.to(torch.long)
        steps, counts = self._window_starts(starts, lengths)
        ends = counts.cumsum(0)
        flat = torch.randint(int(ends[-1]), (num_windows,), generator=self._rng, device=lengths.device)
        traj = torch.searchsorted(ends, flat, right=True)  # (N,)
        t = steps[flat]  # step of the window start inside its episode
        pos = t.unsqueeze(-1) + torch.arange(window, device=t.device)  # (N, K+1)
        length = lengths[traj].unsqueeze(-1)
        index = (starts[traj].unsqueeze(-1) + pos.clamp(max=length - 1)) % storage.shape[0]
        return (index.reshape(-1),), {}


class ChunkWindowTransform(Transform):
    """Replay-buffer transform: flat windows ``[N * (K+1)]`` → samples ``[N]`` with chunk and goal.

    Args:
        chunk_size: ``K``.
        with_images: also build the goal image (False for state-only buffers).
        gripper_only_starts: :func:`step_ids` of the steps whose windows score only the gripper; given, every
            sample gets :data:`~mmada_rl.keys.ACTION_GRIPPER_ONLY_KEY` (True where its window starts at one).
        teacher_labels: the chunk is the teacher's, stored with the window's first transition
            (:data:`~mmada_rl.keys.TEACHER_CHUNK_KEY`), not the demonstrated actions; the pad flags stay the
            demonstration's, so steps past the episode end are left unscored either way.
    """

    def __init__(self, chunk_size: int, *, with_images: bool = True, gripper_only_starts: torch.Tensor | None = None,
                 teacher_labels: bool = False):
        out_keys = [ACTION_CHUNK_KEY, ACTION_IS_PAD_KEY, GOAL_IMAGE_KEY, GOAL_IS_CLIPPED_KEY]
        super().__init__(in_keys=[], out_keys=out_keys + ([ACTION_GRIPPER_ONLY_KEY] if gripper_only_starts is not None else []))
        self.chunk_size = chunk_size
        self.with_images = with_images
        self.gripper_only_starts = gripper_only_starts
        self.teacher_labels = teacher_labels
        self._chunker = ActionChunkTransform(chunk_size, done_key="done")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        K = self.chunk_size
        windows = tensordict.reshape(-1, K + 1)  # (N, K+1)
        # a position is real when it is the next step of the same episode; past the
        # end the sampler repeats the last transition, whose step count then stalls
        step = windows.get(STEP_KEY).reshape(windows.shape)  # (N, K+1)
        episode = windows.get(EPISODE_KEY)
        offsets = torch.arange(K + 1, device=step.device)
        valid = (step == step[:, :1] + offsets) & (episode == episode[:, :1])  # (N, K+1)
        first = windows[:, 0]
        out = first.exclude("next", TEACHER_CHUNK_KEY[0])
        if self.teacher_labels:
            out.set(ACTION_CHUNK_KEY, first.get(TEACHER_CHUNK_KEY).to(torch.float32))  # (N, K, A)
        else:
            chunked = self._chunker(windows.select("action", ("next", "done")).clone())
            out.set(ACTION_CHUNK_KEY, chunked.get(ACTION_CHUNK_KEY)[:, 0])  # (N, K, A)
        out.set(ACTION_IS_PAD_KEY, ~valid[:, :K])  # (N, K)
        if self.with_images:
            last = windows[:, K]
            goal = torch.where(
                valid[:, K].view(-1, 1, 1, 1),
                last.get(IMAGE_KEY),
                last.get(("next", *IMAGE_KEY)),
            )
            out.set(GOAL_IMAGE_KEY, goal)
        # clipped when fewer than K valid steps: t + K lies past the final frame
        out.set(GOAL_IS_CLIPPED_KEY, valid.sum(-1) < K)
        if self.gripper_only_starts is not None:
            start = step_ids(episode[:, 0], step[:, 0])
            out.set(ACTION_GRIPPER_ONLY_KEY, torch.isin(start, self.gripper_only_starts.to(start.device)))
        return out


#: :func:`step_ids` packs an episode id and a step index into one number; no episode is this long.
STEP_STRIDE = 1 << 32


def step_ids(episode: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """One long id per stored step, from its episode id and its index in the episode (same shapes)."""
    return episode.long() * STEP_STRIDE + step.long()



def idle_actions(buffer, tol: float = 1e-4) -> torch.Tensor:
    """Bool ``[storage size]``: transitions whose action holds the arm still: every entry but the last
    (the gripper) within ``tol`` of 0 (a planner's hold steps carry ~4e-6 of numerical noise)."""
    actions = buffer.storage[: len(buffer.storage)].get("action")
    return (actions[..., :-1].abs() <= tol).all(-1)


def leading_run(mask: torch.Tensor, bounds) -> torch.Tensor:
    """``mask`` restricted to each episode's leading run of True steps (``bounds``: ``(start, stop)`` per episode)."""
    out = torch.zeros_like(mask)
    for start, stop in bounds:
        moving = (~mask[start:stop]).nonzero()
        out[start:start + (int(moving[0]) if moving.numel() else stop - start)] = True
    return out


#: The z entry of an end-effector delta action (``pd_ee_delta_pos`` / ``pd_ee_delta_pose``).
LIFT_ACTION_DIM = 2
#: Consecutive upward actions that make a lift (:func:`grasp_holds`).
LIFT_RUN = 3


def grasp_holds(buffer, lift: float) -> torch.Tensor:
    """Bool ``[storage size]``: each episode's steps from its first gripper close (the last action entry
    negative after a non-negative one) up to, not including, its lift: the first step that starts
    :data:`LIFT_RUN` consecutive actions whose z entry (:data:`LIFT_ACTION_DIM`) exceeds ``lift``;
    nothing in episodes with no such close or no lift after it."""
    mode = buffer.metadata.control_mode
    if not mode.startswith("pd_ee_delta_pos"):
        raise ValueError(f"skip_grasp_hold finds the lift in an end-effector delta action's z entry; {buffer.path} "
                         f"holds {mode!r} actions (collect with --control-mode pd_ee_delta_pose), or set it to 0.")
    actions = buffer.storage[: len(buffer.storage)].get("action")
    out = torch.zeros(actions.shape[0], dtype=torch.bool)
    for start, stop in buffer.episode_bounds():
        gripper, z = actions[start:stop, -1], actions[start:stop, LIFT_ACTION_DIM]
        closes = ((gripper[1:] < 0) & (gripper[:-1] >= 0)).nonzero()
        if not closes.numel():
            continue
        close = int(closes[0]) + 1
        up = (z[close:] > lift).float()
        if up.numel() < LIFT_RUN:
            continue
        lifts = (up.unfold(0, LIFT_RUN, 1).sum(-1) == LIFT_RUN).nonzero()
        if lifts.numel():
            out[start + close:start + close + int(lifts[0])] = True
    return out


#: The window options of :func:`make_window_buffer` and :class:`MultiTaskWindows`, each with its "off" value.
WINDOW_SKIPS = {"skip_idle_start": False, "skip_pauses": 0.0, "skip_grasp_hold": 0.0, "grasp_hold_gripper_only": False,
                "teacher_labels": False}


def window_skips(options) -> dict:
    """:data:`WINDOW_SKIPS` read from a mapping (a recipe's ``data`` config, or its saved ``config.json``'s):
    each option as the type of its "off" value, off where the mapping lacks it."""
    return {name: type(off)(options.get(name, off)) for name, off in WINDOW_SKIPS.items()}


def no_start_steps(buffer, *, skip_idle_start: bool = False, skip_pauses: float = 0.0,
                   skip_grasp_hold: float = 0.0) -> torch.Tensor | None:
    """The steps no chunk window may start at (``None``: any step), for :func:`make_window_buffer`'s options."""
    for name, value in (("skip_pauses", skip_pauses), ("skip_grasp_hold", skip_grasp_hold)):
        if value < 0:
            raise ValueError(f"{name}={value} must be >= 0 (0: off).")
    masks = []
    if skip_idle_start:
        masks.append(leading_run(idle_actions(buffer), buffer.episode_bounds()))
    if skip_pauses > 0:
        masks.append(idle_actions(buffer, tol=skip_pauses))
    if skip_grasp_hold > 0:
        masks.append(grasp_holds(buffer, lift=skip_grasp_hold))
    if not masks:
        return None
    return torch.stack(masks).any(0)


def every_window(buffer, chunk_size: int, batch_size: int) -> Iterator[TensorDictBase]:
    """The chunk window of every stored step of ``buffer``, in storage order, ``batch_size`` windows at a time
    (the last batch smaller): the samples :func:`make_window_buffer` draws, each step once, none skipped."""
    if chunk_size < 1 or batch_size < 1:
        raise ValueError(f"chunk_size and batch_size must be >= 1, got {chunk_size} and {batch_size}.")
    transform = window_transform(buffer, chunk_size)
    offsets = torch.arange(chunk_size + 1)
    index = torch.cat([start + (torch.arange(stop - start).unsqueeze(-1) + offsets).clamp(max=stop - start - 1)
                       for start, stop in buffer.episode_bounds()])  # (steps, K+1): each step's window, held at its end
    for rows in index.split(batch_size):
        yield transform(buffer.storage[rows.reshape(-1)])


def window_transform(buffer, chunk_size: int, *, gripper_only_starts: torch.Tensor | None = None,
                     teacher_labels: bool = False) -> Compose:
    """What turns ``buffer``'s flat ``K + 1``-transition windows into samples: :class:`ChunkWindowTransform`
    (its options as given), then the instruction text put back."""
    from mmada_rl.data.buffer import InstructionLookup

    return Compose(
        ChunkWindowTransform(chunk_size, with_images=buffer.metadata.obs_mode == "rgb",
                             gripper_only_starts=gripper_only_starts, teacher_labels=teacher_labels),
        InstructionLookup(buffer.metadata.instructions),
    )


def check_teacher_labels(buffer, chunk_size: int, teacher_labels: bool) -> None:
    """Raise a ``ValueError`` unless ``buffer`` holds a teacher's ``chunk_size``-action chunks where
    ``teacher_labels`` asks for them."""
    if not teacher_labels:
        return
    teacher = buffer.metadata.teacher
    if not teacher:
        raise ValueError(f"teacher_labels trains on a teacher's chunks, which {buffer.path} does not hold; write a "
                         f"relabelled copy first: mmada-rl relabel --checkpoint TEACHER --demos {buffer.path} --out DIR.")
    if int(teacher["chunk_size"]) != chunk_size:
        raise ValueError(f"{buffer.path} holds a teacher's chunks of {teacher['chunk_size']} actions, but chunk_size is "
                         f"{chunk_size}; relabel with a teacher of chunk size {chunk_size}.")


def make_window_buffer(buffer, chunk_size: int, batch_size: int | None, *, seed: int | None = None,
                       skip_idle_start: bool = False, skip_pauses: float = 0.0,
                       skip_grasp_hold: float = 0.0, grasp_hold_gripper_only: bool = False,
                       teacher_labels: bool = False) -> ReplayBuffer:
    """A replay buffer over ``buffer``'s storage that samples ``batch_size`` chunk windows.

    Args:
        buffer: a :class:`~mmada_rl.data.buffer.DemoBuffer`.
        chunk_size: ``K``; must not exceed the longest stored episode.
        batch_size: number of windows per ``sample()``; ``None``: ``sample(batch_size=n * (chunk_size + 1))``
            names the number of transitions each time.
        seed: seeds the sampler's generator for reproducible batches.
        skip_idle_start: draw no window that starts in an episode's leading
            hold actions (:func:`idle_actions`; a motion planner's wait before it moves).
        skip_pauses: draw no window that starts at any step whose arm action (every entry but the
            gripper) is within this of 0 (a planner's pauses, e.g. while the gripper closes); 0: off.
        skip_grasp_hold: draw no window that starts between an episode's first gripper close and
            its lift, the first of three consecutive actions raising the end effector by more than
            this (:func:`grasp_holds`); 0: off.
        grasp_hold_gripper_only: draw the windows ``skip_grasp_hold`` finds after all, each flagged
            (:data:`~mmada_rl.keys.ACTION_GRIPPER_ONLY_KEY`) so that only its gripper entries are scored; every
            sample then carries the flag. Needs ``skip_grasp_hold > 0``.
        teacher_labels: each window's chunk is the one a teacher predicted at its first step, stored in a
            buffer relabelled by ``mmada-rl relabel`` (:func:`~mmada_rl.data.relabel_buffer`), instead of the
            demonstrated actions; the teacher's chunk size must be ``chunk_size``.

    Examples:
        >>> rb = make_window_buffer(DemoBuffer.open("data/pickcube"), chunk_size=5, batch_size=32)  # doctest: +SKIP
        >>> batch = rb.sample()  # doctest: +SKIP
        >>> batch["vla_action", "chunk"].shape, batch["goal", "image"].shape  # doctest: +SKIP
        (torch.Size([32, 5, 7]), torch.Size([32, 3, 64, 64]))
    """
    lengths = [b - a for a, b in buffer.episode_bounds()]
    if not lengths:
        raise ValueError(f"buffer {buffer.path} is empty.")
    if chunk_size > max(lengths):
        raise ValueError(
            f"chunk_size={chunk_size} is longer than every episode in {buffer.path} "
            f"(longest: {max(lengths)} steps); use a chunk_size <= {max(lengths)}."
        )
    check_teacher_labels(buffer, chunk_size, teacher_labels)
    gripper_only = None
    if grasp_hold_gripper_only:
        if not skip_grasp_hold > 0:
            raise ValueError("grasp_hold_gripper_only scores only the gripper of the windows that start in the hold "
                             "after a grasp, which skip_grasp_hold finds; set skip_grasp_hold > 0 (e.g. 0.05).")
        stored = buffer.storage[: len(buffer.storage)]
        hold = grasp_holds(buffer, lift=skip_grasp_hold)
        gripper_only = step_ids(stored.get(EPISODE_KEY).reshape(-1), stored.get(STEP_KEY).reshape(-1))[hold]
    no_start = no_start_steps(buffer, skip_idle_start=skip_idle_start, skip_pauses=skip_pauses,
                              skip_grasp_hold=0.0 if grasp_hold_gripper_only else skip_grasp_hold)
    sampler = ChunkWindowSampler(chunk_size, no_start=no_start)
    transform = window_transform(buffer, chunk_size, gripper_only_starts=gripper_only, teacher_labels=teacher_labels)
    # a plain ReplayBuffer: TensorDictReplayBuffer would write the flat per-transition
    # sample indices back into the (already windowed) output and fail on the shape
    return ReplayBuffer(
        storage=buffer.storage,
        sampler=sampler,
        transform=transform,
        batch_size=None if batch_size is None else batch_size * (chunk_size + 1),
        generator=torch.Generator().manual_seed(seed) if seed is not None else None,
    )


def pad_state(state: torch.Tensor, dim: int) -> torch.Tensor:
    """Zero-pad the last dimension of ``state`` to ``dim`` (tasks of one multi-task model differ in state size)."""
    if state.shape[-1] > dim:
        raise ValueError(f"state has {state.shape[-1]} dimensions, more than the {dim} the model was fitted on.")
    if state.shape[-1] == dim:
        return state
    return torch.nn.functional.pad(state, (0, dim - state.shape[-1]))


def check_state_differences(differences, dim: int | None = None) -> list[list[int]]:
    """``differences`` as ``[[a, b], ...]`` pairs of state dimensions (``dim``: the state's size, if known).

    Raises:
        ValueError: an entry is not a pair of two different non-negative dimensions, or
            names a dimension outside ``0..dim-1``.
    """
    pairs = []
    for pair in differences or []:
        pair = [int(d) for d in pair]
        if len(pair) != 2 or pair[0] == pair[1] or min(pair) < 0 or (dim is not None and max(pair) >= dim):
            where = f" of the state's dimensions 0..{dim - 1}" if dim is not None else ""
            raise ValueError(f"state_differences entries must be pairs [a, b] of two different dimensions{where}; "
                             f"got {pair} in {[list(p) for p in differences]}.")
        pairs.append(pair)
    return pairs


def append_state_differences(state: torch.Tensor, differences) -> torch.Tensor:
    """``state`` with ``state[..., a] - state[..., b]`` appended for each pair ``[a, b]`` of ``differences``.

    Relative quantities the policy would otherwise have to work out from two separately
    quantised tokens, e.g. PickCube-v1's goal relative to the gripper:
    ``[[26, 19], [27, 20], [28, 21]]`` (goal position minus TCP position).
    """
    pairs = check_state_differences(differences, state.shape[-1])
    if not pairs:
        return state
    a, b = torch.tensor(pairs, device=state.device).T
    return torch.cat([state, state[..., a] - state[..., b]], dim=-1)


def kept_state_dims(drop, dim: int, option: str) -> list[int]:
    """The state dimensions ``0..dim-1`` a policy reads when the ones in ``drop`` are left out.

    Raises:
        ValueError: ``drop`` (the value of the config field ``option``) names a dimension
            outside the state, or all of them.
    """
    drop = sorted({int(d) for d in drop})
    bad = [d for d in drop if not 0 <= d < dim]
    if bad or len(drop) >= dim:
        raise ValueError(f"{option}={drop} must name some, not all, of the state's dimensions 0..{dim - 1}"
                         + (f" ({bad} are not)." if bad else "."))
    return [d for d in range(dim) if d not in drop]


class MultiTaskWindows:
    """Chunk windows from several demonstration buffers (one per task), mixed in every batch.

    Each window's task is drawn independently with probabilities ``weights``;
    every buffer then samples its share through its own
    :func:`make_window_buffer` (so windows never cross episodes and each keeps
    its instruction text), and the shares are concatenated. States are
    zero-padded to the largest state size (ManiSkill tasks add task-specific
    entries, e.g. PickCube's goal position), and ``task_index`` records the
    buffer each window came from.

    TorchRL's ``ReplayBufferEnsemble`` is not used: with slice samplers it
    splits a batch into equal per-member sub-batches of whole slices, where a
    multi-task batch needs a random number of windows per task.

    Args:
        buffers: the :class:`~mmada_rl.data.buffer.DemoBuffer` of each task.
        chunk_size, batch_size: as for :func:`make_window_buffer`.
        weights: ``"uniform"`` (each task equally often), ``"transitions"``
            (proportional to stored transitions, as one merged buffer would be)
            or one non-negative weight per buffer.
        seed: seeds the task draw and every member's sampler.
        skip_idle_start, skip_pauses, skip_grasp_hold, grasp_hold_gripper_only, teacher_labels: as for
            :func:`make_window_buffer`, in every buffer.

    Examples:
        >>> windows = MultiTaskWindows([pick, push], chunk_size=5, batch_size=16)  # doctest: +SKIP
        >>> batch = windows.sample()  # doctest: +SKIP
        >>> batch["language_instruction"][:2], batch["task_index"][:2]  # doctest: +SKIP
    """

    def __init__(self, buffers, chunk_size: int, batch_size: int, *, weights="uniform", seed: int | None = None,
                 skip_idle_start: bool = False, skip_pauses: float = 0.0, skip_grasp_hold: float = 0.0,
                 grasp_hold_gripper_only: bool = False, teacher_labels: bool = False):
        buffers = list(buffers)
        if not buffers:
            raise ValueError("MultiTaskWindows needs at least one buffer.")
        if isinstance(weights, str):
            if weights not in ("uniform", "transitions"):
                raise ValueError(f"weights must be 'uniform', 'transitions' or one number per buffer, got {weights!r}.")
            weights = [1.0] * len(buffers) if weights == "uniform" else [float(len(b)) for b in buffers]
        weights = torch.as_tensor([float(w) for w in weights])
        if weights.numel() != len(buffers) or (weights < 0).any() or weights.sum() <= 0:
            raise ValueError(f"need one non-negative weight per buffer ({len(buffers)}), not all zero; got {weights.tolist()}.")
        self.buffers = buffers
        self.chunk_size, self.batch_size = int(chunk_size), int(batch_size)
        self.probabilities = weights / weights.sum()
        self.state_dim = max(b.metadata.state_dim for b in buffers)
        self.members = [
            make_window_buffer(b, chunk_size, None, seed=None if seed is None else seed + 1 + i,
                               skip_idle_start=skip_idle_start, skip_pauses=skip_pauses,
                               skip_grasp_hold=skip_grasp_hold, grasp_hold_gripper_only=grasp_hold_gripper_only,
                               teacher_labels=teacher_labels)
            for i, b in enumerate(buffers)
        ]
        self._rng = torch.Generator().manual_seed(seed) if seed is not None else torch.Generator()

    def append_transform(self, transform) -> None:
        """Append ``transform`` to every task's window buffer (as ``ReplayBuffer.append_transform`` does to one)."""
        for member in self.members:
            member.append_transform(transform)

    @property
    def generators(self) -> dict[str, torch.Generator]:
        """Every generator the batches depend on (checkpointed so a resumed run replays the same batches)."""
        out = {"sampler": self._rng}
        out.update({f"sampler_{i}": member._rng for i, member in enumerate(self.members)})
        return out

    def sample(self) -> TensorDictBase:
        tasks = torch.multinomial(self.probabilities, self.batch_size, replacement=True, generator=self._rng)
        parts = []
        for i, member in enumerate(self.members):
            n = int((tasks == i).sum())
            if n == 0:
                continue
            part = member.sample(batch_size=n * (self.chunk_size + 1))
            part.set(STATE_KEY, pad_state(part.get(STATE_KEY), self.state_dim))
            part.set(TASK_INDEX_KEY, torch.full((n,), i, dtype=torch.int64))
            parts.append(part)
        return torch.cat(parts)


def window_generators(data) -> dict[str, torch.Generator]:
    """The generators of a window sampler (:func:`make_window_buffer` or :class:`MultiTaskWindows`), for checkpoints."""
    return data.generators if isinstance(data, MultiTaskWindows) else {"sampler": data._rng}
