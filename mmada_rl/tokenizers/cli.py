"""``mmada-rl fit-tokenizers``: fit the tokenizers on a buffer and prove they cover its data."""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def build_report(buffer, fitted, *, baselines: dict, replay_episodes: int | None, progress: bool = True) -> dict:
    """Reconstruction errors, code usage, PSNR and closed-loop replay success, as one dict."""
    from mmada_rl.tokenizers.from_buffer import buffer_arrays
    from mmada_rl.tokenizers.replay import replay_demonstrations
    from mmada_rl.tokenizers.report import action_reconstruction_report, image_reconstruction_report

    arrays = buffer_arrays(buffer)
    action_tokenizers = {"vq (ours)" if fitted.action.__class__.__name__ == "VQActionTokenizer" else "action": fitted.action, **baselines}
    report = {
        "buffer": str(buffer.path),
        "task": buffer.metadata.task,
        "control_mode": buffer.metadata.control_mode,
        "episodes": buffer.metadata.num_episodes,
        "transitions": len(buffer),
        "fits": {name: fit.to_dict() for name, fit in fitted.fits.items()},
        "actions": {name: action_reconstruction_report(tok, arrays["action"]) for name, tok in action_tokenizers.items()},
        "image": image_reconstruction_report(fitted.image, arrays["image"]),
    }
    if replay_episodes != 0:
        replays = replay_demonstrations(buffer, {"raw actions": None, **action_tokenizers},
                                        max_episodes=replay_episodes, progress=progress)
        report["replay"] = {name: r.to_dict() for name, r in replays.items()}
    return report


def report_markdown(report: dict) -> str:
    from mmada_rl.tokenizers.report import markdown_table

    rows = []
    for name, rep in report["actions"].items():
        s = rep["summary"]
        row = {"tokenizer": name, "tokens/action": s["tokens_per_action"], "vocab": s["vocab_size"],
               "MAE (norm.)": s["mae_normalized"], "MAE pos (mm)": 1000 * s.get("mae_m", float("nan")),
               "MAE rot (mrad)": 1000 * s.get("mae_rad", float("nan")), "gripper agree": s["gripper_sign_agreement"],
               "code usage": s["code_usage"], "perplexity": s["code_perplexity"]}
        if "replay" in report:
            row["replay success"] = report["replay"][name]["success_rate"]
        rows.append(row)
    md = [f"# Tokenizer report: {report['task']} ({report['control_mode']}), {report['episodes']} demonstrations, "
          f"{report['transitions']} transitions\n", "## Actions (round trip on every stored action)\n", markdown_table(rows)]
    if "replay" in report:
        raw = report["replay"]["raw actions"]
        md.append(f"\nOpen-loop replay from each demonstration's seed: raw actions succeed in "
                  f"{100 * raw['success_rate']:.1f}% of {raw['episodes']} episodes.\n")
    img = report["image"]["summary"]
    md.append("\n## Images\n")
    md.append(markdown_table([{k: v for k, v in img.items()}]))
    for name, fit in report["fits"].items():
        md.append(f"\n{name} tokenizer: {fit.get('steps', 0)} steps, {fit.get('seconds_per_step', 0) * 1000:.1f} ms/step, "
                  f"{fit.get('dead_codes_restarted', 0)} dead codes restarted.")
    return "\n".join(md) + "\n"


