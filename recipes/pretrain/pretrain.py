"""Masked-diffusion pretraining of the MMaDA-VLA policy on demonstrations.

    python recipes/pretrain/pretrain.py                          # toy: real PickCube-v1, about a minute
    python recipes/pretrain/pretrain.py --config-name maniskill  # 100 demos, small model
    python recipes/pretrain/pretrain.py checkpoint.resume=true   # continue the run in run_dir
    python recipes/pretrain/pretrain.py checkpoint.resume=RUN/checkpoints/step_N checkpoint.restore_rng=false \
        seed=1 run_dir=FORK                                      # a fork of RUN from step N, with its own draws
    python recipes/pretrain/pretrain.py --config-name multitask  # one model on PickCube, PushCube, StackCube

Reads a demonstration buffer (collecting it first if missing) — or one per
task when ``tasks`` lists several, the instruction then selecting the task —
fits the tokenizers (or loads ``tokenizers.dir``), trains the denoiser on chunk windows
with the masked-diffusion loss, evaluates in ManiSkill every ``eval.interval``
steps and at the end, scores held-out demonstrations (``validation.dir``) every
``validation.interval`` steps and at the end, and checkpoints atomically every ``checkpoint.interval`` steps.
With ``ema.enabled=true`` a moving average of the denoiser's weights is what is
evaluated and saved (``ema.evaluate_raw=true`` also evaluates the optimizer's own
weights, as ``eval_raw/...``: the two compared within one run). The evaluation at the end
is also written episode by episode to ``run_dir/final_eval/eval.json`` (``final_eval_raw/`` for the own
weights; a multi-task model's under ``final_eval/<task>/``), in ``mmada-rl eval``'s format: what
``benchmarks/paired.py`` pairs on.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig
from tqdm.auto import tqdm

from mmada_rl.data import window_generators
from mmada_rl.training import (
    autocast,
    ema_applied,
    ema_checkpointed,
    latest_checkpoint,
    make_weight_ema,
    optimizer_step,
    resume_own_weights,
    resume_training,
    save_checkpoint,
    start_run,
)
from mmada_rl.training.validation import validation_metrics
from utils import (
    make_data,
    make_demo_buffers,
    make_logger,
    make_loss,
    make_model,
    make_optim,
    make_tokenizers,
    make_validation,
    task_list,
)


def evaluate(cfg: DictConfig, model, record: Path | None = None, checkpoint: Path | None = None,
             own_weights: bool = False) -> dict:
    """Success of ``model`` on each training task; a multi-task model also reports per-task metrics
    (``eval/<task>/...``) and their mean under the plain ``eval/...`` names. With ``record``, each task's
    evaluation is also written there (``eval.json`` with every episode, ``eval.md``; a multi-task model's under
    ``record/<task>/``), naming ``checkpoint`` as the policy evaluated and ``own_weights`` as in ``mmada-rl eval``."""
    from mmada_rl.evaluation import evaluate as run_eval

    tasks = task_list(cfg)
    per_task = {}
    for task in tasks:
        result = run_eval(model, task, episodes=int(cfg.eval.episodes), image_size=int(cfg.env.image_size),
                          control_mode=cfg.env.control_mode, max_episode_steps=cfg.eval.max_episode_steps,
                          execute_steps=int(cfg.eval.execute_steps), progress=False)
        if record is not None:
            result.checkpoint, result.own_weights = str(checkpoint) if checkpoint else None, own_weights
            result.save(record if len(tasks) == 1 else record / task)
        per_task[task] = result.to_dict()
    if len(per_task) == 1:
        return next(iter(per_task.values()))
    out = {f"eval/{task}/{key[len('eval/'):]}": value for task, metrics in per_task.items() for key, value in metrics.items()}
    for key in ("success_once", "success_at_end", "episode_length"):
        out[f"eval/{key}"] = sum(m[f"eval/{key}"] for m in per_task.values()) / len(per_task)
    return out


def evaluate_saved(cfg: DictConfig, model, ema, run_dir: Path | None = None) -> dict:
    """``eval/...`` of the weights the run saves (the moving average with ``ema.enabled``), and with
    ``ema.evaluate_raw`` ``eval_raw/...`` of the optimizer's own weights. With ``run_dir`` (the end of the run),
    the evaluations are also written, episode by episode, to ``run_dir/final_eval/`` and ``run_dir/final_eval_raw/``
    (:func:`evaluate`), naming the run's newest checkpoint as the policy evaluated."""
    def record(name: str) -> Path | None:
        return None if run_dir is None else run_dir / name

    checkpoint = None if run_dir is None else latest_checkpoint(run_dir)
    with ema_applied(ema):
        out = evaluate(cfg, model, record("final_eval"), checkpoint)
    if ema is not None and cfg.ema.evaluate_raw:
        raw = evaluate(cfg, model, record("final_eval_raw"), checkpoint, own_weights=True)
        out.update({f"eval_raw/{key[len('eval/'):]}": value for key, value in raw.items()})
    return out


