"""``mmada-rl average``: one policy from the weight average of several (forks of one pretraining run)."""
from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser(
        "average",
        help="average the weights of MMaDA-VLA policies that share their start (forks of one run) into one policy",
        description="Write one MMaDA-VLA policy whose denoiser weights are the element-wise mean of the given "
        "policies' (a uniform model soup). Meaningful for forks of one pretraining run (each resumed from the same "
        "checkpoint with checkpoint.restore_rng=false and its own seed): independently initialised runs do not line "
        "up. The policies must share configuration and tokenizers. `mmada-rl eval --checkpoint OUT` evaluates it; "
        "`mmada-rl eval --checkpoint A B C` runs them as an ensemble instead.",
    )
    p.add_argument("--checkpoint", nargs="+", required=True, metavar="PATH",
                   help="two or more run, checkpoint or model directories (a run directory: its newest checkpoint, "
                        "whose model is the run's weight average when it kept one)")
    p.add_argument("--out", required=True, help="directory the averaged policy is written to")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from mmada_rl.policy.ensemble import save_weight_average

    if len(args.checkpoint) < 2:
        raise SystemExit("mmada-rl average: give two or more --checkpoint paths.")
    try:
        out = save_weight_average(args.checkpoint, args.out)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"mmada-rl average: {err}") from None
    print(f"[average] {len(args.checkpoint)} policies averaged into {out}")
    return 0
