"""Several MMaDA-VLA policies acting as one: each decodes its chunk, the executed chunk is their average.

Policies trained on the same few demonstrations with different seeds fail on different
episodes: each fits the demonstrations a little differently. A deep ensemble (Lakshminarayanan
et al., 2017) averages their predictions; here each member decodes its chunk greedily from the
same observation, read out its own way (``"mean"`` or ``"token"``, :class:`MMaDAConfig`), and the
chunk executed is the mean of the members' chunks, with each gripper dimension set by the
members' majority (a gripper is -1 or +1, never between; a tie takes the first member's).

An :class:`MMaDAEnsemble` stands where an :class:`MMaDAModel` does for evaluation: wrap it in an
:class:`~mmada_rl.policy.MMaDAActor` (``mmada-rl eval --checkpoint RUN_A RUN_B RUN_C`` does), and
:meth:`decoding` sets the decoding steps and read-out of every member. It decodes greedily only
and has no decoding path of its own (the averaged chunk is no member's sample), so it cannot be
fine-tuned: sampled decoding and decoding-path log-probabilities raise.

    >>> ensemble = MMaDAEnsemble.load(["runs/pick_s0", "runs/pick_s1", "runs/pick_s2"])  # doctest: +SKIP
    >>> chunk = MMaDAActor(ensemble)(env.reset())["vla_action", "chunk"]  # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from mmada_rl.diffusion.sampler import is_greedy
from mmada_rl.policy.model import TOKENIZERS_DIR, MMaDAModel, PolicyOutput

__all__ = ["MMaDAEnsemble", "average_chunks", "average_weights", "check_members", "save_weight_average"]

#: written beside a weight average's model: the policies averaged
AVERAGE_FILE = "average.json"


def check_members(members: Sequence, kind: type, properties: Mapping[str, Callable[[Any], Any]],
                  what: str = "an ensemble") -> list:
    """``members`` as a list, checked to be two or more ``kind`` instances that agree with the first
    on every one of ``properties`` (a name and how to read it); otherwise a ``ValueError`` naming
    the first difference and ``what`` the members make (e.g. ``"a weight average"``)."""
    members = list(members)
    if len(members) < 2 or not all(isinstance(m, kind) for m in members):
        raise ValueError(f"{what} needs two or more {kind.__name__} members, got {[type(m).__name__ for m in members]}.")
    for i, other in enumerate(members[1:], start=1):
        for name, read in properties.items():
            mine, theirs = read(members[0]), read(other)
            if mine != theirs:
                raise ValueError(f"the members of {what} must be alike: member 0 has {name} {mine!r}, member {i} "
                                 f"{theirs!r}.")
    return members


def average_chunks(chunks: torch.Tensor, gripper_dims: Sequence[int] = ()) -> torch.Tensor:
    """The members' chunks ``[M, B, K, A]`` as one ``[B, K, A]``: their mean, and on each of
    ``gripper_dims`` the sign most members give (a gripper is closed or open, never between: the
    mean of two "open" and one "close" would half-close it); a tie takes the first member's value.

    Examples:
        >>> chunks = torch.tensor([[[[0.2, 1.0]]], [[[0.4, -1.0]]], [[[0.6, 1.0]]]])  # M=3, B=1, K=1, A=2
        >>> average_chunks(chunks, gripper_dims=[1])
        tensor([[[0.4000, 1.0000]]])
    """
    chunk = chunks.mean(0)  # (B, K, A)
    grippers = list(gripper_dims)
    if grippers:
        vote = chunks[..., grippers].sign().sum(0)  # (B, K, G): +M all open ... -M all closed
        chunk[..., grippers] = torch.where(vote == 0, chunks[0][..., grippers], vote.sign())
    return chunk


class MMaDAEnsemble(nn.Module):
    """Greedy MMaDA-VLA policies averaged chunk by chunk (see the module docstring).

    Args:
        members: two or more policies that act in the same action space from the same
            observations: the same chunk size, action dimension, image size and cameras,
            all reading the state or none. Their tokenizers may differ (each decodes
            its own tokens). The first member's goal image and decoding path are
            reported with each chunk.
    """

    def __init__(self, members: Sequence[MMaDAModel]) -> None:
        super().__init__()
        members = check_members(members, MMaDAModel, {
            "chunk size": lambda m: m.config.chunk_size,
            "action dimension": lambda m: m.action_tokenizer.action_dim,
            "gripper dimensions": lambda m: m.action_tokenizer.config.gripper_dims,
            "image size": lambda m: m.image_size,
            "cameras (camera_fov)": lambda m: m.config.camera_fov,
            "reads the state": lambda m: m.proprio_tokenizer is not None,
        })  # fmt: skip
        self.members = nn.ModuleList(members)

    @classmethod
    def load(cls, directories: Sequence[str | Path], *, device: str | torch.device = "cpu") -> MMaDAEnsemble:
        """The ensemble of the policies saved in ``directories`` (each as :meth:`MMaDAModel.load` takes it)."""
        return cls([MMaDAModel.load(d, device=device) for d in directories])

    # -- what MMaDAActor and evaluation read: the first member's, checked alike above ----------
    @property
    def lead(self) -> MMaDAModel:
        return self.members[0]

    @property
    def config(self):
        return self.lead.config

    @property
    def action_tokenizer(self):
        return self.lead.action_tokenizer

    @property
    def proprio_tokenizer(self):
        return self.lead.proprio_tokenizer

    @property
    def denoiser(self) -> nn.Module:
        return self.lead.denoiser

    @property
    def image_size(self) -> int:
        return self.lead.image_size

    @property
    def sampler(self):
        return self.lead.sampler

    @property
    def action_readout(self) -> str:
        """The members' read-out when they share one, else ``"mixed"``."""
        readouts = {m.action_readout for m in self.members}
        return readouts.pop() if len(readouts) == 1 else "mixed"

    @contextlib.contextmanager
    def decoding(self, *, num_steps: int | None = None, temperature: float | None = None,
                 readout: str | None = None) -> Iterator[MMaDAEnsemble]:
        """:meth:`MMaDAModel.decoding` for every member at once."""
        with contextlib.ExitStack() as stack:
            for member in self.members:
                stack.enter_context(member.decoding(num_steps=num_steps, temperature=temperature, readout=readout))
            yield self

    # -- acting -------------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, td: TensorDictBase, *, greedy: bool | None = None, generator: torch.Generator | None = None,
            decode_goal: bool = True) -> PolicyOutput:
        """The members' greedy chunks ``[B, K, A]`` averaged, grippers by majority; the rest is the first member's.

        ``action_tokens`` are the first member's tokenizer's encoding of the averaged chunk and
        ``log_prob`` is NaN: no decoding path produced that chunk."""
        if not is_greedy(greedy):
            raise ValueError("an MMaDAEnsemble decodes greedily only: its averaged chunk is no member's sample "
                             "(evaluate its members one by one with sample_temperature).")
        return self.combine([m.act(td, greedy=True, decode_goal=decode_goal and i == 0) for i, m in enumerate(self.members)])

    def combine(self, outputs: Sequence[PolicyOutput]) -> PolicyOutput:
        """The members' outputs as one (what :meth:`act` returns): their chunks averaged, grippers by majority
        (:func:`average_chunks`), ``action_tokens`` the averaged chunk's encoding, ``log_prob`` NaN, the rest the
        first output's."""
        chunk = average_chunks(torch.stack([out.chunk for out in outputs]), self.action_tokenizer.config.gripper_dims)
        first = outputs[0]
        tokens = self.action_tokenizer.encode(chunk).to(first.action_tokens)
        return first._replace(chunk=chunk, action_tokens=tokens, log_prob=torch.full_like(first.log_prob, float("nan")))

    def visual_input(self, td: TensorDictBase):
        raise NotImplementedError("an MMaDAEnsemble has no decoding-path likelihood: its chunk is an average, "
                                  "not a sample of one denoiser (fine-tune its members one by one).")


