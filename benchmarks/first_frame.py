"""What a process pays for its first rendered frame: SAPIEN computing its BRDF table, or reading ours.

    python benchmarks/first_frame.py                       # 3 rounds, PickCube-v1 RGB, ParallelEnv of 2 workers
    python benchmarks/first_frame.py --rounds 1 --steps 2  # a smoke run

SAPIEN computes its BRDF look-up table with a compute shader in every process
that renders (~6 s of both cores on lavapipe); ``mmada_rl/envs/brdf_lut.py``
gives every camera a table computed once per machine instead, and
``MMADA_RL_BRDF_LUT=sapien`` turns that off. Each round runs one fresh Python
process per table source, in alternating order. Each process times, after its
imports: the first env (``make_gym_env``, RGB) to the end of its first reset;
a second one in the same process (SAPIEN keeps its table for the process);
then a ``ParallelEnv`` of ``--workers`` RGB workers (forked from the fork
server: ``mmada_rl/envs/workers.py``), each of which renders its own first
frame, from construction to the end of a ``--steps``-step rollout. It reports
the CPU seconds of the processes it started beside its own. The table is
computed (and timed) once before the rounds, as ``scripts/setup.sh`` does.
Writes ``benchmarks/results/first_frame.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time

from common import RESULTS, alternating_processes, markdown_table, save_figure, write_results

SOURCES = ("sapien", "cached")
PHASES = ("first_env_s", "second_env_s", "parallel_env_s")


def child(args) -> dict:
    """One process's measurement (run with ``MMADA_RL_BRDF_LUT`` set by the parent)."""
    from mmada_rl.envs.maniskill import EnvConfig, make_env, make_gym_env
    from mmada_rl.envs.workers import stop_server

    cfg = EnvConfig(task=args.task, obs_mode="rgb")
    out = {}
    for phase in PHASES[:2]:
        start = time.perf_counter()
        env = make_gym_env(cfg)
        env.reset(seed=0)
        out[phase] = time.perf_counter() - start
        env.close()
    start = time.perf_counter()
    env = make_env(EnvConfig(task=args.task, obs_mode="rgb", num_workers=args.workers))
    env.reset()
    env.rollout(args.steps, break_when_any_done=False)
    out["parallel_env_s"] = time.perf_counter() - start
    env.close()
    stop_server()  # waits for the server, so that its CPU (and its reaped workers') is counted
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return {**out, "own_cpu_s": own.ru_utime + own.ru_stime, "children_cpu_s": kids.ru_utime + kids.ru_stime}


def plot(rows: dict, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for i, source in enumerate(SOURCES):
        axes[0].bar([k + 0.4 * i for k in range(len(PHASES))],
                    [statistics.median(r[phase] for r in rows[source]) for phase in PHASES], 0.4, label=source)
        axes[1].bar([0.4 * i, 1 + 0.4 * i], [statistics.median(r["own_cpu_s"] for r in rows[source]),
                                             statistics.median(r["children_cpu_s"] for r in rows[source])], 0.4, label=source)
    axes[0].set_xticks([k + 0.2 for k in range(len(PHASES))], ["first env", "second env", "ParallelEnv"])
    axes[0].set_ylabel("seconds")
    axes[0].legend(title="BRDF table")
    axes[1].set_xticks([0.2, 1.2], ["the process", "its workers and server"])
    axes[1].set_ylabel("CPU seconds")
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="PickCube-v1")
    p.add_argument("--workers", type=int, default=2, help="ParallelEnv workers (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="ParallelEnv rollout steps after its reset (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="processes per table source (default: %(default)s)")
    p.add_argument("--name", default="first_frame", help="result file name in benchmarks/results")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if min(args.workers, args.steps, args.rounds) < 1:
        p.error("--workers, --steps and --rounds must be positive")
    if args.child:
        print(json.dumps(child(args)))
        return 0
    from mmada_rl.envs.brdf_lut import brdf_lut, compute_brdf_lut

    start = time.perf_counter()
    compute_brdf_lut()
    compute_s = time.perf_counter() - start
    brdf_lut()  # the cache file, as scripts/setup.sh leaves it
    print(f"computing the table with numpy: {compute_s:.1f} s", flush=True)
    rows = alternating_processes(__file__, list(argv if argv is not None else sys.argv[1:]), "MMADA_RL_BRDF_LUT",
                                 SOURCES, args.rounds)
    med = statistics.median
    table = [[source, *(f"{med(r[k] for r in rows[source]):.1f}" for k in (*PHASES, "own_cpu_s", "children_cpu_s"))]
             for source in SOURCES]
    ratios = {k: med(s[k] / c[k] for s, c in zip(rows["sapien"], rows["cached"]))
              for k in ("first_env_s", "parallel_env_s", "children_cpu_s")}
    md = (f"## A process's first frame: SAPIEN's BRDF table or the cached one ({args.task}, RGB)\n\n" + markdown_table(
        ["BRDF table", "first env, s", "second env, s", f"ParallelEnv of {args.workers}, s", "CPU of the process, s",
         "CPU of its workers and server, s"], table))
    md += (f"\n\nMedians over {args.rounds} rounds, each a fresh process per table source, in alternating order; "
           f"times exclude the imports. Each env: construction and first reset; the ParallelEnv: construction, reset "
           f"and a {args.steps}-step rollout. SAPIEN's over the cached (median of the rounds' ratios): first env "
           f"**{ratios['first_env_s']:.2f}×**, ParallelEnv **{ratios['parallel_env_s']:.2f}×**, its workers' CPU "
           f"**{ratios['children_cpu_s']:.2f}×**. Computing the table with numpy, once per machine: {compute_s:.1f} s.")
    write_results(args.name, {"args": {k: v for k, v in vars(args).items() if k != "child"}, "results": rows,
                              "compute_s": compute_s, "sapien_over_cached": ratios}, md)
    plot(rows, RESULTS / f"{args.name}.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
