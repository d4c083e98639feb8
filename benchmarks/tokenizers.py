"""Action tokenizers on real demonstrations: reconstruction error and closed-loop replay success.

For each task's demonstration buffer, fits the paper's VQ action tokenizer
(residual EMA codebook) at several codebook sizes and tokens per action, the
residual-FSQ baseline at the same tokens per action (and the same vocabulary,
2^8 = 256 codes), and the 256-bin baseline (7 tokens per action, one per
dimension); measures round-trip errors on every stored action and the success
of replaying every demonstration open loop through each tokenizer; fits the
image VQ-VAE and reports its PSNR.

    python benchmarks/tokenizers.py                                   # PickCube-v1 and PushCube-v1, ~1 h on 2 cores
    python benchmarks/tokenizers.py --tasks PickCube-v1 --quick       # smoke run

Buffers are read from data/TASK (collected first with `mmada-rl collect` when missing).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from common import RESULTS, markdown_table, save_figure, write_results
from mmada_rl.data import DemoBuffer
from mmada_rl.data.collect import collect
from mmada_rl.envs.maniskill import EnvConfig
from mmada_rl.tokenizers.fit import fit_action_tokenizer, fit_image_tokenizer
from mmada_rl.tokenizers.from_buffer import buffer_arrays, make_action_tokenizer
from mmada_rl.tokenizers.image import VQImageTokenizer, VQImageTokenizerConfig
from mmada_rl.tokenizers.replay import replay_demonstrations
from mmada_rl.tokenizers.report import action_reconstruction_report, image_reconstruction_report, save_reconstruction_grid


def variants(quick: bool) -> list[tuple[str, str, dict]]:
    """(name, kind, config fields) of every action tokenizer compared."""
    vq_grid = [(256, 2), (256, 4), (256, 7), (64, 4), (1024, 4)] if not quick else [(256, 4)]
    out = [(f"VQ K={k} d_tok={d}", "vq", {"codebook_size": k, "tokens_per_action": d}) for k, d in vq_grid]
    fsq_tokens = sorted({d for _, d in vq_grid} | ({7} if not quick else set()))
    out += [(f"FSQ 2^8 d_tok={d}", "fsq", {"levels": (2,) * 8, "num_quantizers": d}) for d in fsq_tokens]
    out.append(("bins 256 d_tok=7", "bins", {"num_bins": 256}))
    return out


def load_buffer(task: str, episodes: int) -> DemoBuffer:
    path = Path("data") / task
    if not (path / "metadata.json").exists() or DemoBuffer.open(path).metadata.num_episodes < episodes:
        collect(path, EnvConfig(task=task), episodes=episodes)
    return DemoBuffer.open(path, task=task, control_mode="pd_ee_delta_pose")


def run_task(task: str, args) -> dict:
    buffer = load_buffer(task, args.episodes)
    arrays = buffer_arrays(buffer)
    actions = arrays["action"]
    tokenizers, rows = {}, []
    for name, kind, fields in variants(args.quick):
        tok = make_action_tokenizer(kind, buffer.metadata.action_dim, **fields)
        t0 = time.perf_counter()
        fit = fit_action_tokenizer(tok, actions, steps=args.action_steps, seed=args.seed, progress=False)
        rep = action_reconstruction_report(tok, actions)["summary"]
        tokenizers[name] = tok
        rows.append({**rep, "task": task, "tokenizer": name, "kind": kind, "fit_seconds": time.perf_counter() - t0,
                     "dead_codes_restarted": fit.dead_codes_restarted})
    replays = replay_demonstrations(buffer, {"raw": None, **tokenizers}, max_episodes=args.replay_episodes)
    raw = replays["raw"].success_rate
    for row in rows:
        rate = replays[row["tokenizer"]].success_rate
        row.update(replay_success=rate, replay_vs_raw=rate / raw if raw else float("nan"))
    image = VQImageTokenizer(VQImageTokenizerConfig(image_size=buffer.metadata.image_size))
    t0 = time.perf_counter()
    fit_image_tokenizer(image, arrays["image"], steps=args.image_steps, seed=args.seed, progress=False)
    image_rep = image_reconstruction_report(image, arrays["image"])["summary"]
    image_rep["fit_seconds"] = time.perf_counter() - t0
    idx = torch.linspace(0, arrays["image"].shape[0] - 1, 8).long()
    save_reconstruction_grid(image, arrays["image"][idx], RESULTS / f"tokenizers_{task}_images.png", title=f"{task}: frames (top) and VQ-VAE reconstructions (bottom)")
    return {"task": task, "episodes": buffer.metadata.num_episodes, "transitions": len(buffer),
            "raw_replay_success": raw, "replay_episodes": len(replays["raw"].successes), "actions": rows, "image": image_rep}


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    colors = {"vq": "#1f77b4", "fsq": "#ff7f0e", "bins": "#2ca02c"}
    markers = ["o", "s", "^"]
    for i, res in enumerate(results):
        for row in res["actions"]:
            kw = dict(color=colors[row["kind"]], marker=markers[i % 3], s=40, alpha=0.85)
            axes[0].scatter(row["tokens_per_action"], 1000 * row["mae_m"], **kw)
            axes[1].scatter(row["tokens_per_action"], 100 * row["replay_success"], **kw)
        axes[1].axhline(100 * res["raw_replay_success"], color="gray", ls="--", lw=1)
    axes[0].set(xlabel="tokens per action", ylabel="position MAE (mm)", yscale="log", title="round-trip error")
    axes[1].set(xlabel="tokens per action", ylabel="open-loop replay success (%)", title="closed-loop proof (dashed: raw actions)")
    handles = [plt.Line2D([], [], color=c, marker="o", ls="", label=k) for k, c in colors.items()]
    handles += [plt.Line2D([], [], color="k", marker=markers[i], ls="", label=r["task"]) for i, r in enumerate(results)]
    axes[0].legend(handles=handles, fontsize=8)
    save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["PickCube-v1", "PushCube-v1"])
    parser.add_argument("--episodes", type=int, default=100, help="demonstrations per task (default: %(default)s)")
    parser.add_argument("--action-steps", type=int, default=1500, help="training steps per learned action tokenizer")
    parser.add_argument("--image-steps", type=int, default=1500, help="image VQ-VAE training steps")
    parser.add_argument("--replay-episodes", type=int, default=None, help="demonstrations replayed per tokenizer (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s; more threads are slower while the simulator runs)")
    parser.add_argument("--quick", action="store_true", help="one VQ, one FSQ, bins; 100 steps; 5 replays")
    args = parser.parse_args()
    if args.quick:
        args.action_steps, args.image_steps, args.replay_episodes = 100, 50, 5
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    results = [run_task(task, args) for task in args.tasks]
    columns = ["tokens/action", "vocab", "pos MAE (mm)", "rot MAE (mrad)", "norm. MAE", "gripper agree", "code usage", "replay success", "vs raw"]
    md = ["## Action tokenizers on planner demonstrations (pd_ee_delta_pose)\n"]
    for res in results:
        md.append(f"\n### {res['task']}: {res['episodes']} demos, {res['transitions']} actions; raw-action replay "
                  f"success {100 * res['raw_replay_success']:.0f}% ({res['replay_episodes']} episodes)\n")
        rows = [[r["tokenizer"], r["tokens_per_action"], r["vocab_size"], f"{1000 * r['mae_m']:.3f}", f"{1000 * r['mae_rad']:.3f}",
                 f"{r['mae_normalized']:.4f}", f"{r['gripper_sign_agreement']:.3f}", f"{r['code_usage']:.2f}",
                 f"{100 * r['replay_success']:.0f}%", f"{r['replay_vs_raw']:.2f}"] for r in res["actions"]]
        md.append(markdown_table(["tokenizer", *columns], rows))
        img = res["image"]
        md.append(f"\nImage VQ-VAE (64×64 → 8×8 codes, 512-code EMA codebook): PSNR {img['psnr_db']:.1f} dB "
                  f"(min {img['psnr_db_min']:.1f}), code usage {img['code_usage']:.2f}, fitted in {img['fit_seconds']:.0f} s.\n")
    write_results("tokenizers", {"args": vars(args), "results": results}, "\n".join(md))
    plot(results, RESULTS / "tokenizers.png")
    print("\n".join(md))


if __name__ == "__main__":
    main()
