"""Online fine-tuning of a pretrained MMaDA-VLA policy in ManiSkill: reward-weighted diffusion or path PPO.

    python recipes/finetune/finetune.py pretrained=runs/pretrain_toy                       # toy: seconds
    python recipes/finetune/finetune.py --config-name maniskill pretrained=runs/pretrain_PickCube-v1_s0
    python recipes/finetune/finetune.py --config-name maniskill algo=ppo pretrained=...    # path-likelihood PPO
    python recipes/finetune/finetune.py ... advantage.estimator=group advantage.group_size=4  # critic-free
    python recipes/finetune/finetune.py ... env.reward=sparse advantage.estimator=return loss.rwr.weighting=binary
    python recipes/finetune/finetune.py ... env.reward=sparse advantage.estimator=return loss.rwr.weighting=binary \
        collector.action_noise=0.1 loss.rwr.weight_goal=true   # the greedy policy's noisy successes imitated
    python recipes/finetune/finetune.py ... advantage.estimator=return_to_go loss.rwr.weighting=signed \
        loss.rwr.standardize_advantage=true collector.action_noise=0.05   # per-chunk returns, no critic
    python recipes/finetune/finetune.py ... optim.lr=1e-4 optim.lr_decay=cosine    # lr to 0.1 x 1e-4 over the budget
    python recipes/finetune/finetune.py ... checkpoint.resume=true                          # continue the run

Each iteration, TorchRL's ``Collector`` runs the actor with sampled
decoding for ``collector.decisions_per_batch`` decisions (one decision = one
chunk of ``k`` executed env steps, rewarded with its discounted reward sum).
Advantages per decision come from a learned value function with TorchRL's GAE
(discount ``gamma ** k``) or, critic-free, from returns standardised within groups
of rollouts that share an initial state (``group``) or from the episode's return
itself (``return``; with ``env.reward=sparse`` and ``loss.rwr.weighting=binary``
the online rows are the successful rollouts: filtered self-imitation) or each
decision's own discounted return to the episode's end (``return_to_go``, discount
``gamma ** k`` per decision, nothing bootstrapped; with ``advantage.baseline_episodes=N``
relative to the last ``N`` episodes' returns to go at the same decision index). Episodes end
at the first success; with ``advantage.absorbing_success=true`` (the default) the
chunk that succeeds also earns the discounted value of staying in success at the
best per-step reward, ``gamma**j / (1 - gamma)``, so that finishing is worth more than
lingering near the goal on the dense reward. Then:

* ``algo=rwr``: the decisions join an online buffer; each update mixes
  ``demos.ratio`` demonstration windows with online rows and applies
  :class:`~mmada_rl.objectives.RewardWeightedDiffusionLoss` (advantage-weighted
  action tokens, plain goal-image denoising, optional KL to the pretrained policy);
* ``algo=ppo``: :class:`~mmada_rl.objectives.PathPPOLoss` on the fresh batch,
  the ratio recomputed exactly from each chunk's stored decoding path; with
  ``loss.ppo.demo_coef > 0`` every minibatch adds that times the masked-diffusion
  loss on ``demos.ratio x replay_buffer.batch_size`` demonstration windows.

With ``collector.action_noise=σ > 0`` (``algo=rwr``) the collector decodes greedily (the policy's own
read-out, e.g. the mean of the action bins) and executes each chunk with ``N(0, σ²)`` noise on the arm's
actions (:class:`~mmada_rl.policy.ExecutionNoise`); the online rows hold the executed actions' tokens, so
with binary weights of episode success the successful noisy rollouts are imitated as demonstrations are.

With ``collector.ensemble_with=[RUN, ...]`` (and ``collector.action_noise > 0``) the fine-tuned policy acts
together with those frozen pretrained policies: each chunk executed is the mean of their greedy chunks
(:class:`~mmada_rl.policy.MMaDAEnsemble`, the fine-tuned policy first) plus the noise, and the online rows teach
the fine-tuned policy that executed chunk, weighted by its advantage. The ensemble explores around a better
policy than any one member; evaluation is of the fine-tuned policy alone.

With ``value.pretrain_steps > 0`` (GAE) the value network is first regressed on the demonstrations'
discounted returns, so that the first advantages come from a critic that has seen the task. With
``value.warmup_env_steps=N > 0`` (GAE; DPPO's critic warm-up) the critic alone learns on the rollouts of the
first ``N`` online env steps: the policy is not updated, and those rollouts, whose advantages came from the
cold critic, never enter the online buffer (which otherwise keeps them, with their advantages, for the run).

With ``collector.overlap=true`` (``algo=rwr``) the next batch is collected in a background thread while this
iteration's updates run (:class:`~mmada_rl.training.CollectAhead`): a frozen copy of the policy acts, its weights
copied from the model just before each collection starts, so each batch comes from the weights of one iteration
earlier than the sequential loop's. Evaluations and checkpoints wait for the collection in flight;
``time/collect_s`` is then the wait for the batch, ``time/collect_ahead_s`` the collection itself. With
``collector.overlap=process`` the collector, its env and the frozen copy live in a process of their own
(:class:`~mmada_rl.training.CollectAheadProcess`), which is sent the weights and the states of the exploration
RNGs (the execution noise's and the sampled tokens') with each request, so the learner and the actor no longer
contend inside one process; only checkpoints wait.

Evaluation (greedy, or sampled with ``eval.sample_temperature``; fixed seeds disjoint from training) runs every
``eval.interval_env_steps`` env steps; ``eval_history.json`` records success
against env steps. With ``ema.enabled=true`` a moving average of the denoiser's weights
(:class:`~mmada_rl.training.WeightEMA`, updated after every gradient step from the pretrained weights on) is what
is evaluated and saved as the checkpoints' model, while the policy's own weights act in the collector and keep
training; keeping the average changes nothing else (evaluation forks the RNG), so the same run without it
evaluates the own weights. Checkpoints (policy, value network, optimizers, counters,
RNGs, how many initial states the training envs have begun) are atomic; the online buffer is saved beside
them. A resumed run's training envs start the initial states after those begun, not the run's first ones
again. If the env raises while collecting, the run saves what it has and stops with a clear message.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from mmada_rl.evaluation import evaluate
from mmada_rl.training import (
    CollectAhead,
    CollectAheadProcess,
    autocast,
    ema_applied,
    ema_checkpointed,
    make_weight_ema,
    optimizer_step,
    resume_own_weights,
    resume_training,
    save_checkpoint,
    start_run,
)
from utils import (
    PREFIX,
    ActingCollector,
    absorb_success,
    action_noise,
    acting_policy,
    check_config,
    collects_ahead,
    critic_warmup_steps,
    decision_rows,
    ensemble_partners,
    executed_steps,
    exploration_sampler,
    initial_states_begun,
    learning_rate,
    load_pretrained,
    make_collector,
    make_demo_anchor,
    make_demo_windows,
    make_episode_groups,
    make_gae,
    make_logger,
    make_loss,
    make_noise_generator,
    make_online_buffer,
    make_optim,
    make_policy_env_for,
    make_sampling_generator,
    make_value,
    mixed_batch,
    open_demo_buffer,
    pretrain_value,
    split_batch,
    with_initial_states_begun,
)
from mmada_rl.envs.maniskill import TORCH_RNG_LOCK
from mmada_rl.keys import SUCCESS_KEY, VALUE_TARGET_KEY
from mmada_rl.policy.value import value_step

BUFFER_DIR = "online_buffer"


def run_eval(cfg: DictConfig, model, env_steps: int, updates: int, start: float) -> dict:
    """Evaluation with the model's own sampler (not the exploration one): greedy, or sampled at
    ``eval.sample_temperature``. The record keeps each episode's env seed and success
    (:meth:`~mmada_rl.evaluation.EvalResult.history_record`), which ``benchmarks/paired.py`` pairs on."""
    temperature = None if cfg.eval.sample_temperature is None else float(cfg.eval.sample_temperature)
    result = evaluate(model, cfg.env.task, episodes=int(cfg.eval.episodes), execute_steps=cfg.collector.execute_steps,
                      control_mode=cfg.env.control_mode, max_episode_steps=cfg.eval.max_episode_steps,
                      sample_temperature=temperature, progress=False)
    return {"env_steps": env_steps, "updates": updates, "sample_temperature": result.sample_temperature,
            **result.history_record(), "wall_s": time.perf_counter() - start}


def update_value(cfg, value_op, value_optim, rows) -> float:
    """A few epochs of regression of ``V(o_t)`` on the GAE value targets of the fresh batch."""
    losses, n = [], rows.shape[0]
    size = max(1, min(int(cfg.value.batch_size), n))
    for _ in range(int(cfg.value.epochs)):
        for idx in torch.randperm(n).split(size):
            batch = rows[idx]
            losses.append(value_step(value_op, value_optim, batch, batch.get(VALUE_TARGET_KEY)))
    return sum(losses) / max(1, len(losses))


def gradient_step(cfg, model, optimizer, losses, ema) -> dict[str, float]:
    return optimizer_step(losses, model.denoiser.parameters(), optimizer, grad_clip=cfg.optim.grad_clip, ema=ema)


@hydra.main(config_path="config", config_name="toy", version_base=None)
def main(cfg: DictConfig) -> None:
    check_config(cfg)
    run_dir, config = start_run(cfg)

    model = load_pretrained(cfg)
    eval_sampler, explore_sampler = model.sampler, exploration_sampler(cfg, model)
    demos = open_demo_buffer(cfg, model)
    value_op, value_optim = make_value(cfg, model, demos)
    gae = make_gae(cfg, value_op, model) if cfg.advantage.estimator == "gae" else None
    groups = make_episode_groups(cfg, model)
    loss_module = make_loss(cfg, model)
    demo_anchor = make_demo_anchor(cfg, model)
    optimizer = make_optim(cfg, model)
    online = make_online_buffer(cfg)
    demo_windows = make_demo_windows(cfg, demos, model)
    n_online, n_demo = split_batch(cfg)
    logger = make_logger(cfg, run_dir)
    generators = {"demos": demo_windows._rng} if demo_windows is not None else {}
    noise_generator = make_noise_generator(cfg)  # collector.action_noise > 0: the exploration noise's RNG
    if noise_generator is not None:
        generators["noise"] = noise_generator
    overlap = collects_ahead(cfg)
    if overlap == "process":  # the tokens the collector's process samples: their RNG is checkpointed here
        generators["sampling"] = make_sampling_generator(cfg)

    iteration, env_steps, updates, history = 0, 0, 0, []
    begun = 0  # initial states each training worker has begun: a resumed run's envs start after them

    def load_weights(model_dir: Path) -> None:
        model.denoiser.load_state_dict(type(model).load(model_dir).denoiser.state_dict())

    ckpt = resume_training(cfg.checkpoint.resume, run_dir, load_weights=load_weights, optimizer=optimizer, generators=generators)
    ema = make_weight_ema(model.denoiser, cfg.ema)  # after resume: a saved average is the loaded model
    if ckpt is not None:
        extra = ckpt.trainer_state["extra"]
        resume_own_weights(model.denoiser, ema, extra)
        iteration, env_steps, updates, history = ckpt.step, extra["env_steps"], extra["updates"], extra["eval_history"]
        saved_begun = extra.get("initial_states_begun")  # None in checkpoints from before it was saved
        begun = int(saved_begun or 0)
        value_op.load_state_dict(extra["value"])
        value_optim.load_state_dict(extra["value_optimizer"])
        if "advantage_baseline" in extra:
            if groups is not None and groups.baseline is not None:
                groups.baseline.load_state_dict(extra["advantage_baseline"])
            else:
                print(f"{PREFIX} the checkpoint's decision-index baseline "
                      f"({len(extra['advantage_baseline']['window'])} episodes) is not used: "
                      f"advantage.baseline_episodes=0")
        if (run_dir / BUFFER_DIR).exists():
            online.loads(run_dir / BUFFER_DIR)
        print(f"{PREFIX} resumed from {ckpt.path}: iteration {iteration}, {env_steps} env steps, {len(online)} online rows; "
              + (f"training episodes continue from initial state {begun} of each env worker"
                 if saved_begun is not None else
                 "the checkpoint does not say how many initial states the training envs began: they start again "
                 "from env.train_seed"))
    elif gae is not None:  # a fresh run: the critic first learns the demonstrations' returns (value.pretrain_steps > 0)
        value_loss = pretrain_value(cfg, value_op, value_optim, demos)
        if value_loss is not None:
            logger.log_scalar("value/pretrain_loss", value_loss, step=0)
            print(f"{PREFIX} value network fitted to the demonstrations' returns: "
                  f"{cfg.value.pretrain_steps} steps, loss {value_loss:.3f} over the last tenth")

    ahead: CollectAhead | CollectAheadProcess | None = None  # collector.overlap: the next batch is collected while the updates run

    def checkpoint() -> Path:
        if ahead is not None:  # the collection in flight draws from the noise RNG being saved: let it finish
            ahead.wait()
        if len(online):
            online.dumps(run_dir / BUFFER_DIR)
        extra = {"env_steps": env_steps, "updates": updates, "eval_history": history, "initial_states_begun": begun,
                 "value": value_op.state_dict(), "value_optimizer": value_optim.state_dict()}
        if groups is not None and groups.baseline is not None:
            extra["advantage_baseline"] = groups.baseline.state_dict()
        with ema_checkpointed(ema) as own:  # the average is the saved model; own: the weights training resumes from
            return save_checkpoint(run_dir, iteration, model=model, optimizer=optimizer, config=config,
                                   generators=generators, extra={**extra, **own}, keep=int(cfg.checkpoint.keep))

    start = time.perf_counter()
    total = int(cfg.collector.total_env_steps)
    eval_every = int(cfg.eval.interval_env_steps or 0)
    if not history and int(cfg.eval.episodes) > 0:
        with ema_applied(ema):  # no update yet: the average is the pretrained weights
            history.append(run_eval(cfg, model, 0, 0, start))
        print(f"{PREFIX} pretrained policy: success_once {history[-1]['success_once']:.2f} over {history[-1]['episodes']} episodes")
    updates_desc = (f"batch {n_online} online + {n_demo} demo rows" if cfg.algo == "rwr" else
                    f"{cfg.loss.ppo.epochs} epochs over each iteration's decisions in minibatches of {cfg.replay_buffer.batch_size}"
                    + (f", each with {n_demo} demo windows (demo_coef {cfg.loss.ppo.demo_coef})" if demo_anchor is not None else ""))
    warmup = critic_warmup_steps(cfg)
    noise = action_noise(cfg)
    partners = ensemble_partners(cfg)
    acting = f"the greedy mean chunk of this policy and {len(partners)} frozen others" if partners else "greedy chunks"
    exploring = (f"{acting} + N(0, {noise:g}^2) on the arm's actions" if noise > 0 else
                 f"tokens sampled at temperature {cfg.collector.temperature}")
    print(f"{PREFIX} algo={cfg.algo} advantage={cfg.advantage.estimator} {updates_desc}; exploration: {exploring}; "
          f"{cfg.collector.decisions_per_batch} decisions per iteration, budget {total} env steps"
          + (f"; the critic alone learns for the first {warmup} env steps" if warmup else ""))

    collector = None
    train_cfg = with_initial_states_begun(cfg, begun)  # a resumed run's training envs: new initial states
    if overlap == "process":  # the collector, its env and a frozen copy live in a process of their own
        ahead = CollectAheadProcess(ActingCollector(train_cfg), weights=model.state_dict,
                                    generators={k: generators[k] for k in ("noise", "sampling") if k in generators},
                                    num_threads=torch.get_num_threads())
    else:
        # with overlap a frozen copy acts in the collector's thread, its weights refreshed before each collection
        acting = acting_policy(cfg, model) if overlap else model
        collector = make_collector(cfg, make_policy_env_for(train_cfg, acting, noise_generator))
        batches = iter(collector)
        if overlap:
            ahead = CollectAhead(batches, sync=lambda: acting.load_state_dict(model.state_dict()))
    if overlap:
        print(f"{PREFIX} collector.overlap={overlap}: each batch is collected in a "
              f"{'background thread' if overlap == 'thread' else 'process of its own'} while the previous "
              "batch's updates run, by the weights from before those updates")
    pbar = tqdm(total=total, initial=min(env_steps, total), desc=f"finetune {cfg.algo}", unit="step")
    try:
        while env_steps < total:
            t0 = time.perf_counter()
            model.eval()  # sampling and the recorded paths without dropout
            if ahead is None:
                model.sampler = explore_sampler
            try:
                batch, collected_s = ahead.take() if ahead is not None else (next(batches), None)
            except Exception as err:  # an env (or worker) failed: keep what was learned and collected
                model.sampler = eval_sampler
                path = checkpoint()
                sys.exit(f"{PREFIX} collection failed after {env_steps} env steps: {type(err).__name__}: {err}\n"
                         f"{PREFIX} saved checkpoint {path} and the online buffer ({len(online)} rows) in {run_dir / BUFFER_DIR}; "
                         "fix the cause and rerun with checkpoint.resume=true.")
            model.sampler = eval_sampler  # evaluation and checkpoints keep the model's own sampler
            steps = int(executed_steps(batch).sum())
            env_steps += steps
            begun = initial_states_begun(batch, cfg, begun)
            if ahead is not None and env_steps < total:  # the next batch, by the weights before this one's updates
                ahead.start()
            warming = env_steps <= warmup  # value.warmup_env_steps: the critic learns, the policy waits
            pbar.update(steps)
            collect_s = time.perf_counter() - t0  # with collector.overlap: the wait for the batch collected ahead
            metrics = {"train/chunk_reward": float(batch.get(("next", "reward")).mean()), "time/collect_s": collect_s}
            if collected_s is not None:
                metrics["time/collect_ahead_s"] = collected_s  # the collection's own duration in its thread or process
            ended = batch.get(("next", "done")).reshape(-1)
            if ended.any():  # episodes that ended in this batch; success terminates them (success_once)
                metrics["train/success_rate"] = float(batch.get(("next", SUCCESS_KEY)).reshape(-1)[ended].float().mean())
                metrics["train/episodes"] = int(ended.sum())

            # the collection thread's env resets seed torch's process-wide RNG and put it back: none runs in the
            # middle of the learner's draws (TORCH_RNG_LOCK), so that they are the same whatever the timing
            with TORCH_RNG_LOCK:
                absorb_success(cfg, batch)  # after the logged reward: the success's lasting value, for the advantages only
                if gae is not None:
                    with torch.no_grad():
                        gae(batch)
                    episodes = [batch]
                else:
                    episodes = groups.add(batch)
                parts = [decision_rows(model, ep) for ep in episodes if ep.numel()]
                rows = torch.cat(parts) if parts else None  # decisions whose advantages are known
                if rows is not None:
                    metrics["train/advantage_abs"] = float(rows.get("advantage").abs().mean())
                    if gae is not None:
                        metrics["train/value_loss"] = update_value(cfg, value_op, value_optim, rows)

            t1, stepped = time.perf_counter(), []  # each gradient step's losses and grad norm, averaged for the log
            lr = learning_rate(cfg, env_steps)  # optim.lr_decay=cosine: lower as the budget is spent
            for group in optimizer.param_groups:
                group["lr"] = lr
            metrics["train/lr"] = lr
            if warming:
                metrics["train/critic_warmup"] = 1.0
            elif cfg.algo == "rwr":
                if rows is not None:
                    online.extend(rows)
                model.train()
                for _ in range(int(cfg.optim.updates_per_batch) if len(online) or not n_online else 0):
                    with TORCH_RNG_LOCK, autocast(cfg.optim.precision):  # optim.precision=bf16: the forward in bfloat16
                        losses = loss_module(mixed_batch(model, online.sample() if n_online else None, demo_windows))
                        stepped.append(gradient_step(cfg, model, optimizer, losses, ema))
                    updates += 1
            elif rows is not None:  # PPO: a few epochs over the fresh decisions, then they are dropped
                size = max(1, min(int(cfg.replay_buffer.batch_size), rows.shape[0]))
                for _ in range(int(cfg.loss.ppo.epochs)):
                    with TORCH_RNG_LOCK:
                        order = torch.randperm(rows.shape[0])
                    for idx in order.split(size):
                        with TORCH_RNG_LOCK:
                            losses = loss_module(rows[idx])
                            if demo_anchor is not None:  # the demonstrations' denoising loss, scaled by loss.ppo.demo_coef
                                demo = demo_anchor(mixed_batch(model, None, demo_windows))
                                losses.update({"loss_demo_action": demo["loss_action"], "loss_demo_goal": demo["loss_goal"]})
                            stepped.append(gradient_step(cfg, model, optimizer, losses, ema))
                        updates += 1
            if stepped:  # means over the iteration's gradient steps (PPO's clip fraction and KL grow over its epochs)
                metrics.update({f"train/{k}": sum(s[k] for s in stepped) / len(stepped) for k in stepped[0]})
            metrics["time/update_s"] = time.perf_counter() - t1
            metrics["time/iteration_s"] = time.perf_counter() - t0  # collection (or the wait for it) to the last update
            iteration += 1
            metrics.update({"train/env_steps": env_steps, "train/updates": updates})

            crossed = eval_every and (env_steps // eval_every) > ((env_steps - steps) // eval_every)
            if int(cfg.eval.episodes) > 0 and (crossed or env_steps >= total):
                if overlap == "thread":  # evaluation sets the process-wide exploration type the collection reads
                    ahead.wait()
                with ema_applied(ema):  # ema.enabled: the moving average is what is evaluated
                    history.append(run_eval(cfg, model, env_steps, updates, start))
                metrics["eval/success_once"] = history[-1]["success_once"]
                (run_dir / "eval_history.json").write_text(json.dumps(history, indent=2))
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=env_steps)
            if "train/success_rate" in metrics:
                pbar.set_postfix(reward=f"{metrics['train/chunk_reward']:.3f}", success=f"{metrics['train/success_rate']:.2f}")
            if iteration % int(cfg.checkpoint.interval) == 0 or env_steps >= total:
                checkpoint()
    finally:
        pbar.close()
        if ahead is not None:
            ahead.close()
        if collector is not None:
            collector.shutdown()

    (run_dir / "eval_history.json").write_text(json.dumps(history, indent=2))
    final = {**(history[-1] if history else {}), "iterations": iteration, "config": config}
    (run_dir / "final.json").write_text(json.dumps(final, indent=2))
    print(f"{PREFIX} done: {env_steps} env steps, {updates} updates; "
          + (f"success_once {history[-1]['success_once']:.2f}" if history else "no evaluation"))


if __name__ == "__main__":
    main()
