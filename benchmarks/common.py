"""Helpers shared by the benchmarks: result files (JSON + Markdown + PNG) and machine facts."""
from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    import torch

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def write_results(name: str, payload: dict, markdown: str, directory: Path = RESULTS) -> tuple[Path, Path]:
    """Write ``results/NAME.json`` and ``results/NAME.md`` (the Markdown gets the command line)."""
    directory.mkdir(parents=True, exist_ok=True)
    command = "python " + shlex.join([os.path.relpath(sys.argv[0])] + sys.argv[1:])  # quoted as typed
    payload = {"command": command, "machine": machine(), **payload}
    json_path = directory / f"{name}.json"
    md_path = directory / f"{name}.md"
    json_path.write_text(json.dumps(payload, indent=2))
    md_path.write_text(f"{markdown.rstrip()}\n\nReproduce: `{command}` ({payload['machine']['date']}, "
                       f"{payload['machine']['cpu_count']} CPU cores, torch {payload['machine']['torch']}).\n")
    return json_path, md_path


def save_figure(fig, path: Path, **savefig_kwargs) -> Path:
    """Lay out ``fig``, write it to ``path`` (its folder created; 120 dpi) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, **savefig_kwargs)
    plt.close(fig)
    return path


def alternating_processes(script: str, argv: list[str], variable: str, values: tuple[str, ...], rounds: int,
                          describe=lambda result: ", ".join(f"{k} {v:.1f}" for k, v in result.items())) -> dict[str, list[dict]]:
    """Run ``script argv --child`` once per value of the environment ``variable`` in each of ``rounds`` rounds,
    in alternating order (fresh processes, so none inherits another's warm state); each child prints its
    measurement as JSON on its last line. Returns the measurements per value; exits with the child's error if one
    fails.
    """
    rows: dict[str, list[dict]] = {value: [] for value in values}
    for r in range(rounds):
        for value in values if r % 2 == 0 else values[::-1]:
            out = subprocess.run([sys.executable, os.path.abspath(script), *argv, "--child"],
                                 env={**os.environ, variable: value}, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                sys.exit(f"the {variable}={value} process failed:\n{out.stderr[-3000:]}")
            rows[value].append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"round {r}: {value} {describe(rows[value][-1])}", flush=True)
    return rows


def flat_gradient(params: list, grads: list) -> "torch.Tensor":
    """One flat vector of the gradients of ``params`` (zeros where a gradient is ``None``)."""
    import torch

    return torch.cat([(torch.zeros_like(p) if g is None else g).reshape(-1) for p, g in zip(params, grads)])


def markdown_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def parse_devices(parser, option: str, names: list[str]) -> list:
    """The torch devices of a benchmark's ``option`` (``names`` as typed); ``parser.error`` on a malformed
    name or a CUDA device that torch does not see here."""
    import torch

    try:
        devices = [torch.device(name) for name in names]
    except RuntimeError as err:
        parser.error(f"{option}: {err}")
    missing = [name for name, device in zip(names, devices) if device.type == "cuda" and not torch.cuda.is_available()]
    if missing:
        parser.error(f"{option} {' '.join(missing)}: torch sees no CUDA device on this machine.")
    return devices


def synchronize(device) -> None:
    """Wait for the work queued on ``device``, so a timing ends when the work does, not when it was launched."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def maniskill_env(env):
    """The ManiSkill task (``BaseEnv``) under a TorchRL env built by :func:`mmada_rl.envs.make_env`."""
    while not hasattr(env, "_env"):
        env = env.base_env
    return env._env.unwrapped


def probed_episode(penv, seed: int, max_decisions: int, probe, executed: list | None = None) -> tuple[list, bool]:
    """One greedy evaluation episode from ``reset(seed=seed)``; ``probe(task)`` reads the simulator
    (the ManiSkill task) before every decision. Returns the probes and whether the task succeeded.
    ``executed``: a list that receives each decision's executed actions, ``[k, A]`` (the chunk's first k)."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

    from mmada_rl.keys import ACTION_CHUNK_KEY

    task = maniskill_env(penv.env)
    td = penv.env.reset(seed=seed)
    probes, success = [], False
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(max_decisions):
            probes.append(probe(task))
            td = penv.policy(td)
            if executed is not None:
                chunk = td.get(ACTION_CHUNK_KEY)
                executed.append(chunk.reshape(-1, *chunk.shape[-2:])[0, : penv.actor.execute_steps].clone())
            td = penv.env.step(td)
            success = success or bool(td.get(("next", "success")).any())
            if td.get(("next", "done")).any():
                break
            td = step_mdp(td)
    return probes, success


def load_policy(checkpoint, action_readout: str | None = None):
    """The actor of ``checkpoint`` (MMaDA-VLA or baseline) in eval mode; ``action_readout``: as
    ``mmada-rl eval --action-readout`` (MMaDA-VLA only; None keeps the policy's own)."""
    from mmada_rl.evaluation import load_actor
    from mmada_rl.policy import MMaDAActor

    actor = load_actor(checkpoint)
    actor.eval()
    if action_readout is not None:
        if not isinstance(actor, MMaDAActor):
            raise SystemExit(f"--action-readout needs an MMaDA-VLA policy; {checkpoint} holds a {type(actor).__name__}.")
        actor.model.set_action_readout(action_readout)
    return actor


def eval_policy_env(checkpoint, task: str, max_episode_steps: int | None = None, action_readout: str | None = None):
    """The policy of ``checkpoint`` (MMaDA-VLA or baseline) in its evaluation env on ``task``:
    ``(penv, max_decisions)``, as ``mmada-rl eval`` runs it (``action_readout``: as its ``--action-readout``)."""
    from mmada_rl.evaluation import eval_env_config
    from mmada_rl.policy import make_policy_env

    actor = load_policy(checkpoint, action_readout)
    cfg = eval_env_config(actor, task, max_episode_steps=max_episode_steps)
    penv = make_policy_env(cfg, actor)
    return penv, -(-cfg.episode_steps // penv.actor.execute_steps) + 1


def probe_parser(description: str, name: str, task: str):
    """The options every per-episode probe of a policy takes (``--checkpoint``, ``--episodes``, ...)."""
    import argparse

    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help=f"{task} policy: a pretraining or imitation run, "
                        "checkpoint or saved model directory")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--max-episode-steps", type=int, default=None, help="default: the task's own length")
    parser.add_argument("--threads", type=int, default=1)
    from mmada_rl.policy import ACTION_READOUTS

    parser.add_argument("--action-readout", choices=ACTION_READOUTS, default=None,
                        help="MMaDA-VLA only, as mmada-rl eval's option (default: the policy's own)")
    parser.add_argument("--demo-seeds", default=None, metavar="BUFFER",
                        help="run this buffer's demonstrations' seeds (their initial states) instead of the evaluation "
                        "seeds, as mmada-rl eval's option")
    parser.add_argument("--name", default=name)
    parser.add_argument("--out", type=Path, default=RESULTS)
    return parser


def run_probe(args, task: str, rollout, show=lambda episode: episode) -> tuple[list[dict], object]:
    """``rollout(penv, seed, max_decisions) -> dict`` on each evaluation seed (or each of ``--demo-seeds``);
    returns the episodes and the policy env (its env closed). ``show`` picks what is printed per episode."""
    import torch

    from mmada_rl.evaluation import episode_seeds

    if args.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    try:
        seeds = episode_seeds(args.episodes, demo_seeds=args.demo_seeds, task=task)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(str(err)) from None
    torch.set_num_threads(args.threads)
    penv, max_decisions = eval_policy_env(args.checkpoint, task, args.max_episode_steps, args.action_readout)
    episodes = []
    for seed in seeds:
        episodes.append(rollout(penv, seed, max_decisions))
        print(show(episodes[-1]), flush=True)
    penv.env.close()
    return episodes, penv
