"""Reinforcement-learning baselines on TorchRL's losses, on the tasks, demos, evaluation seeds and env-step budget of our method.

    python recipes/baselines/online.py algo=ppo                                   # toy runs on real PickCube-v1, < 1 min each
    python recipes/baselines/online.py algo=sac
    python recipes/baselines/online.py algo=iql
    python recipes/baselines/online.py --config-name online_maniskill algo=ppo                  # 64x64 RGB + proprio, from scratch
    python recipes/baselines/online.py --config-name online_maniskill algo=ppo env.obs_mode=state
    python recipes/baselines/online.py --config-name online_maniskill algo=sac                  # RLPD, privileged state (reference)
    python recipes/baselines/online.py --config-name online_maniskill algo=iql                  # offline -> online, privileged state
    python recipes/baselines/online.py --config-name online_maniskill algo=sac checkpoint.resume=true   # continue an interrupted run

``algo`` picks the TorchRL loss and its update rule:

* ``ppo`` — ``ClipPPOLoss`` + ``GAE`` from scratch (no demos), on-policy epochs over each collected batch;
* ``sac`` — ``SACLoss`` RLPD-style: demos in the replay (``replay_buffer.demo_fraction=0.5`` of every
  batch), ``loss.sac.utd_ratio`` updates per env step, a LayerNorm Q ensemble;
* ``iql`` — ``IQLLoss``: ``loss.iql.offline_updates`` updates on the demos (evaluated at env step 0), then
  online fine-tuning on the demos plus online transitions.

``env.obs_mode=null`` gives PPO the 64x64 RGB + proprio our policy reads and SAC/IQL ManiSkill's privileged
state vector (references, labelled ``"observation": "privileged_state"`` in ``final.json``). Demonstrations:
``data.root/{task}`` (RGB) or ``data.root/state/{task}`` (state; planner demos are collected when missing).

Writes into ``run_dir``: ``checkpoints/step_{updates}/`` (atomic; weights, optimizer, RNG, the online replay
buffer, config), CSV logs under ``logs/``, ``eval_history.json`` (one record per evaluation: ``env_steps``
(online simulator steps only), ``updates``, ``success_once`` and its 95% Wilson interval, ``success_at_end``,
``episodes``, ``wall_s``) and ``final.json`` (the last record and the config).
"""
from __future__ import annotations

import json
import time

import hydra
from omegaconf import DictConfig
from tqdm.auto import tqdm

from mmada_rl.baselines.rl import RLAgent
from mmada_rl.envs.maniskill import make_env
from mmada_rl.training import start_run
from online_utils import (PREFIX, EvalHistory, Progress, check_config, evaluate, make_collector, make_demo_replay, make_demos,
                          make_env_config, make_logger, make_loss, make_networks, make_online_replay, make_optim, make_updater,
                          obs_mode, resume, save)


