"""Does one policy, averaged over views of its own observation, act like an ensemble of seeds?

    python benchmarks/view_ensemble.py --checkpoint runs/pick100_goalrel_l1w20_cells4_10k_s{0,1,2} --episodes 50

Three MMaDA-VLA policies trained on the same demonstrations with different seeds succeed
more often as one ensemble (``mmada-rl eval --checkpoint A B C``: the members' greedy chunks
averaged) than any of them alone: they fail on different episodes. This asks whether one
policy gets part of that from views of the observation it was trained to be indifferent
to, decoded separately and averaged the same way (the arm's actions by their mean, the
gripper by majority; :meth:`mmada_rl.policy.MMaDAEnsemble.combine`):

* ``shifts``: the image as observed and shifted by ``--shift`` pixels up, down, left and
  right (five views; the edge pixels repeated, as the training's random shift pads them);
* ``state``: the state as read, and with the tokens masked that state dropout masked in
  training (``loss.proprio_drop_prob``; the dimensions of ``loss.proprio_drop_keep_dims``
  stay readable, as they did there): two views.

Each arm runs the policy on the same fixed evaluation seeds as ``mmada-rl eval`` (greedy,
the policy's own read-out), and the ``policy`` arm is the policy alone on them. Reports each
checkpoint's successes per arm, the arms pooled over the checkpoints with 95% Wilson
intervals, and per arm the episodes it won and lost against the policy alone.

Writes ``benchmarks/results/view_ensemble.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402

ARMS = ("policy", "shifts", "state")


def state_dropped(model, keep_dims):
    """A shallow copy of ``model`` (the same weights) whose prompts mask the proprio tokens that state
    dropout masks in training with ``keep_dims`` left readable (every proprio token when it is empty)."""
    from mmada_rl.policy.model import MMaDAModel

    proprio = model.layout.positions("proprio")
    index = model.proprio_drop_index(keep_dims)
    positions = proprio if index is None else proprio[torch.as_tensor(index)]
    mask_id = model.layout.vocab.mask_id

    def prompt(td):
        ids = MMaDAModel.prompt(model, td).clone()
        ids[:, positions.to(ids.device)] = mask_id
        return ids

    dropped = copy.copy(model)
    dropped.prompt = prompt  # what MMaDAModel.act reads the conditioning from
    return dropped


def view_ensemble(members, shifts):
    """The :class:`~mmada_rl.policy.MMaDAEnsemble` whose member ``i`` decodes the observation with its image
    shifted by ``shifts[i] = (dy, dx)`` pixels (edges repeated); ``members`` are one policy or its copies."""
    from mmada_rl.keys import IMAGE_KEY
    from mmada_rl.policy.ensemble import MMaDAEnsemble

    pad = max(1, *(abs(v) for shift in shifts for v in shift))

    class ViewEnsemble(MMaDAEnsemble):
        @torch.no_grad()
        def act(self, td, *, greedy=None, generator=None, decode_goal=True):
            image = td.get(IMAGE_KEY)
            flat = image.reshape(-1, *image.shape[-3:])
            H, W = flat.shape[-2:]
            padded = F.pad(flat.float(), (pad, pad, pad, pad), mode="replicate").to(flat.dtype)
            outputs = []
            for i, (member, (dy, dx)) in enumerate(zip(self.members, shifts)):
                view = td.clone(False)
                view.set(IMAGE_KEY, padded[..., pad + dy:pad + dy + H, pad + dx:pad + dx + W].reshape(image.shape))
                outputs.append(member.act(view, greedy=True, decode_goal=decode_goal and i == 0))
            return self.combine(outputs)

    return ViewEnsemble(members)


def arm_policy(model, arm: str, shift: int, keep_dims):
    """The policy an arm evaluates: ``model`` itself, or its :func:`view_ensemble`."""
    if arm == "policy":
        return model
    if arm == "shifts":
        shifts = [(0, 0), (shift, 0), (-shift, 0), (0, shift), (0, -shift)]
        return view_ensemble([model] * len(shifts), shifts)
    if model.proprio_tokenizer is None:
        raise SystemExit("--arms state: the policy does not read the state.")
    return view_ensemble([model, state_dropped(model, keep_dims)], [(0, 0), (0, 0)])


def drop_keep_dims(model_dir: Path) -> list[int]:
    """``loss.proprio_drop_keep_dims`` of the training run that saved ``model_dir`` (its checkpoint's config)."""
    config = model_dir.parent / "config.json"
    if not config.is_file():
        raise SystemExit(f"--arms state reads the training's state dropout from {config}, which is missing: "
                         "give the policy as a run or checkpoint directory.")
    loss = json.loads(config.read_text())["loss"]
    if not float(loss.get("proprio_drop_prob", 0.0)) > 0:
        raise SystemExit(f"--arms state: {model_dir.parent} was trained without state dropout (loss.proprio_drop_prob=0).")
    return [int(d) for d in loss.get("proprio_drop_keep_dims") or []]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", nargs="+", required=True, type=Path,
                        help="MMaDA-VLA runs (or checkpoint directories), each evaluated on its own")
    parser.add_argument("--task", default="PickCube-v1")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed-offset", type=int, default=0, help="first evaluation seed, as mmada-rl eval's")
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS), help="which arms to run (default: all)")
    parser.add_argument("--shift", type=int, default=2, help="pixels each shifted view moves the image (default 2)")
    parser.add_argument("--name", default="view_ensemble")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.shift < 1:
        parser.error("--episodes and --shift must be >= 1.")

    from mmada_rl.evaluation import evaluate, resolve_model_dir, wilson_interval
    from mmada_rl.policy.model import MODEL_CONFIG, MMaDAModel

    try:
        model_dirs = [resolve_model_dir(checkpoint) for checkpoint in args.checkpoint]
    except FileNotFoundError as err:
        parser.error(str(err))
    for checkpoint, model_dir in zip(args.checkpoint, model_dirs):
        if not (model_dir / MODEL_CONFIG).is_file():
            parser.error(f"--checkpoint {checkpoint}: not an MMaDA-VLA policy (a baseline has no views to average here).")
    rows = []
    for checkpoint, model_dir in zip(args.checkpoint, model_dirs):
        model = MMaDAModel.load(model_dir)
        keep = drop_keep_dims(model_dir) if "state" in args.arms else []
        per_arm = {}
        for arm in args.arms:
            result = evaluate(arm_policy(model, arm, args.shift, keep), args.task, args.episodes,
                              seed_offset=args.seed_offset, progress=True)
            per_arm[arm] = [bool(r.success_once) for r in result.per_episode]
            print(f"{checkpoint} {arm}: {sum(per_arm[arm])}/{len(per_arm[arm])}", flush=True)
        rows.append({"checkpoint": str(checkpoint), "model": str(model_dir), "success": per_arm})

    def cell(row, arm):  # successes, and the episodes the arm won and lost against the policy alone
        mine, alone = row["success"][arm], row["success"].get("policy")
        text = f"{sum(mine)}/{len(mine)}"
        if arm == "policy" or alone is None:
            return text
        won, lost = sum(m and not a for m, a in zip(mine, alone)), sum(a and not m for m, a in zip(mine, alone))
        return f"{text} (+{won}, -{lost})"

    summary = {}
    for arm in args.arms:
        wins, n = sum(sum(row["success"][arm]) for row in rows), sum(len(row["success"][arm]) for row in rows)
        ci = wilson_interval(wins, n)
        summary[arm] = {"successes": wins, "episodes": n, "success_once": wins / n, "ci_low": ci.low, "ci_high": ci.high}
    payload = {"task": args.task, "episodes": args.episodes, "seed_offset": args.seed_offset, "shift": args.shift,
               "arms": args.arms, "summary": summary, "checkpoints": rows}
    table = markdown_table(
        ["checkpoint", *args.arms],
        [[f"`{row['checkpoint']}`", *(cell(row, a) for a in args.arms)] for row in rows]
        + [["pooled [95% CI]", *(f"{s['successes']}/{s['episodes']} = {s['success_once']:.2f} "
                                 f"[{s['ci_low']:.2f}, {s['ci_high']:.2f}]" for s in summary.values())]])
    markdown = (f"# One policy averaged over views of its observation: {args.task}\n\n"
                f"{args.episodes} evaluation seeds from offset {args.seed_offset}, greedy decoding. `policy`: the policy "
                f"alone; `shifts`: the mean chunk over the image as observed and shifted by {args.shift} px up, down, "
                "left and right; `state`: the mean chunk over the state as read and with the tokens state dropout "
                "masked in training masked. (+w, -l): episodes the arm succeeded in where the policy alone failed, "
                f"and the reverse.\n\n{table}\n")
    write_results(args.name, payload, markdown, args.out)
    plot(summary, args.out / f"{args.name}.png", args.task)
    print(markdown)
    return 0


def plot(summary: dict, path: Path, task: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = list(summary)
    values = [summary[a]["success_once"] for a in arms]
    errors = [[v - summary[a]["ci_low"] for a, v in zip(arms, values)], [summary[a]["ci_high"] - v for a, v in zip(arms, values)]]
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(arms), 3.2))
    ax.bar(arms, values, yerr=errors, capsize=4, color="tab:blue")
    ax.set_ylim(0, 1)
    ax.set_ylabel("success_once (pooled, 95% CI)")
    ax.set_title(f"{task}: one policy over views of its observation", fontsize=9)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
