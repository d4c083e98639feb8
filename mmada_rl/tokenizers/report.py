"""Measurements of the tokenizers, as JSON-ready dicts, Markdown tables and PNGs.

Action errors are given in normalised units (the tokenizer's [-1, 1]) and in
physical units: for ManiSkill's ``pd_ee_delta_pose`` an env action of 1 is
0.1 m (dims 0-2) or 0.1 rad (dims 3-5), so ``error_m = |a - a_hat| * 0.1``;
the gripper is scored by sign agreement. Codebook usage is the fraction of the
vocabulary a token position uses on the data; perplexity is ``exp(entropy)``
of its code histogram (= the number of equally used codes it is worth).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mmada_rl.tokenizers.action import ActionTokenizer
from mmada_rl.tokenizers.fit import FitResult
from mmada_rl.tokenizers.image import FOREGROUND_THRESHOLD, VQImageTokenizer, foreground_mask, median_background
from mmada_rl.tokenizers.normalize import ActionOutOfRangeWarning

__all__ = [
    "ActionUnits",
    "PD_EE_DELTA_POSE_UNITS",
    "codebook_usage",
    "action_reconstruction_report",
    "image_reconstruction_report",
    "psnr",
    "save_reconstruction_grid",
    "save_loss_curves",
    "markdown_table",
    "write_markdown_table",
]


@dataclass(frozen=True)
class ActionUnits:
    """Per-dimension scale from env action units to a physical unit, and the unit's name."""

    scales: tuple[float, ...]
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        if len(self.scales) != len(self.names):
            raise ValueError(f"scales and names differ in length: {len(self.scales)} vs {len(self.names)}.")


#: ManiSkill ``pd_ee_delta_pose``: normalised position deltas x 0.1 m, rotation deltas x 0.1 rad, gripper.
PD_EE_DELTA_POSE_UNITS = ActionUnits(scales=(0.1,) * 6 + (1.0,), names=("m",) * 3 + ("rad",) * 3 + ("gripper",))


def codebook_usage(tokens: torch.Tensor, vocab_size: int) -> dict:
    """Usage fraction and perplexity per token position of ``tokens [N, P]``."""
    tokens = tokens.reshape(tokens.shape[0], -1).long()  # (N, P)
    usage, perplexity = [], []
    for column in tokens.T:
        counts = torch.bincount(column, minlength=vocab_size).double()
        probs = counts / counts.sum().clamp_min(1)
        entropy = -(probs[probs > 0] * probs[probs > 0].log()).sum()
        usage.append(float((counts > 0).sum()) / vocab_size)
        perplexity.append(float(entropy.exp()))
    return {
        "usage": usage,
        "perplexity": perplexity,
        "mean_usage": sum(usage) / len(usage),
        "mean_perplexity": sum(perplexity) / len(perplexity),
    }


@torch.no_grad()
def action_reconstruction_report(
    tokenizer: ActionTokenizer,
    actions: torch.Tensor,
    *,
    units: ActionUnits = PD_EE_DELTA_POSE_UNITS,
) -> dict:
    """Round-trip errors of ``tokenizer`` on env-unit ``actions [N, d_a]``, and its code usage.

    Errors include the clipping of out-of-range actions (``clipped_fraction``
    says how many were clipped; the normaliser's warning is recorded, not shown).
    """
    norm = tokenizer.normalizer
    if len(units.scales) != tokenizer.action_dim:
        raise ValueError(f"units cover {len(units.scales)} dimensions, the tokenizer has {tokenizer.action_dim}.")
    actions = actions.reshape(-1, tokenizer.action_dim).float()  # (N, d_a)
    before = norm.num_out_of_range
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ActionOutOfRangeWarning)
        tokens = tokenizer.encode(actions)  # (N, d_tok)
    clipped = norm.num_out_of_range - before
    recon = tokenizer.decode(tokens)  # (N, d_a)
    err_norm = (norm.affine(recon) - norm.affine(actions)).abs()  # (N, d_a)
    err_env = (recon - actions).abs()
    per_dim, by_unit, signs = [], {}, []
    for d in range(tokenizer.action_dim):
        row = {"dim": d, "unit": units.names[d]}
        if bool(norm.is_gripper[d]):
            agree = float(((recon[:, d] > 0) == (actions[:, d] > 0)).double().mean())
            row["sign_agreement"] = agree
            signs.append(agree)
        else:
            e, scale = err_norm[:, d].double(), units.scales[d]
            row |= {
                "mae_normalized": float(e.mean()),
                "rmse_normalized": float(e.pow(2).mean().sqrt()),
                "max_normalized": float(e.max()),
                "mae_env": float(err_env[:, d].double().mean() * scale),
                "rmse_env": float(err_env[:, d].double().pow(2).mean().sqrt() * scale),
                "max_env": float(err_env[:, d].double().max() * scale),
            }
            by_unit.setdefault(units.names[d], []).append(row["mae_env"])
        per_dim.append(row)
    continuous = [r["mae_normalized"] for r in per_dim if "mae_normalized" in r]
    summary = {
        "tokenizer": type(tokenizer).__name__,
        "tokens_per_action": tokenizer.tokens_per_action,
        "vocab_size": tokenizer.vocab_size,
        "num_actions": actions.shape[0],
        "clipped_fraction": clipped / max(actions.shape[0], 1),
        "mae_normalized": sum(continuous) / max(len(continuous), 1),
        **{f"mae_{unit}": sum(v) / len(v) for unit, v in by_unit.items()},
        "gripper_sign_agreement": sum(signs) / len(signs) if signs else None,
    }
    usage = codebook_usage(tokens, tokenizer.vocab_size)
    summary |= {"code_usage": usage["mean_usage"], "code_perplexity": usage["mean_perplexity"]}
    return {"summary": summary, "per_dim": per_dim, "codebook": usage}


