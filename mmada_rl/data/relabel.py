"""A demonstration buffer relabelled by a teacher: the chunk a trained policy predicts from every stored observation.

Knowledge distillation (Hinton et al., 2015) on the demonstrations' own observations: the teacher (one
policy, or several as one ensemble, e.g. seeds trained apart on the same demonstrations, which succeed more
often together than any one alone) decodes greedily from each stored step's observation, as it acts in
evaluation, and the chunk it predicts is stored with that step under
:data:`~mmada_rl.keys.TEACHER_CHUNK_KEY`, beside the demonstrated action. A student trained on the copy with
``data.teacher_labels=true`` (:func:`~mmada_rl.data.make_window_buffer`) learns the teacher's chunk for each
window instead of the demonstrated actions. No step is added and the simulator is not run: the student sees
the same observations as a policy trained on the demonstrations, only other labels.

    >>> relabel_buffer("data/dart/PickCube-v1-fov45", ["runs/pick_s0", "runs/pick_s1", "runs/pick_s2"],
    ...                "data/relabelled/PickCube-v1-fov45-ens3")  # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import torch
from tqdm.auto import tqdm

from mmada_rl.data.buffer import DemoBuffer
from mmada_rl.data.metadata import METADATA_FILE, BufferMetadata
from mmada_rl.data.windows import every_window
from mmada_rl.keys import INSTRUCTION_ID_KEY, TEACHER_CHUNK_KEY

__all__ = ["relabel_buffer"]


def relabel_buffer(demos: str | Path, checkpoints: Sequence[str | Path], out: str | Path, *, batch_size: int = 64,
                   device: str = "cpu", progress: bool = True) -> DemoBuffer:
    """A new buffer in ``out`` holding every episode of ``demos`` with the teacher's chunk for each step.

    Args:
        demos: the buffer to relabel (``mmada-rl collect`` format; any source).
        checkpoints: the teacher: a run, checkpoint or model directory, or several acting as one ensemble
            (what ``mmada-rl eval --checkpoint`` takes); it must read the buffer's camera and image size.
        out: the new buffer's directory (must not hold a buffer).
        batch_size: observations decoded per forward pass.
        device: where the teacher runs.
        progress: show a progress bar.

    Returns:
        the new buffer; its ``metadata.teacher`` names the teacher, the chunk size, the relabelled buffer
        and the mean absolute error of the teacher's chunks against the demonstrated ones (padded steps
        left out).

    Raises:
        ValueError: ``demos`` already holds a teacher's labels.
        BufferMismatchError: the teacher reads another observation mode, image size or camera than ``demos`` holds.
        FileExistsError: ``out`` already holds a buffer.
    """
    from mmada_rl.evaluation import eval_env_config, load_actor
    from mmada_rl.policy import MMaDAActor
    from mmada_rl.training.validation import chunk_abs_errors, predicted_chunks

    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}.")
    if (Path(out) / METADATA_FILE).exists():  # DemoBuffer.create would refuse it too, after the decoding
        raise FileExistsError(f"{out} already holds a buffer; give a new directory.")
    checkpoints = [str(c) for c in checkpoints]
    if not checkpoints:
        raise ValueError("a teacher needs at least one policy directory (--checkpoint PATH).")
    actor = load_actor(checkpoints, device)
    policy = actor.model if isinstance(actor, MMaDAActor) else actor
    sees = eval_env_config(actor, BufferMetadata.load(demos).task)  # what the teacher reads, checked on opening
    source = DemoBuffer.open(demos, obs_mode=sees.obs_mode, image_size=sees.image_size, camera_fov=sees.camera_fov)
    meta = source.metadata
    if meta.teacher:
        raise ValueError(f"{source.path} is already relabelled by {meta.teacher['checkpoints']}; "
                         f"relabel the buffer it was made from ({meta.teacher['buffer']}).")
    chunk_size = int(policy.config.chunk_size)

    chunks, errors = [], []
    bar = tqdm(total=len(source), desc=f"relabel {meta.task}", unit="step", disable=not progress)
    for batch in every_window(source, chunk_size, batch_size):
        chunk = predicted_chunks(policy, batch.to(device)).float().cpu()  # (B, K, A)
        errors.append(chunk_abs_errors(chunk, batch))  # (M, A)
        chunks.append(chunk)
        bar.update(chunk.shape[0])
    bar.close()
    chunks = torch.cat(chunks)  # (steps, K, A), storage order
    mae = torch.cat(errors).mean(0)

    teacher = {"checkpoints": checkpoints, "chunk_size": chunk_size, "buffer": str(source.path),
               "action_readout": getattr(policy, "action_readout", None),
               "num_denoise_steps": policy.sampler.config.num_steps if hasattr(policy, "sampler") else None,
               "chunk_mae": float(mae.mean()), "chunk_mae_per_dim": mae.tolist()}
    new = dataclasses.replace(meta, teacher=teacher, instructions=[], seeds=[], num_episodes=0, num_transitions=0,
                              action_stats={}, parts=list(meta.parts), checkpoint=list(meta.checkpoint))
    relabelled = DemoBuffer.create(out, new, capacity=len(source))
    for (start, stop), episode, seed in zip(source.episode_bounds(), source.episodes(), meta.seeds):
        episode.set(TEACHER_CHUNK_KEY, chunks[start:stop])
        relabelled.add_episode(episode, seed=seed, instruction=meta.instructions[int(episode.get(INSTRUCTION_ID_KEY)[0])])
    return relabelled
