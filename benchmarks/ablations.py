"""Inference-time ablations of a trained MMaDA-VLA policy: decoding steps N, executed steps k, temporal ensembling.

    python benchmarks/ablations.py --checkpoint runs/pretrain_PushCube-v1_s0 --task PushCube-v1 \\
        --steps 1 2 5 10 20 --execute 1 5 --episodes 20

Every setting is evaluated greedily on the same fixed evaluation seeds
(``mmada_rl.evaluation``), so the rows differ only by the setting. Training-time
ablations (goal prediction on/off, chunk size K, VQ vs bins, absorbing vs uniform
kernel) are configs of ``recipes/pretrain`` (``model.predict_goal=false``,
``model.chunk_size=10``, ``tokenizers.action_type=bins``, ``loss.kernel=uniform``),
each a separate pretraining run evaluated with ``mmada-rl eval``.

Writes ``benchmarks/results/ablations_{task}.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="pretraining run, checkpoint or saved model directory")
    parser.add_argument("--task", required=True)
    parser.add_argument("--steps", nargs="+", type=int, default=[1, 2, 5, 10, 20], help="decoding steps N")
    parser.add_argument("--execute", nargs="+", type=int, default=[], help="executed steps k (default: the whole chunk)")
    parser.add_argument("--temporal-ensemble", action="store_true", help="also evaluate ACT's temporal ensemble (k=1)")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from mmada_rl.evaluation import evaluate, resolve_model_dir
    from mmada_rl.policy import MMaDAModel

    model = MMaDAModel.load(resolve_model_dir(args.checkpoint))
    K = model.config.chunk_size
    settings = [{"num_denoise_steps": n, "execute_steps": None} for n in args.steps]
    settings += [{"num_denoise_steps": None, "execute_steps": k} for k in args.execute if k != K]
    if args.temporal_ensemble:
        settings.append({"num_denoise_steps": None, "execute_steps": None, "temporal_ensemble": True})
    records = []
    for setting in settings:
        result = evaluate(model, args.task, episodes=args.episodes, progress=True, **setting)
        record = {**{k: v for k, v in result.to_dict().items() if not isinstance(v, list)}, **setting}
        records.append(record)
        print({k: record[k] for k in ("eval/num_denoise_steps", "eval/execute_steps", "eval/success_once", "eval/decode_ms_mean")
               if k in record}, flush=True)

    rows = [[r.get("eval/num_denoise_steps"), r.get("eval/execute_steps"), "yes" if r.get("temporal_ensemble") else "no",
             f"{r['eval/success_once']:.2f} [{r['eval/success_once_ci_low']:.2f}, {r['eval/success_once_ci_high']:.2f}]",
             f"{r['eval/success_at_end']:.2f}", f"{r['eval/episode_length']:.1f}", f"{r['eval/decode_ms_mean']:.0f}"]
            for r in records]
    header = ["N", "k", "temporal ensemble", "success_once [95% CI]", "success_at_end", "episode length", "decode ms/chunk"]
    table = markdown_table(header, rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_rows = [r for r in records if r.get("num_denoise_steps") is not None]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ns = [r["eval/num_denoise_steps"] for r in n_rows]
    ax[0].errorbar(ns, [r["eval/success_once"] for r in n_rows],
                   yerr=[[r["eval/success_once"] - r["eval/success_once_ci_low"] for r in n_rows],
                         [r["eval/success_once_ci_high"] - r["eval/success_once"] for r in n_rows]], marker="o", capsize=3)
    ax[0].set_xscale("log")
    ax[0].set_xlabel("decoding steps N")
    ax[0].set_ylabel("success_once")
    ax[0].set_ylim(-0.02, 1.02)
    ax[1].plot(ns, [r["eval/decode_ms_mean"] for r in n_rows], marker="o")
    ax[1].set_xscale("log")
    ax[1].set_xlabel("decoding steps N")
    ax[1].set_ylabel("decode ms per chunk")
    fig.suptitle(f"{args.task}: {args.episodes} episodes per setting")
    name = f"ablations_{args.task}"
    save_figure(fig, args.out / f"{name}.png")
    write_results(name, {"checkpoint": str(args.checkpoint), "task": args.task, "episodes": args.episodes, "records": records},
                  f"# Inference-time ablations: {args.task}\n\n{table}\n\n![N ablation]({name}.png)\n", directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
