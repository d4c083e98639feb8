"""How well does a checkpoint fit each task's demonstrations?

    python benchmarks/demo_fit.py \\
        --run runs/push_bins_s0=PushCube-v1 \\
        --run runs/multitask_bins_s0=PickCube-v1,PushCube-v1,StackCube-v1

For every ``RUN=TASK[,TASK...]`` pair it draws ``--minibatches`` minibatches of
chunk windows from the task's demonstrations (``--demos``: a template with
``{task}`` filled in, and/or ``TASK=PATH`` for a task's own buffer, e.g.
``--demos 'data/dart/{task}-fov45' PushCube-v1=data/dart/PushCube-v1-fov60``;
each buffer must have been recorded with the policy's camera, image size and
observations for that task), masks the target tokens (goal image + action chunk) at each fixed ratio of
``--ratios`` and reports the denoiser's accuracy on the masked action and goal
tokens. It also decodes each window's chunk greedily with the model's sampler
(the N steps the policy runs) and reports its mean absolute error against the
demonstrated chunk, in the environment's action units, per action dimension.
``--decode READOUT:N`` (repeatable) decodes instead with each of the given
action read-outs and step counts, e.g. ``--decode token:10 --decode mean:1``
(``mean:1``: every action token's expected bin from one pass over the fully
masked chunk, the conditional mean a regression policy predicts).
``--swap image`` / ``--swap state`` (repeatable) decodes the same windows once
more with that input of each window replaced by the next window's of its
minibatch (another episode at another phase: another cube position and arm
pose), the rest left as it is: the error's rise measures how much the
prediction follows that input. A policy that predicts from the arm's state and
ignores where the cube is seen fits the demonstrations with the image swapped
almost as well as without.
A BC or Diffusion Policy run (``recipes/baselines/imitation.py``) gets the
same decoded error on the same windows (its own chunk prediction), so the
policy's fit can be set beside the baseline's at equal updates.
The same seed gives every run the same windows and the same masks, so two
checkpoints are compared on identical inputs. Ratio 1.0 is what the first of
the N decoding steps sees (every target masked).

Token accuracies of two models are comparable only when they share an action
tokenizer: a multi-task tokenizer spans every task's action range, so its bins
are wider and a token is easier to hit. The decoded error is in action units
and compares any two models.

The windows are the training demonstrations (there is no held-out split of 100
demonstrations): this measures how well a model has fitted each task, e.g. a
multi-task model against the per-task ones at the same number of updates.

Writes ``benchmarks/results/demo_fit.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402

from mmada_rl.data import BufferMismatchError  # noqa: E402
from mmada_rl.keys import IMAGE_KEY, IMAGE_TOKENS_KEY, STATE_KEY  # noqa: E402
from mmada_rl.evaluation import eval_env_config, load_actor  # noqa: E402
from mmada_rl.policy import MMaDAActor, MMaDAModel  # noqa: E402
from mmada_rl.policy.model import ACTION_READOUTS  # noqa: E402
from mmada_rl.training.demos import open_demos  # noqa: E402
from mmada_rl.training.validation import chunk_error, fixed_windows, masked_token_scores  # noqa: E402


def parse_run(text: str) -> tuple[Path, list[str]]:
    """``RUN=TASK[,TASK...]`` -> (run path, tasks)."""
    run, sep, tasks = text.partition("=")
    names = [t for t in tasks.split(",") if t]
    if not sep or not run or not names:
        raise argparse.ArgumentTypeError(f"expected RUN=TASK[,TASK...], got {text!r}.")
    return Path(run), names


def parse_demos(specs: list[str]) -> tuple[str | None, dict[str, Path]]:
    """``--demos`` entries -> (the template, ``{task}`` filled in per task, or None; {task: its own buffer})."""
    templates = [spec for spec in specs if "=" not in spec]
    named = dict(spec.split("=", 1) for spec in specs if "=" in spec)
    if len(templates) > 1 or not all(named) or not all(named.values()):
        raise argparse.ArgumentTypeError(f"--demos takes at most one path template (with {{task}}) and TASK=PATH "
                                         f"entries, got {specs}.")
    return (templates[0] if templates else None), {task: Path(path) for task, path in named.items()}


def demos_path(demos: tuple[str | None, dict[str, Path]], task: str) -> Path | None:
    """The buffer of ``task``: its own ``TASK=PATH`` entry, else the template filled in (None: neither)."""
    template, named = demos
    return named.get(task) or (Path(template.format(task=task)) if template else None)


def parse_decode(text: str) -> tuple[str, int]:
    """``READOUT:N`` -> (read-out, decoding steps N)."""
    readout, sep, steps = text.partition(":")
    if not sep or readout not in ACTION_READOUTS or not steps.isdigit() or int(steps) < 1:
        raise argparse.ArgumentTypeError(f"expected READOUT:N with READOUT in {ACTION_READOUTS} and N >= 1, "
                                         f"got {text!r}.")
    return readout, int(steps)


#: The inputs ``--swap`` replaces, and the keys that hold each (the image's tokens when a window carries them).
SWAPS = {"image": (IMAGE_KEY, IMAGE_TOKENS_KEY), "state": (STATE_KEY,)}


def swapped(batches, what: str | None):
    """``batches`` with the ``what`` input of every window replaced by the next window's of its minibatch (rolled by
    one); ``None``: ``batches`` as they are."""
    if what is None:
        return batches
    out = []
    for batch in batches:
        batch = batch.clone()
        for key in SWAPS[what]:
            if key in batch.keys(include_nested=True):
                batch.set(key, batch.get(key).roll(1, dims=0))
        out.append(batch)
    return out


def decoded_row(run: Path, task: str, model, batches, swap: str | None = None) -> dict:
    """The error of ``model``'s chunks on ``batches`` as it decodes now (an MMaDA policy: its N and read-out), with
    the ``swap`` input of each window taken from another (:func:`swapped`)."""
    mae = chunk_error(model, swapped(batches, swap))
    mmada = isinstance(model, MMaDAModel)
    return {"run": str(run), "task": task, "swapped": swap,
            "num_denoise_steps": model.sampler.config.num_steps if mmada else None,
            "action_readout": model.action_readout if mmada else None,
            "chunk_mae_per_dim": mae, "chunk_mae": sum(mae) / len(mae)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=parse_run, action="append", required=True, metavar="RUN=TASK[,TASK...]",
                        help="a pretraining run (or checkpoint / model directory; a BC or Diffusion Policy run gets the "
                             "decoded error only) and the tasks to score it on; repeatable")
    parser.add_argument("--demos", nargs="+", default=["data/{task}"], metavar="TEMPLATE|TASK=PATH",
                        help="demonstration buffers: a path template with {task}, and/or TASK=PATH for a task's own "
                             "(default: data/{task}); each must match the policy's camera and image size for its task")
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.5, 0.8, 1.0],
                        help="masking ratios of the target tokens (default: 0.5 0.8 1.0)")
    parser.add_argument("--minibatches", type=int, default=20, help="minibatches per (run, task, ratio) (default: 20)")
    parser.add_argument("--batch-size", type=int, default=16, help="windows per minibatch (default: 16)")
    parser.add_argument("--decode-minibatches", type=int, default=4,
                        help="minibatches whose chunks are decoded greedily (default: 4; 0 skips decoding)")
    parser.add_argument("--decode", type=parse_decode, action="append", default=None, metavar="READOUT:N",
                        help="MMaDA-VLA runs: decode with this action read-out (token | mean) and N steps; "
                             "repeatable, one row each (default: the policy's own)")
    parser.add_argument("--swap", choices=sorted(SWAPS), action="append", default=[],
                        help="decode once more with this input of each window taken from another window of its "
                             "minibatch; repeatable, one row each (default: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="demo_fit", help="results file stem (default: demo_fit)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.minibatches < 1 or args.batch_size < 1 or args.decode_minibatches < 0:
        parser.error("--minibatches and --batch-size must be >= 1, --decode-minibatches >= 0.")
    if any(not 0.0 < r <= 1.0 for r in args.ratios):
        parser.error(f"every ratio must be in (0, 1], got {args.ratios}.")
    try:
        demos_of = parse_demos(args.demos)
    except argparse.ArgumentTypeError as err:
        parser.error(str(err))
    for _, tasks in args.run:
        for task in tasks:
            path = demos_path(demos_of, task)
            if path is None or not path.exists():
                parser.error(f"no demonstration buffer for {task}" + (f" at {path}." if path else " in --demos."))

    results, decoded = [], []
    bar = tqdm(total=sum(len(tasks) for _, tasks in args.run) * (len(args.ratios) + 1), desc="demo fit")
    for run, tasks in args.run:
        actor = load_actor(run)
        model = actor.model if isinstance(actor, MMaDAActor) else actor  # a baseline has no tokens to score
        model.eval()
        for task in tasks:
            try:  # opened once for every ratio and the decoding, checked against the policy's view of the task
                demos = open_demos(demos_path(demos_of, task), eval_env_config(actor, task))
            except (BufferMismatchError, ValueError) as err:
                parser.error(f"{run} on {task}: {err}")
            chunk_size = model.config.chunk_size if isinstance(model, MMaDAModel) else model.chunk_size
            if isinstance(model, MMaDAModel):  # a baseline has no tokens to score
                batches = fixed_windows(demos, chunk_size, args.minibatches, args.batch_size, args.seed)  # every ratio's
                for ratio in args.ratios:
                    scores = masked_token_scores(model, batches, ratio, seed=args.seed)
                    results.append({"run": str(run), "task": task, "ratio": ratio, **scores})
            bar.update(len(args.ratios))
            if args.decode_minibatches:
                batches = fixed_windows(demos, chunk_size, args.decode_minibatches, args.batch_size, args.seed)
                for swap in [None, *args.swap]:
                    if not isinstance(model, MMaDAModel):  # a baseline decodes as it acts
                        decoded.append(decoded_row(run, task, model, batches, swap))
                        continue
                    for readout, steps in args.decode or [(None, None)]:  # None: the policy's own
                        with model.decoding(num_steps=steps, readout=readout):
                            decoded.append(decoded_row(run, task, model, batches, swap))
            bar.update()
    bar.close()

    header = ["run", "task", "mask ratio", "action-token accuracy", "goal-token accuracy", "action CE"]
    rows = [[r["run"], r["task"], f"{r['ratio']:.2f}", f"{r['action_accuracy']:.3f}",
             f"{r['goal_accuracy']:.3f}" if "goal_accuracy" in r else "-", f"{r['loss_action']:.3f}"] for r in results]
    table = markdown_table(header, rows)
    if decoded:
        table += ("\n\nPredicted chunks (MMaDA-VLA: greedily decoded, N steps; baselines: as they act) against the "
                  "demonstrated ones (mean absolute error, action units):\n\n")
        table += markdown_table(["run", "task", "swapped input", "read-out", "N", "all dims", "per dim"],
                                [[d["run"], d["task"], d["swapped"] or "-", d["action_readout"] or "-",
                                  d["num_denoise_steps"] or "-",
                                  f"{d['chunk_mae']:.4f}",
                                  " ".join(f"{x:.4f}" for x in d["chunk_mae_per_dim"])] for d in decoded])

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for run, tasks in args.run:
        for task in tasks:
            mine = [r for r in results if r["run"] == str(run) and r["task"] == task]
            if not mine:  # a baseline: no tokens
                continue
            ax.plot([r["ratio"] for r in mine], [r["action_accuracy"] for r in mine], marker="o", label=f"{run.name} / {task}")
    ax.set_xlabel("masking ratio of the targets")
    ax.set_ylabel("action-token accuracy")
    ax.legend(fontsize=7)
    save_figure(fig, args.out / f"{args.name}.png")
    payload = {"runs": {str(run): tasks for run, tasks in args.run}, "demos": args.demos, "minibatches": args.minibatches,
               "decode": [f"{readout}:{steps}" for readout, steps in args.decode or []], "swap": args.swap,
               "batch_size": args.batch_size, "seed": args.seed, "results": results, "decoded": decoded}
    command = "python benchmarks/demo_fit.py " + " ".join(f"--run {run}={','.join(tasks)}" for run, tasks in args.run)
    command += " --demos " + " ".join(shlex.quote(spec) for spec in args.demos)
    command += "".join(f" --decode {readout}:{steps}" for readout, steps in args.decode or [])
    command += "".join(f" --swap {what}" for what in args.swap)
    write_results(args.name, payload,
                  f"# How well each checkpoint fits the demonstrations\n\n`{command}`\n\n{args.minibatches} minibatches of "
                  f"{args.batch_size} windows per row; the same windows and masks for every run.\n\n{table}\n\n"
                  f"![accuracy]({args.name}.png)\n", directory=args.out)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