def _run(args: argparse.Namespace) -> int:
    from mmada_rl.data.buffer import DemoBuffer
    from mmada_rl.tokenizers.from_buffer import TokenizerFitConfig, buffer_arrays, fit_tokenizers, make_action_tokenizer
    from mmada_rl.tokenizers.fit import fit_action_tokenizer
    from mmada_rl.tokenizers.report import save_loss_curves, save_reconstruction_grid

    import torch

    torch.set_num_threads(args.num_threads)
    buffer = DemoBuffer.open(args.data)
    out = Path(args.out)
    action = {"codebook_size": args.codebook_size, "tokens_per_action": args.tokens_per_action} if args.action_type == "vq" else {}
    cfg = TokenizerFitConfig(action_type=args.action_type, action=action, action_steps=args.action_steps,
                             image={"codebook_size": args.image_codebook_size, "grid_size": args.image_grid,
                                    "foreground_weight": args.image_foreground_weight},
                             image_steps=args.image_steps, proprio_bins=args.proprio_bins,
                             state_differences=args.state_differences, seed=args.seed)
    fitted = fit_tokenizers(buffer, cfg)
    fitted.save(out)
    baselines = {}
    if args.baselines:
        actions = buffer_arrays(buffer)["action"]
        dim = buffer.metadata.action_dim
        baselines["256 bins"] = make_action_tokenizer("bins", dim, num_bins=256)
        fit_action_tokenizer(baselines["256 bins"], actions, progress=False)
        levels = args.fsq_levels
        baselines["residual FSQ"] = make_action_tokenizer("fsq", dim, levels=tuple(levels), num_quantizers=args.tokens_per_action)
        fitted.fits["fsq"] = fit_action_tokenizer(baselines["residual FSQ"], actions, steps=args.action_steps, seed=args.seed)
    report = build_report(buffer, fitted, baselines=baselines, replay_episodes=args.replay_episodes)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    (out / "report.md").write_text(report_markdown(report))
    images = buffer_arrays(buffer)["image"]
    idx = list(range(0, images.shape[0], max(1, images.shape[0] // 8)))[:8]
    save_reconstruction_grid(fitted.image, images[idx], out / "reconstructions.png")
    save_loss_curves(fitted.fits, out / "loss_curves.png")
    print(report_markdown(report))
    print(f"tokenizers and report written to {out}")
    return 0


def _state_pair(text: str) -> list[int]:
    """``"26:19"`` → ``[26, 19]`` (an argparse type)."""
    try:
        a, b = (int(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B, two state dimensions, e.g. 26:19; got {text!r}") from None
    return [a, b]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "fit-tokenizers",
        help="fit action/image/text tokenizers on a demonstration buffer and report how well they cover it",
        description="Fit the action (VQ with EMA codebook by default), image (VQ-VAE), text and proprioception "
        "tokenizers on a buffer; write them and a report (JSON + Markdown + PNG): action reconstruction errors per "
        "dimension, code usage and perplexity, image PSNR (whole frame and foreground), and the success of replaying every demonstration through "
        "each action tokenizer (against the two baselines, 256 bins and residual FSQ).",
    )
    p.add_argument("--data", required=True, help="demonstration buffer directory (mmada-rl collect)")
    p.add_argument("--out", required=True, help="output directory for tokenizers and report")
    p.add_argument("--action-type", default="vq", choices=["vq", "bins", "fsq"], help="policy action tokenizer (default: %(default)s)")
    p.add_argument("--codebook-size", type=int, default=1024, help="VQ codes per quantizer; 1024 x 4 tokens replayed 99%% as well as raw actions on PickCube and PushCube (benchmarks/results/tokenizers.md) (default: %(default)s)")
    p.add_argument("--tokens-per-action", type=int, default=4, help="VQ/FSQ residual quantizers = tokens per action (default: %(default)s)")
    p.add_argument("--action-steps", type=int, default=3000, help="action tokenizer training steps (default: %(default)s)")
    p.add_argument("--image-codebook-size", type=int, default=512, help="image VQ-VAE codes (default: %(default)s)")
    p.add_argument("--image-grid", type=int, default=8, help="image token grid side: grid^2 tokens per image (default: %(default)s)")
    p.add_argument("--image-foreground-weight", type=float, default=1.0, help="weight of the VQ-VAE's squared error at pixels that differ from the median frame (robot, objects): above 1 it keeps small objects such as PickCube's cube, which plain MSE decodes away; 1: plain MSE (default: %(default)s)")
    p.add_argument("--image-steps", type=int, default=3000, help="image VQ-VAE training steps (default: %(default)s)")
    p.add_argument("--state-differences", type=_state_pair, nargs="+", default=[], metavar="A:B",
                   help="append state[A] - state[B] to the state before its bins are fitted, one per pair (the "
                        "policy's model.state_differences, e.g. 26:19 27:20 28:21, PickCube-v1's goal minus the "
                        "gripper's position); default: none")
    p.add_argument("--proprio-bins", type=int, default=64, help="bins per state dimension for proprioception tokens; 0: none (default: %(default)s)")
    p.add_argument("--fsq-levels", type=int, nargs="+", default=[2] * 8, help="FSQ levels per latent channel; the vocabulary is their product, 2^8 = 256 by default like the VQ codebook (default: %(default)s)")
    p.add_argument("--baselines", default=True, action=argparse.BooleanOptionalAction, help="also fit and report the baselines (default: yes)")
    p.add_argument("--replay-episodes", type=int, default=None, help="demonstrations replayed for the closed-loop proof (default: all; 0: skip)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--num-threads", type=int, default=1, help="torch threads; more contend with the simulator on 2 cores (default: %(default)s)")
    p.set_defaults(func=_run)
