"""Chunk-level advantages for fine-tuning: group-relative or plain Monte-Carlo episode returns.

A decision is one executed chunk (a macro-action). Learned-value advantages use
TorchRL's :class:`~torchrl.objectives.value.GAE` directly on the chunk-level
transitions, with the discount ``gamma ** k`` of ``k`` executed steps (the
chunk's reward is already its discounted sum, :class:`~mmada_rl.policy.execution.ChunkReward`).
The critic-free alternative below compares rollouts that started from the same
initial state, as TorchRL's ``vla_grpo`` recipe (SimpleVLA-RL) does; or, with
no baseline at all, takes each episode's return as the advantage of its decisions
(with a sparse success reward and binary weights: imitate the successful rollouts).
Each decision's discounted return to its episode's end (:func:`returns_to_go`) can
be compared with what recent episodes returned from the same decision index
(:class:`DecisionIndexBaseline`): a baseline that depends on the time alone, not on
the state, so the advantage says how much better than usual the rest of this
episode went, not how close to its end the decision was.

Episodes end at the first success (ManiSkill's ``success_once``), so an
undiscounted or discounted sum of positive dense rewards favours lingering next
to the goal over finishing: PickCube-v1's normalised dense reward pays about 0.57
per step once the cube sits at the goal unsettled, 1 on the success step, and
nothing after it. :func:`absorbing_success_reward` makes the success an absorbing
state that keeps paying the best per-step reward, so that finishing is worth most.
"""
from __future__ import annotations

from collections import deque

import torch

__all__ = ["DecisionIndexBaseline", "absorbing_success_reward", "group_relative_advantages", "returns_to_go"]


