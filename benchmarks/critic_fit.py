"""How well can the privileged-state critic fit a fine-tuning run's value targets, with and without scaled inputs and targets?

    python benchmarks/critic_fit.py \\
        --online runs/compare_pick_hold/PickCube-v1/mmada_gae_noise_privileged/s2/online_buffer

A fine-tuning run with ``value.input=privileged_state`` stores each decision's
simulator state (``("observation", "privileged_state")``) and its GAE value
target in its online buffer. This fits a fresh
:class:`~mmada_rl.policy.value.PrivilegedValueNetwork` (the recipe's critic, its
width, learning rate and minibatch size) to those targets offline, on a random
``1 - --holdout`` of the rows, and scores the rest, for each input scaling:

* ``raw``: the state as the simulator gives it (what the recipe's critic reads);
* ``standardised``: each dimension minus its mean over the fitting rows, over its
  standard deviation (floored at 1e-3), unclipped (``clip=inf``);
* ``standardised, clipped to [-5, 5]``: the same, clipped (as running observation
  normalisers in RL do): the recipe's critic itself (``value.normalize_privileged=true``).

Both scaled rows are the network's own normaliser, its moments taken in from the
fitting rows by :meth:`~mmada_rl.policy.value.PrivilegedValueNetwork.observe`.

It reports the held-out and fitting mean squared errors and the share of the
held-out targets' variance explained. The targets were made with the run's own
critic, so this measures how well a critic of this form can follow them, not
which advantages a better critic would have given.

It then replays the run's critic as the recipe trains it: the rows in collection
order, ``--online-batch`` decisions at a time; each batch is first scored (the
error of the values GAE reads for those decisions' advantages) and then fitted
``--online-epochs`` times in minibatches with the recipe's own
:func:`~mmada_rl.policy.value.value_step`, for the recipe's critic
(standardised, clipped input) learning the targets as they are and standardised
by their running moments (:class:`~mmada_rl.policy.value.StandardizedValue`,
``value.normalize_targets=true``). The errors are averaged over each fifth of
the run.

Last, what the run's own critic gave: the correlation of the stored advantages
with the stored value targets (the λ-returns) over each fifth of the run. Near
1, the critic's values hardly vary between states and the advantages rank the
decisions by the return that followed them.

Writes ``benchmarks/results/critic_fit.{json,md,png}`` (``--name`` renames them).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402
from finetune_gradients import load_online_rows  # noqa: E402

from mmada_rl.keys import ADVANTAGE_KEY, PRIVILEGED_STATE_KEY, VALUE_TARGET_KEY  # noqa: E402
from mmada_rl.policy.value import (  # noqa: E402
    PrivilegedValueNetwork,
    StandardizedValue,
    make_value_operator,
    value_step,
)

#: each input scaling and the PrivilegedValueNetwork arguments that give it (the last is the recipe's critic)
SCALINGS = {"raw": {"normalize": False}, "standardised": {"normalize": True, "clip": math.inf},
            "standardised, clipped to [-5, 5]": {"normalize": True, "clip": 5.0}}


def fit(states, targets, fit_rows, held_out, *, scaling: str, hidden: int, lr: float, batch_size: int, steps: int,
        seed: int) -> dict:
    """Adam on the mean squared error from a seeded initialisation; the errors on both row sets at the end."""
    torch.manual_seed(seed)
    net = PrivilegedValueNetwork(states.shape[-1], hidden=hidden, **SCALINGS[scaling])
    net.observe(states[fit_rows])  # the moments the scaled rows read (the raw critic ignores them)
    optimizer = torch.optim.Adam(net.parameters(), lr=lr)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = fit_rows[torch.randint(len(fit_rows), (batch_size,), generator=generator)]
        loss = torch.nn.functional.mse_loss(net(states[idx]), targets[idx])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        mse = {name: float(torch.nn.functional.mse_loss(net(states[rows]), targets[rows]))
               for name, rows in (("held_out_mse", held_out), ("fit_mse", fit_rows))}
    variance = float(targets[held_out].var())
    return {**mse, "held_out_variance": variance, "explained": 1.0 - mse["held_out_mse"] / variance}


#: the critics replayed in collection order: whether each learns standardised targets
TARGETS = {"targets as they are": False, "standardised targets (value.normalize_targets)": True}
PARTS = 5


def replay(rows, *, standardized: bool, batch_decisions: int, epochs: int, hidden: int, lr: float, batch_size: int,
           seed: int) -> dict:
    """The recipe's critic over the run's rows in collection order: each batch of ``batch_decisions`` is scored
    before it is fitted (``epochs`` passes in minibatches of ``batch_size``); the mean error of each fifth."""
    torch.manual_seed(seed)
    net = PrivilegedValueNetwork(rows.get(PRIVILEGED_STATE_KEY).shape[-1], hidden=hidden)
    value_op = make_value_operator(StandardizedValue(net) if standardized else net)
    optimizer = torch.optim.Adam(value_op.parameters(), lr=lr)
    generator, errors = torch.Generator().manual_seed(seed), []
    for start in range(0, len(rows) - batch_decisions + 1, batch_decisions):
        batch = rows[start:start + batch_decisions]
        with torch.no_grad():
            pred = value_op(batch.select(*value_op.in_keys).clone()).get("state_value")
            errors.append(float(torch.nn.functional.mse_loss(pred, batch.get(VALUE_TARGET_KEY).reshape(pred.shape))))
        for _ in range(epochs):
            for idx in torch.randperm(len(batch), generator=generator).split(batch_size):
                value_step(value_op, optimizer, batch[idx], batch[idx].get(VALUE_TARGET_KEY))
    parts = [sum(errors[a:b]) / max(1, b - a) for a, b in fifths(len(errors))]
    return {"batches": len(errors), "error_by_fifth": parts, "mean_error": sum(errors) / max(1, len(errors))}


def fifths(n: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of each fifth of ``n`` items in order."""
    bounds = [round(i * n / PARTS) for i in range(PARTS + 1)]
    return list(zip(bounds, bounds[1:]))