def psnr(images: torch.Tensor, reconstructions: torch.Tensor) -> torch.Tensor:
    """PSNR in dB per image of uint8 ``[N, C, H, W]`` pairs (capped at 100 dB for exact copies)."""
    mse = (images.double() - reconstructions.double()).pow(2).flatten(1).mean(-1)  # (N,)
    return (10 * torch.log10(255.0**2 / mse.clamp_min(255.0**2 * 1e-10))).float()


@torch.no_grad()
def image_reconstruction_report(tokenizer: VQImageTokenizer, images: torch.Tensor, *, batch_size: int = 256,
                                foreground_threshold: float = FOREGROUND_THRESHOLD) -> dict:
    """PSNR and code usage of ``tokenizer`` on uint8 ``images [N, C, H, W]``.

    ``psnr_foreground_db`` is the PSNR over foreground pixels only: those that differ
    from the images' per-pixel median by more than ``foreground_threshold`` (0-255
    units) in a channel (the robot, objects and markers in front of a fixed camera;
    ``foreground_fraction`` of all pixels). A small object lost by the tokenizer shows
    there, not in the whole-image PSNR.
    """
    images = tokenizer.check_images(images).reshape(-1, *images.shape[-3:])  # (N, C, H, W)
    background = median_background(images)
    all_tokens, all_psnr, fg_error, fg_pixels = [], [], 0.0, 0
    for chunk in images.split(batch_size):
        rec = tokenizer.reconstruct(chunk)
        all_tokens.append(rec.tokens.flatten(1))  # (n, g*g)
        all_psnr.append(psnr(chunk, rec.images))
        mask = foreground_mask(chunk.float(), background, foreground_threshold)  # (n, 1, H, W)
        error = (chunk.double() - rec.images.double()).pow(2).mean(dim=-3, keepdim=True)  # (n, 1, H, W)
        fg_error, fg_pixels = fg_error + float(error[mask].sum()), fg_pixels + int(mask.sum())
    values = torch.cat(all_psnr)
    fg_mse = fg_error / max(fg_pixels, 1)
    usage = codebook_usage(torch.cat(all_tokens).reshape(-1, 1), tokenizer.vocab_size)
    return {
        "summary": {
            "tokenizer": type(tokenizer).__name__,
            "tokens_per_image": tokenizer.tokens_per_image,
            "vocab_size": tokenizer.vocab_size,
            "num_images": images.shape[0],
            "psnr_db": float(values.mean()),
            "psnr_db_min": float(values.min()),
            "psnr_foreground_db": float(10 * math.log10(255.0**2 / max(fg_mse, 255.0**2 * 1e-10))),
            "foreground_fraction": fg_pixels / max(images[:, :1].numel(), 1),
            "code_usage": usage["mean_usage"],
            "code_perplexity": usage["mean_perplexity"],
        }
    }


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    return path


@torch.no_grad()
def save_reconstruction_grid(
    tokenizer: VQImageTokenizer, images: torch.Tensor, path: str | Path, *, num_images: int = 8, title: str | None = None
) -> Path:
    """PNG with the first ``num_images`` images (top row) above their reconstructions (bottom row)."""
    images = tokenizer.check_images(images).reshape(-1, *images.shape[-3:])[:num_images]
    rec = tokenizer.reconstruct(images).images
    scores = psnr(images, rec)
    n = images.shape[0]
    fig = Figure(figsize=(1.6 * n, 3.6))
    axes = fig.subplots(2, n, squeeze=False)
    for i in range(n):
        for row, img in enumerate((images[i], rec[i])):
            ax = axes[row][i]
            ax.imshow(img.permute(1, 2, 0).cpu().numpy())
            ax.set_xticks([])
            ax.set_yticks([])
        axes[1][i].set_xlabel(f"{float(scores[i]):.1f} dB", fontsize=8)
    axes[0][0].set_ylabel("input")
    axes[1][0].set_ylabel("decoded")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_loss_curves(results: Mapping[str, FitResult], path: str | Path) -> Path:
    """PNG of the total loss per step of each named fit (log scale)."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for name, result in results.items():
        if result.losses:
            ax.plot(result.losses, label=name)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.legend()
    return _save(fig, path)


def _cell(value) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return f"{value:.3g}" if abs(value) >= 1e-3 or value == 0 else f"{value:.2e}"
    return "" if value is None else str(value)


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str] | None = None) -> str:
    """A Markdown table of flat dicts (e.g. report ``"summary"`` entries); columns default to the first row's keys."""
    if not rows:
        raise ValueError("markdown_table needs at least one row.")
    columns = list(columns) if columns is not None else list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(row.get(c)) for c in columns) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_markdown_table(rows: Sequence[Mapping], path: str | Path, columns: Sequence[str] | None = None) -> Path:
    """Writes :func:`markdown_table` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(markdown_table(rows, columns))
    return path
