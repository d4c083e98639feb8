"""Signal and noise of the fine-tuning gradients: demonstrations against the policy's own rollouts.

    python benchmarks/finetune_gradients.py --pretrained runs/push_bins_s0 \\
        --online runs/compare/PushCube-v1/mmada_rft/s0/online_buffer --demos data/PushCube-v1

For each source of training rows — demonstration windows, the online rows with
a positive advantage (with episode-success advantages, ``advantage.estimator=return``
and a sparse reward: the successful rollouts that filtered self-imitation
imitates), and every online row — it draws ``--minibatches`` minibatches of ``--batch-size`` rows, takes the
gradients of the masked-diffusion losses of the pretrained denoiser on each —
``loss_action`` and ``loss_goal`` separately, same masks — and reports, per loss:

* ``cos_pairs``: the mean cosine similarity between the gradients of two
  independent minibatches. For a gradient ``g = mu + noise`` it estimates
  ``|mu|^2 / (|mu|^2 + var / batch)``: near 0, minibatch updates point in random
  directions (Adam still moves the weights a full ``lr`` per step);
* ``norm_mean_over_mean_norm``: the norm of the averaged gradient over the mean
  minibatch norm (1 = every minibatch agrees);
* ``cos_to_demos``: cosine between the source's averaged gradient and the
  demonstrations' (do the two sources pull the same way?).

The last source is the update of ``loss.rwr.weighting=signed
loss.rwr.standardize_advantage=true``: each online row's cross-entropy weighted
by its advantage standardised over the minibatch, so a drift shared by every
row (whatever its advantage) cancels.

Writes ``benchmarks/results/finetune_gradients.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import torch
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, flat_gradient, markdown_table, save_figure, write_results  # noqa: E402

from mmada_rl.data import DemoBuffer, make_window_buffer  # noqa: E402
from mmada_rl.evaluation import resolve_model_dir  # noqa: E402
from mmada_rl.keys import ACTION_IS_PAD_KEY, ADVANTAGE_KEY, SEQUENCE_KEY  # noqa: E402
from mmada_rl.objectives import MaskedDiffusionLoss, RewardWeightedDiffusionLoss  # noqa: E402
from mmada_rl.policy import MMaDAModel  # noqa: E402


def load_online_rows(path: Path):
    """The rows a fine-tuning run stored in its online buffer (``online_buffer/`` of the run directory)."""
    import json

    from tensordict import TensorDict

    meta = path / "storage" / "storage_metadata.json"
    if not meta.exists():
        raise FileNotFoundError(f"{path} holds no online buffer (expected the online_buffer/ of a finetune run).")
    rows = TensorDict.load_memmap(path / "storage")  # the storage TorchRL's dumps wrote, at full capacity
    return rows[: json.loads(meta.read_text())["len"]].clone()


PARTS = ("action", "goal")


def flat_grads(model: MMaDAModel, loss_module: MaskedDiffusionLoss, rows) -> dict[str, torch.Tensor]:
    """The gradient of ``loss_action`` and of ``loss_goal`` on one minibatch (same masks), flattened."""
    losses = loss_module(rows.select(*(k for k in (SEQUENCE_KEY, ACTION_IS_PAD_KEY, ADVANTAGE_KEY) if k in rows.keys(True))))
    params = [p for p in model.denoiser.parameters() if p.requires_grad]
    out = {}
    for i, part in enumerate(PARTS):
        grads = torch.autograd.grad(losses[f"loss_{part}"], params, retain_graph=i < len(PARTS) - 1, allow_unused=True)
        out[part] = flat_gradient(params, grads)
    return out


def statistics(grads: list[torch.Tensor], reference: torch.Tensor | None) -> dict:
    g = torch.stack(grads)
    unit = g / g.norm(dim=1, keepdim=True)
    pairs = [float(unit[i] @ unit[j]) for i, j in itertools.combinations(range(len(grads)), 2)]
    mean = g.mean(0)
    out = {"minibatches": len(grads), "cos_pairs": sum(pairs) / len(pairs), "cos_pairs_all": pairs,
           "norm_mean_over_mean_norm": float(mean.norm() / g.norm(dim=1).mean()), "mean_norm": float(g.norm(dim=1).mean())}
    if reference is not None:
        out["cos_to_demos"] = float(torch.nn.functional.cosine_similarity(mean, reference, dim=0))
    return out, mean


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pretrained", type=Path, required=True, help="pretraining run, checkpoint or model directory")
    parser.add_argument("--online", type=Path, required=True, help="online_buffer/ directory of a fine-tuning run")
    parser.add_argument("--demos", type=Path, required=True, help="demonstration buffer of the same task")
    parser.add_argument("--first-rows", type=int, default=None,
                        help="use only the first N online rows (those the earliest, least fine-tuned policy collected)")
    parser.add_argument("--minibatches", type=int, default=12, help="minibatches per source (default: 12)")
    parser.add_argument("--batch-size", type=int, default=8, help="rows per minibatch (default: 8, the online half of a fine-tuning batch)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.minibatches < 2 or args.batch_size < 1:
        parser.error("--minibatches must be >= 2 and --batch-size >= 1.")
    torch.manual_seed(args.seed)

    model = MMaDAModel.load(resolve_model_dir(args.pretrained))
    model.train()
    for p in model.denoiser.parameters():
        p.requires_grad_(True)
    plain = MaskedDiffusionLoss(model.denoiser, schedule="cosine")
    # the signed variant's update: advantages standardised over the minibatch (zero mean), weights A / std
    signed = RewardWeightedDiffusionLoss(model.denoiser, schedule="cosine", weighting="signed", standardize_advantage=True)
    windows = make_window_buffer(DemoBuffer.open(args.demos), model.config.chunk_size, args.batch_size, seed=args.seed)
    online = load_online_rows(args.online)
    if args.first_rows is not None:
        online = online[: args.first_rows]
    success = online[online.get(ADVANTAGE_KEY).reshape(-1) > 0]
    if success.shape[0] < args.batch_size:
        raise SystemExit(f"{args.online} holds {success.shape[0]} rows with a positive advantage, fewer than --batch-size.")

    def demo_batch():
        return model.loss_inputs(windows.sample())

    def rows_from(data):
        return lambda: data[torch.randint(data.shape[0], (args.batch_size,))]

    sources = {"demonstrations": (demo_batch, plain), "online, advantage > 0": (rows_from(success), plain),
               "online, all rows": (rows_from(online), plain),
               "online, all rows, zero-mean signed advantage weights": (rows_from(online), signed)}
    results, reference = {}, {}
    bar = tqdm(total=len(sources) * args.minibatches, desc="gradients")
    for name, (draw, loss_module) in sources.items():
        grads = {part: [] for part in PARTS}
        for _ in range(args.minibatches):
            for part, g in flat_grads(model, loss_module, draw()).items():
                grads[part].append(g)
            bar.update()
        results[name] = {}
        for part in PARTS:
            results[name][part], mean = statistics(grads[part], reference.get(part))
            reference.setdefault(part, mean)
    bar.close()

    header = ["rows", "loss", "mean cosine of two minibatch gradients", "|mean g| / mean |g|", "mean |g|",
              "cosine of the mean to the demos' mean"]
    rows = [[name, f"loss_{part}", f"{r['cos_pairs']:.3f}", f"{r['norm_mean_over_mean_norm']:.3f}", f"{r['mean_norm']:.2f}",
             f"{r['cos_to_demos']:.3f}" if "cos_to_demos" in r else "-"]
            for name, by_part in results.items() for part, r in by_part.items()]
    table = markdown_table(header, rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PARTS), figsize=(10, 3.5))
    for ax, part in zip(axes, PARTS):
        for name, by_part in results.items():
            ax.hist(by_part[part]["cos_pairs_all"], bins=30, alpha=0.5, label=name)
        ax.set_title(f"loss_{part}")
        ax.set_xlabel("cosine between two minibatch gradients")
        ax.set_ylabel("pairs")
        ax.legend(fontsize=7)
    save_figure(fig, args.out / "finetune_gradients.png")
    payload = {"pretrained": str(args.pretrained), "online": str(args.online), "demos": str(args.demos), "first_rows": args.first_rows,
               "online_rows": int(online.shape[0]), "positive_advantage_rows": int(success.shape[0]), "batch_size": args.batch_size,
               "sources": results}
    write_results("finetune_gradients", payload,
                  f"# Fine-tuning gradients: signal and noise\n\n{online.shape[0]} online rows ({success.shape[0]} with a "
                  f"positive advantage) of `{args.online}`; pretrained `{args.pretrained}`.\n\n{table}\n\n"
                  "![cosines](finetune_gradients.png)\n", directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
