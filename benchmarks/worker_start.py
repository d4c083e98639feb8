"""How long simulator workers take to start: spawned, or forked from a server with the imports done.

    python benchmarks/worker_start.py                  # 3 rounds, ParallelEnv of 2 RGB workers built 3 times a process
    python benchmarks/worker_start.py --rounds 1 --starts 2 --obs-mode state   # a smoke run

``make_env(num_workers=N)`` starts ``ParallelEnv``'s workers the way
``mmada_rl/envs/workers.py`` says (``forkserver``, preloading torch, tensordict,
TorchRL and ManiSkill); ``MMADA_RL_WORKER_START=spawn`` starts them spawned, as
before. Each round runs one fresh Python process per start method, in
alternating order; each process builds the ParallelEnv ``--starts`` times in a
row (a recipe builds its training env, then its evaluation env, and a test
process many), timing each from construction to the end of its first reset and a
``--steps``-step rollout, then closing it. The process reports the CPU seconds
of everything it started (workers, and the fork server, stopped and waited for
at the end), beside its own. Writes ``benchmarks/results/worker_start.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time

from common import RESULTS, alternating_processes, markdown_table, save_figure, write_results

METHODS = ("spawn", "forkserver")


def child(args) -> dict:
    """One process's measurement (run with ``MMADA_RL_WORKER_START`` set by the parent)."""
    from mmada_rl.envs.maniskill import EnvConfig, make_env
    from mmada_rl.envs.workers import stop_server

    cfg = EnvConfig(task=args.task, obs_mode=args.obs_mode, num_workers=args.workers)
    seconds = []
    for _ in range(args.starts):
        start = time.perf_counter()
        env = make_env(cfg)
        env.reset()
        env.rollout(args.steps, break_when_any_done=False)
        seconds.append(time.perf_counter() - start)
        env.close()
    stop_server()  # waits for the server, so that its CPU (and its reaped workers') is counted
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"start_s": seconds, "own_cpu_s": own.ru_utime + own.ru_stime, "children_cpu_s": kids.ru_utime + kids.ru_stime}


def plot(rows: dict, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for i, method in enumerate(METHODS):
        starts = list(zip(*[r["start_s"] for r in rows[method]]))
        axes[0].bar([k + 0.4 * i for k in range(len(starts))], [statistics.median(s) for s in starts], 0.4, label=method)
        axes[1].bar(i, statistics.median(r["children_cpu_s"] for r in rows[method]), 0.6, label=method)
    axes[0].set_xlabel("ParallelEnv built in the process (1st, 2nd, ...)")
    axes[0].set_ylabel("seconds to the end of a short rollout")
    axes[0].set_xticks([k + 0.2 for k in range(len(starts))], [str(k + 1) for k in range(len(starts))])
    axes[0].legend()
    axes[1].set_xticks(range(len(METHODS)), METHODS)
    axes[1].set_ylabel("CPU seconds of the started processes")
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="PickCube-v1")
    p.add_argument("--obs-mode", default="rgb", choices=("rgb", "state"))
    p.add_argument("--workers", type=int, default=2, help="ParallelEnv workers (default: %(default)s)")
    p.add_argument("--starts", type=int, default=3, help="ParallelEnvs built one after another per process (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="rollout steps after the first reset (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="processes per start method (default: %(default)s)")
    p.add_argument("--name", default="worker_start", help="result file name in benchmarks/results")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if min(args.workers, args.starts, args.steps, args.rounds) < 1:
        p.error("--workers, --starts, --steps and --rounds must be positive")
    if args.child:
        print(json.dumps(child(args)))
        return 0
    rows = alternating_processes(
        __file__, list(argv if argv is not None else sys.argv[1:]), "MMADA_RL_WORKER_START", METHODS, args.rounds,
        lambda r: f"starts {[round(s, 1) for s in r['start_s']]} s, started processes' CPU {r['children_cpu_s']:.1f} s")
    med = statistics.median
    table = []
    for method in METHODS:
        starts = list(zip(*[r["start_s"] for r in rows[method]]))
        table.append([method, f"{med(starts[0]):.1f}", f"{med(s for later in starts[1:] for s in later):.1f}" if len(starts) > 1 else "-",
                      f"{med(sum(r['start_s']) for r in rows[method]):.1f}",
                      f"{med(r['children_cpu_s'] for r in rows[method]):.1f}", f"{med(r['own_cpu_s'] for r in rows[method]):.1f}"])
    spawn_total = [sum(r["start_s"]) for r in rows["spawn"]]
    fork_total = [sum(r["start_s"]) for r in rows["forkserver"]]
    ratio = med(s / f for s, f in zip(spawn_total, fork_total))
    md = (f"## Simulator worker start-up ({args.task}, {args.obs_mode}, ParallelEnv of {args.workers} workers, "
          f"built {args.starts} times per process)\n\n" + markdown_table(
              ["start method", "first ParallelEnv, s", "each later one, s", f"all {args.starts}, s",
               "CPU of the started processes, s", "CPU of the process itself, s"], table))
    md += (f"\n\nMedians over {args.rounds} rounds, each a fresh process per start method, in alternating order. "
           f"Each time: construction, first reset and a {args.steps}-step rollout. The forkserver's CPU includes the "
           f"server's own imports. All {args.starts} together, spawn over forkserver: **{ratio:.2f}×** (median of "
           f"the rounds' ratios).")
    write_results(args.name, {"args": {k: v for k, v in vars(args).items() if k != "child"}, "results": rows,
                              "spawn_over_forkserver": ratio}, md)
    plot(rows, RESULTS / f"{args.name}.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