def group_relative_advantages(returns: torch.Tensor, groups: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Standardise episode returns within groups of rollouts from one initial state.

    Args:
        returns: float ``[E]``, one return per episode.
        groups: int ``[E]``, the group of each episode (e.g. its reset seed).
        eps: added to the standard deviation; a group whose returns are all equal
            gets advantage 0 everywhere (nothing to learn from it).

    Returns:
        float ``[E]``: ``(R - mean_g) / (std_g + eps)`` with the population std of the group.

    Examples:
        >>> group_relative_advantages(torch.tensor([1., 0., 1., 1.]), torch.tensor([7, 7, 8, 8]))
        tensor([ 1.0000, -1.0000,  0.0000,  0.0000])
    """
    if returns.shape != groups.shape or returns.ndim != 1:
        raise ValueError(f"returns and groups must be 1-d of one shape, got {tuple(returns.shape)} and {tuple(groups.shape)}.")
    _, index = torch.unique(groups, return_inverse=True)
    n = int(index.max()) + 1 if index.numel() else 0
    returns = returns.float()
    count = torch.zeros(n).index_add(0, index, torch.ones_like(returns))
    mean = torch.zeros(n).index_add(0, index, returns) / count
    var = torch.zeros(n).index_add(0, index, (returns - mean[index]) ** 2) / count
    std = var.sqrt()
    adv = (returns - mean[index]) / (std[index] + eps)
    return torch.where(std[index] > 0, adv, torch.zeros_like(adv))


def absorbing_success_reward(reward: torch.Tensor, success: torch.Tensor, executed: torch.Tensor, gamma: float,
                             success_reward: float = 1.0) -> torch.Tensor:
    """Chunk rewards with each success treated as absorbing: the value of staying in it added to its chunk.

    A chunk that ran ``j`` steps and ended the episode in success gains
    ``success_reward * gamma**j / (1 - gamma)``, the discounted sum of the per-step
    reward ``success_reward`` from the step after the success on (1 for
    ManiSkill's normalised dense reward and for the sparse one). Other chunks are
    unchanged. Bootstrapping stops at the success as before (it is a terminal
    transition); its value is now in the reward.

    Args:
        reward: float ``[*B, 1]`` (or ``[*B]``), each chunk's discounted reward sum.
        success: bool, the ``success`` flag after each chunk, shaped as ``reward``.
        executed: int ``[*B]``, env steps each chunk ran.
        gamma: per-step discount, ``0 < gamma < 1``.
        success_reward: the per-step reward of the absorbing success state.

    Returns:
        float, shaped as ``reward``.

    Examples:
        >>> reward = torch.tensor([[0.5], [1.5]])
        >>> absorbing_success_reward(reward, torch.tensor([[False], [True]]), torch.tensor([5, 2]), gamma=0.5)
        tensor([[0.5000],
                [2.0000]])
    """
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"an absorbing success needs a discount 0 < gamma < 1 (its value is 1 / (1 - gamma)), got {gamma!r}.")
    if success.shape != reward.shape:
        raise ValueError(f"success must be shaped as reward, got {tuple(success.shape)} and {tuple(reward.shape)}.")
    steps = executed.reshape(*executed.shape, *([1] * (reward.ndim - executed.ndim))).to(reward.dtype)
    bonus = success_reward * gamma ** steps / (1.0 - gamma)
    return reward + success.to(reward.dtype) * bonus


def returns_to_go(rewards: torch.Tensor, gamma: float, final_value: float = 0.0) -> torch.Tensor:
    """Discounted return from every step of one episode: ``G_t = sum_{i >= t} gamma**(i - t) r_i + gamma**(T - t) V_T``.

    Args:
        rewards: float ``[T]``, the episode's per-step rewards.
        gamma: per-step discount, ``0 < gamma <= 1``.
        final_value: ``V_T``, the value of the state after the last step: 0 where the
            episode terminated, ``1 / (1 - gamma)`` after an absorbing success
            (:func:`absorbing_success_reward`).

    Returns:
        float ``[T]``.

    Examples:
        >>> returns_to_go(torch.tensor([0.0, 1.0, 1.0]), gamma=0.5)
        tensor([0.7500, 1.5000, 1.0000])
        >>> returns_to_go(torch.tensor([0.0, 1.0]), gamma=0.5, final_value=2.0)   # success absorbing at reward 1
        tensor([1., 2.])
    """
    if rewards.ndim != 1:
        raise ValueError(f"rewards must be 1-d (one episode), got shape {tuple(rewards.shape)}.")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}.")
    out = torch.empty_like(rewards, dtype=torch.float32)
    running = float(final_value)
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = float(rewards[t]) + gamma * running
        out[t] = running
    return out


class DecisionIndexBaseline:
    """Returns to go relative to recent episodes at the same decision index, in units of their spread.

    A decision's discounted return to its episode's end grows towards the end of a
    successful episode (the absorbing success is discounted less), so on a task the
    policy mostly solves, standardising returns to go over a batch ranks the early
    decisions of every successful episode below its late ones and pushes them down.
    This baseline keeps the returns to go of the last ``episodes`` finished episodes
    and gives decision ``t`` of a new one the advantage ``(G_t - b_t) / s``, where
    ``b_t`` is the mean return to go at index ``t`` over the kept episodes that lasted
    beyond ``t`` (a baseline of time alone, the REINFORCE baseline's time-dependent
    form) and ``s`` the root mean square of every kept decision's ``G - b``. An
    episode that went as the recent ones did scores about 0 throughout; one that
    finished sooner scores above, one that failed below.

    :meth:`__call__` adds the episode to the window before it scores it, so the
    first episode scores 0 everywhere and an episode's own return weighs ``1 / n``
    in the baseline of an index ``n`` kept episodes reached.

    Args:
        episodes: how many recent episodes the baseline and the spread average over.
        eps: the least spread divided by.

    Examples:
        >>> baseline = DecisionIndexBaseline(episodes=10)
        >>> baseline(torch.tensor([2.0, 4.0]))             # the first episode: no other to compare with
        tensor([0., 0.])
        >>> baseline(torch.tensor([4.0, 6.0, 8.0]))        # better at both shared indices; index 2 alone
        tensor([1.1180, 1.1180, 0.0000])
    """

    def __init__(self, episodes: int, eps: float = 1e-6) -> None:
        if int(episodes) < 1:
            raise ValueError(f"the baseline needs at least one episode, got episodes={episodes!r}.")
        self.episodes, self.eps = int(episodes), float(eps)
        self.window: deque[torch.Tensor] = deque(maxlen=self.episodes)

    def __len__(self) -> int:
        return len(self.window)

    def state_dict(self) -> dict:
        """The kept episodes' returns to go (checkpointed, so that a resumed run scores as it would have)."""
        return {"episodes": self.episodes, "window": [g.clone() for g in self.window]}

    def load_state_dict(self, state: dict) -> None:
        """Keep the saved episodes' returns to go; this baseline's own ``episodes`` stays the window's
        length, so a resumed run with a shorter window keeps the most recent saved episodes."""
        self.window = deque((torch.as_tensor(g).float() for g in state["window"]), maxlen=self.episodes)

    def mean_by_index(self) -> torch.Tensor:
        """Float ``[L]``: the mean return to go at each index over the kept episodes that reached it."""
        length = max(g.shape[0] for g in self.window)
        total, count = torch.zeros(length), torch.zeros(length)
        for g in self.window:
            total[: g.shape[0]] += g
            count[: g.shape[0]] += 1
        return total / count

    def __call__(self, to_go: torch.Tensor) -> torch.Tensor:
        """Float ``[T]``: the advantages of one finished episode's returns to go ``[T]`` (then kept)."""
        if to_go.ndim != 1:
            raise ValueError(f"returns to go must be 1-d (one episode), got shape {tuple(to_go.shape)}.")
        to_go = to_go.detach().float().cpu()
        self.window.append(to_go)
        mean = self.mean_by_index()
        residuals = torch.cat([g - mean[: g.shape[0]] for g in self.window])
        spread = residuals.pow(2).mean().sqrt().clamp_min(self.eps)
        return (to_go - mean[: to_go.shape[0]]) / spread