def average_weights(members: Sequence[MMaDAModel]) -> MMaDAModel:
    """One policy whose denoiser weights are the element-wise mean of ``members``' (a uniform model
    soup, Wortsman et al., 2022): one set of weights and one decoding pass per chunk, where an
    :class:`MMaDAEnsemble` runs every member.

    It is meaningful for policies that share their start, such as forks of one pretraining run
    (``checkpoint.resume=RUN/checkpoints/step_N checkpoint.restore_rng=false`` with a seed each); the
    weights of independently initialised runs do not line up, and their mean is no policy at all.
    The members must be alike in configuration, vocabulary and sequence layout (checked; their
    tokenizers, which this cannot see, :func:`save_weight_average` checks file by file). Integer
    buffers must agree and are kept.

    Examples:
        >>> soup = average_weights([MMaDAModel.load(d) for d in ["runs/fork_s1/model", "runs/fork_s2/model"]])  # doctest: +SKIP
    """
    members = check_members(members, MMaDAModel, {
        "configuration": lambda m: asdict(m.config),
        "action read-out": lambda m: m.action_readout,
        "vocabulary": lambda m: m.vocab.to_dict(),
        "sequence layout": lambda m: m.layout.to_dict(),
    }, what="a weight average")  # fmt: skip
    states = [m.denoiser.state_dict() for m in members]
    averaged = {}
    for key, value in states[0].items():
        if value.is_floating_point():
            averaged[key] = torch.stack([s[key].to(value.dtype) for s in states]).mean(0)
        elif all(torch.equal(value, s[key]) for s in states[1:]):
            averaged[key] = value
        else:
            raise ValueError(f"the members' {key} differ and cannot be averaged (an integer buffer).")
    soup = copy.deepcopy(members[0])
    soup.denoiser.load_state_dict(averaged)
    return soup


def _tokenizer_digest(model_dir: Path) -> str:
    """A digest of every file under ``model_dir/tokenizers`` (names and bytes)."""
    digest = hashlib.sha256()
    root = model_dir / TOKENIZERS_DIR
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def save_weight_average(directories: Sequence[str | Path], out: str | Path) -> Path:
    """:func:`average_weights` of the MMaDA-VLA policies saved in ``directories`` (run, checkpoint or
    model directories), written as a policy to ``out`` (``mmada-rl eval --checkpoint OUT`` loads it),
    with ``average.json`` naming the members. Their tokenizers must be the same files: a weight average
    of denoisers that read different tokens is meaningless."""
    from mmada_rl.evaluation import resolve_model_dir

    model_dirs = [resolve_model_dir(d) for d in directories]
    digests = [_tokenizer_digest(d) for d in model_dirs]
    for d, digest in zip(model_dirs[1:], digests[1:]):
        if digest != digests[0]:
            raise ValueError(f"{d} was trained with other tokenizers than {model_dirs[0]}; a weight average needs "
                             "policies that share their tokenizers (forks of one run, or runs given one tokenizers.dir).")
    soup = average_weights([MMaDAModel.load(d) for d in model_dirs])
    out = soup.save(out)
    (out / AVERAGE_FILE).write_text(json.dumps({"members": [str(d) for d in model_dirs]}, indent=2))
    return out
