"""Imitation baselines on the demonstrations the MMaDA-VLA policy learns from: BC and Diffusion Policy.

    python recipes/baselines/imitation.py                                     # toy BC, real PickCube-v1, seconds
    python recipes/baselines/imitation.py algo=diffusion_policy               # toy Diffusion Policy
    python recipes/baselines/imitation.py --config-name maniskill algo=bc     # 100 demos, 6000 steps
    python recipes/baselines/imitation.py --config-name maniskill algo=bc checkpoint.resume=true

``algo`` picks the policy and its TorchRL loss: ``bc`` (chunk MLP, ``BCLoss`` with
the ``action_is_pad`` mask) or ``diffusion_policy`` (DDPM over the flattened chunk,
``DiffusionBCLoss``). Both read the same chunk windows (64x64 RGB + proprio state
at ``t``, actions ``t..t+K-1``) as the pretraining recipe, are evaluated by
``mmada_rl.evaluation.evaluate`` on the same fixed seeds every ``eval.interval``
steps and at the end (that one also written episode by episode to ``run_dir/final_eval/eval.json``, in
``mmada-rl eval``'s format), and checkpoint atomically every ``checkpoint.interval`` steps.
Diffusion Policy keeps a moving average of its weights (``ema``, as Chi et al.):
the average is what is evaluated and saved as the checkpoint's policy.
"""
from __future__ import annotations

import json
import time

import hydra
from omegaconf import DictConfig
from tqdm.auto import tqdm

from mmada_rl.training import ema_applied, latest_checkpoint, optimizer_step, resume_own_weights, start_run
from utils import (PREFIX, evaluate, make_data, make_demo_buffer, make_ema, make_logger, make_loss, make_optim, make_policy,
                   resume, save)


@hydra.main(config_path="config", config_name="toy", version_base=None)
def main(cfg: DictConfig) -> None:
    run_dir, config = start_run(cfg)

    buffer = make_demo_buffer(cfg)
    policy = make_policy(cfg, buffer)
    data = make_data(cfg, buffer)
    loss_module = make_loss(cfg, policy)
    optimizer, scheduler = make_optim(cfg, policy)
    logger = make_logger(cfg, run_dir)
    generators = {"sampler": data._rng}  # the window sampler's generator
    start, extra = resume(cfg, run_dir, policy, optimizer, scheduler, generators)
    ema = make_ema(cfg, policy)  # after resume: the average starts from the saved one
    resume_own_weights(policy, ema, extra)
    params = sum(p.numel() for p in policy.parameters())
    print(f"{PREFIX} {cfg.algo}: {buffer.metadata.num_episodes} demos, {len(buffer)} transitions; "
          f"{params / 1e6:.2f}M parameters; chunk {policy.chunk_size}x{policy.action_dim}"
          + ("; evaluates the moving average of its weights" if ema is not None else ""))

    history = list(extra.get("history", []))  # the rows logged up to the checkpoint resumed from
    total, eval_every = int(cfg.optim.total_steps), int(cfg.eval.interval or 0)
    policy.train()
    pbar = tqdm(range(start, total), initial=start, total=total, desc=cfg.algo)
    for step in pbar:
        t0 = time.perf_counter()
        scalars = optimizer_step(loss_module(data.sample().to(cfg.device)), policy.parameters(), optimizer,
                                 grad_clip=cfg.optim.grad_clip, scheduler=scheduler, ema=ema)
        done = step + 1
        metrics = {f"train/{k}": v for k, v in scalars.items()}
        metrics["time/step_s"] = time.perf_counter() - t0
        if eval_every and int(cfg.eval.episodes) > 0 and done % eval_every == 0 and done < total:
            with ema_applied(ema):
                metrics.update(evaluate(cfg, policy))
        if done % int(cfg.logger.log_interval) == 0 or done == total or "eval/success_once" in metrics:
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=done)
            history.append({"step": done, **metrics})
        pbar.set_postfix(loss=f"{metrics['train/loss']:.4f}")
        if done % int(cfg.checkpoint.interval) == 0 or done == total:
            save(cfg, run_dir, done, policy=policy, ema=ema, optimizer=optimizer, scheduler=scheduler, config=config,
                 generators=generators, history=history)
    pbar.close()

    final = {"step": total}
    if total > start and int(cfg.eval.episodes) > 0:
        with ema_applied(ema):
            final.update(evaluate(cfg, policy, record=run_dir / "final_eval", checkpoint=latest_checkpoint(run_dir)))
        for key, value in final.items():
            if key.startswith("eval/"):
                logger.log_scalar(key, value, step=total)
    (run_dir / "history.json").write_text(json.dumps(history, indent=2))
    (run_dir / "final.json").write_text(json.dumps(final, indent=2))
    print(f"{PREFIX} done:", json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in final.items()}))


if __name__ == "__main__":
    main()