def stored_correlation(rows) -> list[float]:
    """The correlation of the run's stored advantages with its stored value targets, per fifth of the rows (NaN for
    a fifth of fewer than two rows)."""
    advantages = rows.get(ADVANTAGE_KEY).float().reshape(-1)
    targets = rows.get(VALUE_TARGET_KEY).float().reshape(-1)
    return [float(torch.corrcoef(torch.stack([advantages[a:b], targets[a:b]]))[0, 1]) if b - a >= 2 else math.nan
            for a, b in fifths(len(rows))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--online", type=Path, required=True,
                        help="online_buffer/ of a fine-tuning run with value.input=privileged_state")
    parser.add_argument("--holdout", type=float, default=0.2, help="share of the rows scored, not fitted (default: 0.2)")
    parser.add_argument("--steps", type=int, default=3000, help="minibatch steps of each fit (default: 3000)")
    parser.add_argument("--hidden", type=int, default=256, help="critic width (default: 256, maniskill.yaml's value.hidden)")
    parser.add_argument("--lr", type=float, default=3e-4, help="learning rate (default: 3e-4, the recipe's value.lr)")
    parser.add_argument("--batch-size", type=int, default=64, help="rows per step (default: 64, maniskill.yaml's)")
    parser.add_argument("--online-batch", type=int, default=40,
                        help="decisions per batch of the collection-order replay (default: 40, maniskill.yaml's "
                             "collector.decisions_per_batch)")
    parser.add_argument("--online-epochs", type=int, default=4,
                        help="passes over each batch in the replay (default: 4, maniskill.yaml's value.epochs)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default="critic_fit")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if not 0.0 < args.holdout < 1.0 or args.steps < 1:
        parser.error("--holdout must lie in (0, 1) and --steps be >= 1.")
    if args.online_batch < 1 or args.online_epochs < 1:
        parser.error("--online-batch and --online-epochs must be >= 1.")

    rows = load_online_rows(args.online)
    if PRIVILEGED_STATE_KEY not in rows.keys(include_nested=True):
        raise SystemExit(f"{args.online} holds no {PRIVILEGED_STATE_KEY}: the run's critic read the observation "
                         "(fine-tune with value.input=privileged_state).")
    states = rows.get(PRIVILEGED_STATE_KEY).float()
    targets = rows.get(VALUE_TARGET_KEY).float().reshape(-1, 1)
    order = torch.randperm(len(rows), generator=torch.Generator().manual_seed(args.seed))
    split = int(round(len(rows) * (1.0 - args.holdout)))
    fit_rows, held_out = order[:split], order[split:]
    if len(fit_rows) < 2 or len(held_out) < 2:
        raise SystemExit(f"{args.online} holds {len(rows)} rows: too few to fit and score (--holdout {args.holdout}).")
    if len(rows) < PARTS * args.online_batch:
        raise SystemExit(f"{args.online} holds {len(rows)} rows: too few for {PARTS} parts of --online-batch "
                         f"{args.online_batch}.")

    results = {s: fit(states, targets, fit_rows, held_out, scaling=s, hidden=args.hidden, lr=args.lr,
                      batch_size=args.batch_size, steps=args.steps, seed=args.seed) for s in SCALINGS}
    in_order = {name: replay(rows, standardized=standardized, batch_decisions=args.online_batch,
                             epochs=args.online_epochs, hidden=args.hidden, lr=args.lr, batch_size=args.batch_size,
                             seed=args.seed) for name, standardized in TARGETS.items()}
    correlation = stored_correlation(rows)
    spread = states[fit_rows].std(0)
    widest = spread.argsort(descending=True)[:3].tolist()
    table = markdown_table(["input", "held-out MSE", "fitting MSE", "held-out variance explained"],
                           [[s, f"{r['held_out_mse']:.1f}", f"{r['fit_mse']:.1f}", f"{r['explained']:.2f}"]
                            for s, r in results.items()])
    markdown = (f"# Critic fit on `{args.online}`\n\n{len(rows)} rows ({len(fit_rows)} fitted, {len(held_out)} held out), "
                f"{states.shape[-1]}-dimensional privileged state; value targets {float(targets.min()):.1f} to "
                f"{float(targets.max()):.1f} (held-out variance {results['raw']['held_out_variance']:.1f}); "
                f"{args.steps} steps of {args.batch_size} rows. The widest state dimensions: "
                + ", ".join(f"{d} (std {float(spread[d]):.2f})" for d in widest) + ".\n\n" + table
                + f"\n\n## In collection order\n\nThe recipe's critic (standardised, clipped input) over the rows as "
                f"they were collected, {args.online_batch} decisions at a time, each batch scored before it is fitted "
                f"({args.online_epochs} passes in minibatches of {args.batch_size}): the mean squared error of the "
                f"values GAE would read, averaged over each fifth of the run (all targets' variance "
                f"{float(targets.var()):.1f}).\n\n"
                + markdown_table(["critic", *(f"fifth {i + 1}" for i in range(PARTS)), "mean"],
                                 [[name, *(f"{e:.1f}" for e in r["error_by_fifth"]), f"{r['mean_error']:.1f}"]
                                  for name, r in in_order.items()])
                + "\n\n## What the run's critic gave\n\nThe correlation of the run's stored advantages with its "
                "stored value targets, per fifth of the run: "
                + ", ".join(f"{c:.2f}" for c in correlation) + ".")
    payload = {"online": str(args.online), "rows": len(rows), "fitted": len(fit_rows), "held_out": len(held_out),
               "steps": args.steps, "hidden": args.hidden, "lr": args.lr, "batch_size": args.batch_size,
               "widest_dims": {str(d): float(spread[d]) for d in widest}, "results": results,
               "online_batch": args.online_batch, "online_epochs": args.online_epochs,
               "target_variance": float(targets.var()), "in_order": in_order,
               "advantage_target_correlation_by_fifth": correlation}
    json_path, md_path = write_results(args.name, payload, markdown, args.out)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 3.2))
    ax.bar(range(len(SCALINGS)), [results[s]["explained"] for s in SCALINGS])
    ax.set_xticks(range(len(SCALINGS)), ["raw", "standardised", "std. + clip"])
    ax.set_ylabel("held-out variance explained")
    ax.set_title("privileged-state critic on the run's value targets")
    for name, r in in_order.items():
        ax2.plot(range(1, PARTS + 1), r["error_by_fifth"], marker="o", label=name)
    ax2.axhline(float(targets.var()), color="grey", linestyle=":", label="targets' variance")
    ax2.set_xticks(range(1, PARTS + 1))
    ax2.set_xlabel("fifth of the run")
    ax2.set_ylabel("error on each fresh batch")
    ax2.set_title("in collection order")
    ax2.legend(fontsize=7)
    png = save_figure(fig, args.out / f"{args.name}.png")
    print(markdown)
    print(f"wrote {json_path}, {md_path}, {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
