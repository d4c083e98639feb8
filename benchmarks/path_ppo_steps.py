"""Cost and fidelity of replaying a subset of the decoding steps in path-likelihood PPO.

    python benchmarks/path_ppo_steps.py --pretrained runs/push_fov60_s1 --task PushCube-v1 \\
        --decisions 16 --steps 1 2 5 --draws 8

:class:`~mmada_rl.objectives.PathPPOLoss` replays the stored decoding path of
every chunk under the current parameters: one denoiser forward pass per decoding
step, so an update costs ``N`` times a plain denoising step. With
``denoising_steps=S`` each loss call replays ``S`` of the ``N`` steps of every
path (drawn uniformly), an unbiased estimate of the step-level objective.

This benchmark samples ``--decisions`` chunks with the pretrained policy in the
real ManiSkill task (sampled decoding, the model's own temperature), gives them
fixed standard-normal advantages, and for each ``S`` (interleaved with the full
replay, so the two are timed side by side) measures

* the wall time of one loss forward + backward on the whole batch, and its ratio
  to the full replay's (median over ``--draws`` pairs);
* the cosine between the gradient of one draw and the full replay's gradient,
  and the norm ratio: how much of the full update a single draw carries.

At unchanged parameters every ratio is 1, so the gradient is the policy
gradient of the sampled paths; the full replay's is deterministic.

Writes ``benchmarks/results/path_ppo_steps.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, flat_gradient, markdown_table, save_figure, write_results  # noqa: E402


def timed_grad(loss_fn, batch, params) -> tuple[float, torch.Tensor]:
    for p in params:
        p.grad = None
    start = time.perf_counter()
    loss_fn(batch)["loss_objective"].backward()
    return time.perf_counter() - start, flat_gradient(params, [p.grad for p in params])


def sample_chunks(model, task: str, decisions: int, seed: int):
    """``decisions`` chunks sampled by the policy in the real task, with their decoding paths."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mmada_rl.envs import make_env
    from mmada_rl.policy import MMaDAActor, make_policy_env

    env = make_env(task, image_size=model.image_size, camera_fov=model.config.camera_fov_for(task))
    env.set_seed(seed)
    penv = make_policy_env(env, MMaDAActor(model), chunk_gamma=0.99)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        rollout = penv.env.rollout(decisions, penv.policy, break_when_any_done=False)
    env.close()
    return rollout


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pretrained", required=True, help="pretraining run, checkpoint or saved model directory")
    parser.add_argument("--task", required=True)
    parser.add_argument("--decisions", type=int, default=16, help="sampled chunks in the batch (the recipe's minibatch)")
    parser.add_argument("--steps", nargs="+", type=int, default=[1, 2, 5], help="replayed decoding steps S per path")
    parser.add_argument("--draws", type=int, default=8, help="loss calls per setting")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--name", default="path_ppo_steps")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)

    from mmada_rl.evaluation import resolve_model_dir
    from mmada_rl.keys import ADVANTAGE_KEY
    from mmada_rl.objectives import PathPPOLoss
    from mmada_rl.policy import MMaDAModel

    model = MMaDAModel.load(resolve_model_dir(args.pretrained)).eval()
    num_steps = int(model.sampler.config.num_steps)
    if any(not 0 < s < num_steps for s in args.steps):
        parser.error(f"--steps must lie in [1, {num_steps - 1}] (the policy decodes in {num_steps} steps).")
    batch = sample_chunks(model, args.task, args.decisions, args.seed)
    advantage = torch.randn(args.decisions, generator=torch.Generator().manual_seed(args.seed))
    batch.set(ADVANTAGE_KEY, (advantage - advantage.mean()) / advantage.std())
    params = [p for p in model.denoiser.parameters() if p.requires_grad]
    full_fn = PathPPOLoss(model.denoiser)
    _, full = timed_grad(full_fn, batch, params)  # warm-up; deterministic

    records = []
    for s in args.steps:
        loss_fn = PathPPOLoss(model.denoiser, denoising_steps=s)
        ratios, times, cosines, norms, grads = [], [], [], [], []
        for _ in range(args.draws):
            t_full, _ = timed_grad(full_fn, batch, params)
            t, g = timed_grad(loss_fn, batch, params)
            ratios.append(t / t_full)
            times.append(t)
            cosines.append(float(torch.nn.functional.cosine_similarity(g, full, dim=0)))
            norms.append(float(g.norm() / full.norm()))
            grads.append(g)
        mean_grad = torch.stack(grads).mean(0)
        records.append({
            "denoising_steps": s, "num_steps": num_steps, "time_s_median": statistics.median(times),
            "time_ratio_to_full_median": statistics.median(ratios), "cos_to_full_mean": statistics.mean(cosines),
            "cos_to_full_min": min(cosines), "norm_ratio_mean": statistics.mean(norms),
            "cos_mean_of_draws_to_full": float(torch.nn.functional.cosine_similarity(mean_grad, full, dim=0)),
        })
        print(records[-1], flush=True)

    header = ["replayed steps S (of N)", "time / full replay", "cos(draw, full gradient)", "norm(draw) / norm(full)",
              f"cos(mean of {args.draws} draws, full)"]
    rows = [[f"{r['denoising_steps']} of {num_steps}", f"{r['time_ratio_to_full_median']:.2f}",
             f"{r['cos_to_full_mean']:.2f} (min {r['cos_to_full_min']:.2f})", f"{r['norm_ratio_mean']:.2f}",
             f"{r['cos_mean_of_draws_to_full']:.2f}"] for r in records]
    markdown = (f"# Path PPO: replaying S of the N decoding steps ({args.task}, `{args.pretrained}`)\n\n"
                f"{args.decisions} chunks sampled by the policy in the task, fixed standard-normal advantages; "
                f"one loss forward + backward on the whole batch; time ratios are medians of {args.draws} side-by-side pairs "
                "with the full replay.\n\n" + markdown_table(header, rows))
    payload = {"task": args.task, "pretrained": args.pretrained, "decisions": args.decisions, "draws": args.draws,
               "records": records}
    json_path, md_path = write_results(args.name, payload, markdown, args.out)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.5))
    xs = [r["denoising_steps"] for r in records] + [num_steps]
    ax1.plot(xs, [r["time_ratio_to_full_median"] for r in records] + [1.0], "o-")
    ax1.plot(xs, [x / num_steps for x in xs], "k:", label="S / N")
    ax1.set(xlabel="replayed steps S", ylabel="time / full replay", title="cost of one update")
    ax1.legend()
    ax2.plot(xs, [r["cos_to_full_mean"] for r in records] + [1.0], "o-", label="one draw")
    ax2.plot(xs, [r["cos_mean_of_draws_to_full"] for r in records] + [1.0], "s--", label=f"mean of {args.draws} draws")
    ax2.set(xlabel="replayed steps S", ylabel="cosine to the full gradient", title="fidelity", ylim=(0, 1.05))
    ax2.legend()
    save_figure(fig, args.out / f"{args.name}.png")
    print(f"wrote {json_path}, {md_path} and {args.out / f'{args.name}.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