def validate(model, ema, batches: list) -> dict:
    """``val/...`` scores of the weights the run saves (the moving average with ``ema.enabled``) on the
    held-out windows."""
    with ema_applied(ema):
        return validation_metrics(model, batches)


@hydra.main(config_path="config", config_name="toy", version_base=None)
def main(cfg: DictConfig) -> None:
    run_dir, config = start_run(cfg)
    autocast(cfg.optim.precision, cfg.device)  # a bad optim.precision fails here, before the data and tokenizers

    buffers = make_demo_buffers(cfg)
    tokenizers = make_tokenizers(cfg, buffers, run_dir)
    model = make_model(cfg, tokenizers)
    data = make_data(cfg, buffers)
    loss_module = make_loss(cfg, model)
    optimizer, scheduler = make_optim(cfg, model)
    logger = make_logger(cfg, run_dir)
    generators = window_generators(data)
    held_out = make_validation(cfg, model)  # drawn before training: the same windows at every report

    start, history = 0, []
    def load_weights(model_dir: Path) -> None:
        model.denoiser.load_state_dict(type(model).load(model_dir).denoiser.state_dict())

    ckpt = resume_training(cfg.checkpoint.resume, run_dir, load_weights=load_weights, optimizer=optimizer,
                           scheduler=scheduler, generators=generators, restore_rng=bool(cfg.checkpoint.restore_rng))
    ema = make_weight_ema(model.denoiser, cfg.ema)  # after resume: a saved average is the loaded model
    if ckpt is not None:
        start = ckpt.step
        extra = ckpt.trainer_state.get("extra", {})
        resume_own_weights(model.denoiser, ema, extra)
        history = list(extra.get("history", []))  # the rows logged up to the checkpoint
        forked = "" if cfg.checkpoint.restore_rng else f" with this run's seed {cfg.seed} (a fork)"
        print(f"[pretrain] resumed from {ckpt.path} at step {start}{forked}")
    params = sum(p.numel() for p in model.denoiser.parameters())
    demos = ", ".join(f"{b.metadata.task}: {b.metadata.num_episodes} demos, {len(b)} transitions" for b in buffers)
    print(f"[pretrain] {demos}; denoiser "
          f"{params / 1e6:.2f}M parameters; sequence length {model.layout.length}; vocabulary {model.vocab.size}")

    total = int(cfg.optim.total_steps)
    model.train()
    pbar = tqdm(range(start, total), initial=start, total=total, desc="pretrain")
    for step in pbar:
        t0 = time.perf_counter()
        batch = data.sample()
        with autocast(cfg.optim.precision, cfg.device):  # optim.precision=bf16: the forward pass in bfloat16
            losses = loss_module(model.loss_inputs(batch))
        scalars = optimizer_step(losses, model.denoiser.parameters(), optimizer, grad_clip=cfg.optim.grad_clip,
                                 scheduler=scheduler, ema=ema)
        done = step + 1
        metrics = {f"train/{k}": v for k, v in scalars.items()}
        metrics["time/step_s"] = time.perf_counter() - t0
        if held_out and cfg.validation.interval and done % int(cfg.validation.interval) == 0 and done < total:
            metrics.update(validate(model, ema, held_out))
        if cfg.eval.interval and int(cfg.eval.episodes) > 0 and done % int(cfg.eval.interval) == 0 and done < total:
            metrics.update(evaluate_saved(cfg, model, ema))
            model.train()
        reported = any(key.startswith(("eval/", "val/")) for key in metrics)
        if done % int(cfg.logger.log_interval) == 0 or done == total or reported:
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=done)
            history.append({"step": done, **metrics})
        pbar.set_postfix(loss=f"{scalars['loss']:.3f}", acc=f"{scalars['action_accuracy']:.2f}")
        if done % int(cfg.checkpoint.interval) == 0 or done == total:
            with ema_checkpointed(ema) as extra:  # the average is the saved model; extra: the weights to resume
                save_checkpoint(run_dir, done, model=model, optimizer=optimizer, scheduler=scheduler, config=config,
                                generators=generators, extra={**extra, "history": history},
                                keep=int(cfg.checkpoint.keep))
    pbar.close()

    final = {"step": total}
    if total > start and held_out:
        final.update(validate(model, ema, held_out))
    if total > start and int(cfg.eval.episodes) > 0:
        final.update(evaluate_saved(cfg, model, ema, run_dir))
    for key, value in final.items():
        if key.startswith(("eval/", "eval_raw/", "val/")):
            logger.log_scalar(key, value, step=total)
    (run_dir / "history.json").write_text(json.dumps(history, indent=2))
    (run_dir / "final.json").write_text(json.dumps(final, indent=2))
    print("[pretrain] done:", json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in final.items()}))


if __name__ == "__main__":
    main()