@hydra.main(config_path="config", config_name="online_toy", version_base=None)
def main(cfg: DictConfig) -> None:
    check_config(cfg)
    run_dir, config = start_run(cfg)

    env_cfg = make_env_config(cfg)
    demos = make_demos(cfg, env_cfg)
    env = make_env(env_cfg)
    action_spec = env.action_spec
    nets = make_networks(cfg, env, demos)
    loss = make_loss(cfg, nets, action_spec)
    optimizer = make_optim(cfg, loss)
    online, demo_replay = make_online_replay(cfg), make_demo_replay(demos, obs_mode(cfg), action_spec)
    updater = make_updater(cfg, loss, optimizer, online, demo_replay)
    agent = RLAgent(cfg.algo, nets.config, loss.module, nets.actor)
    logger = make_logger(cfg, run_dir)
    progress = resume(cfg, run_dir, agent, optimizer, online)
    history = EvalHistory(run_dir / "eval_history.json", progress)
    label = "privileged_state" if nets.config.obs_mode == "state" else "rgb+proprio"
    params = sum(p.numel() for p in nets.actor.parameters())
    print(f"{PREFIX} {cfg.algo} on {cfg.env.task} ({label}): actor {params / 1e6:.3f}M parameters; "
          f"{f'{len(demo_replay)} demo transitions' if demo_replay is not None else 'no demos'}")
    start, wall0 = time.perf_counter(), progress.wall_s

    def now(p: Progress) -> Progress:
        return p._replace(wall_s=wall0 + time.perf_counter() - start)

    # offline phase (IQL): updates on the demos alone, evaluated at env step 0
    offline = int(cfg.loss[cfg.algo].get("offline_updates", 0)) if progress.env_steps == 0 else 0
    for _ in tqdm(range(progress.updates, offline), initial=progress.updates, total=offline, desc=f"{cfg.algo} offline",
                  disable=not offline):
        metrics = updater.update(1)
        progress = now(progress._replace(updates=progress.updates + 1))
        if progress.updates % int(cfg.logger.log_interval) == 0:
            for key, value in metrics.items():
                logger.log_scalar(key.replace("train/", "offline/"), value, step=progress.updates)
        if progress.updates % int(cfg.checkpoint.offline_interval) == 0 or progress.updates == offline:
            save(cfg, run_dir, agent, optimizer, online, progress, config)
    if offline and int(cfg.eval.episodes) and not any(r["env_steps"] == 0 for r in history.records):
        history.append(evaluate(cfg, nets.actor, now(progress)))
        print(f"{PREFIX} offline: {json.dumps({k: v for k, v in history.records[-1].items() if k != 'per_episode'})}")

    # online phase: collect, update, evaluate every eval.interval env steps, checkpoint every checkpoint.interval
    total, eval_every, ckpt_every = int(cfg.collector.total_env_steps), int(cfg.eval.interval or 0), int(cfg.checkpoint.interval)
    if progress.episodes:  # resumed: continue the training episode seeds where the checkpoint stopped
        env.close()
        env = make_env(make_env_config(cfg, progress.episodes))
    collector = make_collector(cfg, env, nets.actor, progress.env_steps)
    pbar = tqdm(total=total, initial=progress.env_steps, desc=cfg.algo, unit="step")
    t_last = time.perf_counter()
    for batch in collector or ():  # None: the budget was already spent (resuming a finished run)
        t0, before = time.perf_counter(), progress.env_steps
        progress = progress._replace(env_steps=before + batch.numel(),
                                     episodes=progress.episodes + int(batch["next", "done"].sum()))
        num_updates, metrics = updater(batch, progress.env_steps)
        collector.update_policy_weights_()
        progress = now(progress._replace(updates=progress.updates + num_updates))
        done = batch["next", "done"].squeeze(-1)
        metrics |= {"train/reward": float(batch["next", "reward"].mean()), "train/updates": progress.updates,
                    "time/collect_s": t0 - t_last, "time/update_s": time.perf_counter() - t0, "time/wall_s": progress.wall_s}
        if done.any():  # episodes that ended in this batch; success terminates them (success_once)
            metrics["train/success_rate"] = float(batch["next", "success"].squeeze(-1)[done].float().mean())
            metrics["train/episodes"] = int(done.sum())
        if eval_every and int(cfg.eval.episodes) and progress.env_steps // eval_every > before // eval_every and progress.env_steps < total:
            history.append(evaluate(cfg, nets.actor, progress))
            metrics |= {f"eval/{k}": v for k, v in history.records[-1].items() if k.startswith("success")}
        for key, value in metrics.items():
            logger.log_scalar(key, value, step=progress.env_steps)
        pbar.update(batch.numel())
        pbar.set_postfix(updates=progress.updates, **({"success": f"{history.records[-1]['success_once']:.2f}"} if history.records else {}))
        if progress.env_steps // ckpt_every > before // ckpt_every or progress.env_steps == total:
            save(cfg, run_dir, agent, optimizer, online, progress, config)
        t_last = time.perf_counter()
    pbar.close()
    if collector is not None:
        collector.shutdown()

    if int(cfg.eval.episodes) and not (history.records and history.records[-1]["env_steps"] == total):
        history.append(evaluate(cfg, nets.actor, now(progress)))
        logger.log_scalar("eval/success_once", history.records[-1]["success_once"], step=total)
    last = history.records[-1] if history.records else {"env_steps": progress.env_steps, "updates": progress.updates}
    final = {**last, "algo": cfg.algo, "task": cfg.env.task, "observation": label, "config": config}
    tmp = run_dir / "final.json.tmp"
    tmp.write_text(json.dumps(final, indent=2))
    tmp.replace(run_dir / "final.json")
    print(f"{PREFIX} done: {json.dumps(last)}")


if __name__ == "__main__":
    main()
