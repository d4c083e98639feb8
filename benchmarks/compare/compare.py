"""Offline-to-online comparison: our two fine-tuning algorithms against the RL and imitation baselines.

    # run (or continue) every method on one task, one training seed, a 50k env-step budget
    python benchmarks/compare/compare.py run --task PickCube-v1 --seeds 0 --budget 50000 \\
        --pretrained runs/pretrain_{task}_s{seed}
    # only some methods, shorter
    python benchmarks/compare/compare.py run --task PickCube-v1 --methods mmada_rwr mmada_ppo --budget 5000 ...
    # a policy pretrained through a narrower camera mixes in the demonstrations seen through it
    python benchmarks/compare/compare.py run --task PushCube-v1 --methods mmada_ppo_group --pretrained runs/push_fov60_s{seed} \\
        --demos data/{task}-fov60 --runs runs/compare_fov60 --budget 8000 --eval-every 4000 --eval-episodes 50
    # the baselines on the same demonstrations and camera (the pixel baselines take the buffer's camera)
    python benchmarks/compare/compare.py run --task PushCube-v1 --methods ppo_rgb bc --demos data/{task}-fov60 \
        --runs runs/compare_fov60 --budget 24000 --eval-every 4000 --eval-episodes 50
    # tables and curves from whatever runs exist
    python benchmarks/compare/compare.py report --task PickCube-v1 PushCube-v1
    # several run directories side by side, each but the first named (its methods' labels say which)
    python benchmarks/compare/compare.py report --task PushCube-v1 \
        --runs runs/compare_fov60 "block-causal pretraining=runs/compare_fov60_blockcausal"

Every method is one of the project's recipes run as a subprocess into
``--runs/{task}/{method}/s{seed}`` (default ``runs/compare``); a run directory
that holds checkpoints but no ``final.json`` is resumed (``checkpoint.resume=true``),
so an interrupted benchmark continues where it stopped, and so is a finished online
run whose env steps fall short of a larger ``--budget`` (24k runs extend to 50k). Each recipe evaluates on
the same fixed seeds (``1_000_000 + i``, disjoint from every training seed) and
writes ``eval_history.json`` (``success_once`` against online env steps); the
imitation baselines train on the demonstrations only and are drawn as a level
line at env step 0.

``report`` writes ``benchmarks/results/compare.{json,md,png}``: each run's first and last evaluation, the mean
``success_once`` over seeds at equal online env steps (``--at``), and, for our fine-tuning runs, the successes of
the episodes their sampled policy finished while collecting, per ``--window`` env steps (the evaluations decode
greedily, so this is the one measure of the stochastic policy that fine-tuning trains, at no extra cost).
``report --runs`` takes several directories, ``PATH`` or ``NAME=PATH`` (e.g. the same methods started from other
pretrained policies): each named directory's methods are reported as their own rows and curves, ``NAME`` in their
labels and ``METHOD@NAME`` as their key in ``compare.json``.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import RESULTS, markdown_table, save_figure, write_results  # noqa: E402
from pretraining import read_scalar  # noqa: E402

#: the fine-tuning recipe as the methods below were run and recorded: a success ended the episode and was worth its
#: step's reward alone (advantage.absorbing_success=false), and the demonstration updates trained without the
#: pretraining run's state dropout, expected-bin loss and image shift; kept so that their recorded results reproduce
_FINETUNE = ["recipes/finetune/finetune.py", "--config-name", "maniskill", "advantage.absorbing_success=false",
             "loss.proprio_drop_prob=0", "loss.action_mean_weight=0", "demos.random_shift=0"]
#: the recipe's defaults for those three: the loss the policy was pretrained with (the methods named ..._keep)
_KEEP_PRETRAINING_LOSS = ("loss.proprio_drop_prob=", "loss.action_mean_weight=", "demos.random_shift=")


def _keep_pretraining_loss(args: list[str]) -> list[str]:
    """``args`` without the overrides that turn the pretraining run's regularisers off."""
    return [a for a in args if not a.startswith(_KEEP_PRETRAINING_LOSS)]
#: filtered self-imitation: sparse reward, episode returns as advantages, binary weights
_RFT = [*_FINETUNE, "algo=rwr", "env.reward=sparse",
        "advantage.estimator=return", "loss.rwr.weighting=binary", "loss.rwr.normalize_weights=true",
        "collector.temperature=0.5"]
#: filtered self-imitation of the executed actions of the greedy policy's noisy rollouts (goal tokens weighted too)
_RFT_NOISE = [*(a for a in _RFT if not a.startswith("collector.temperature")), "collector.action_noise=0.1",
              "loss.rwr.weight_goal=true"]
#: the same noisy rollouts, each chunk's GAE advantage (a learned value of the dense reward) standardised over the
#: batch's online rows and used as a signed weight: chunks better than expected are pulled up, worse ones pushed down
_GAE_NOISE = [*_FINETUNE, "algo=rwr", "env.reward=dense",
              "advantage.estimator=gae", "loss.rwr.weighting=signed", "loss.rwr.standardize_advantage=true",
              "loss.rwr.normalize_weights=true", "collector.action_noise=0.05", "loss.rwr.weight_goal=true"]
#: the same with each success absorbing (the recipe's default): the succeeding chunk also earns gamma**j / (1 - gamma)
_GAE_NOISE_ABSORBING = [a.replace("absorbing_success=false", "absorbing_success=true") for a in _GAE_NOISE]
#: and the critic first fitted to the demonstrations' returns (2000 minibatches of 64 steps, about 6 passes over 300 demos)
_GAE_NOISE_VDEMO = [*_GAE_NOISE_ABSORBING, "value.pretrain_steps=2000"]
#: or the critic reading the simulator's privileged state (an asymmetric critic; the policy still reads its pixels)
_GAE_NOISE_PRIVILEGED = [*_GAE_NOISE_ABSORBING, "value.input=privileged_state"]
#: the same critic reading the raw state, unscaled (the first run of it; benchmarks/critic_fit.py shows why it changed)
_GAE_NOISE_PRIVILEGED_RAW = [*_GAE_NOISE_PRIVILEGED, "value.normalize_privileged=false"]
#: the standardised privileged critic learning alone on the first 10k env steps' rollouts (DPPO's critic warm-up)
_GAE_NOISE_PRIVILEGED_WARMUP = [*_GAE_NOISE_PRIVILEGED, "value.warmup_env_steps=10000"]
#: no critic: each chunk's discounted return to its episode's end (success absorbing) as its advantage, standardised
#: over the batch's online rows as a signed weight (what the privileged critic's advantages turned out to track)
_RETURN_TO_GO_NOISE = [a.replace("estimator=gae", "estimator=return_to_go") for a in _GAE_NOISE_ABSORBING]
#: the same with the pretraining run's regularisers kept
_RETURN_TO_GO_KEEP = _keep_pretraining_loss(_RETURN_TO_GO_NOISE)
#: and at the learning rate 1e-4 (3.3x the recipe's 3e-5)
_RETURN_TO_GO_KEEP_LR1E4 = [*_RETURN_TO_GO_KEEP, "optim.lr=1e-4"]
#: and evaluated and saved as the moving average of the weights
_RETURN_TO_GO_KEEP_LR1E4_EMA = [*_RETURN_TO_GO_KEEP_LR1E4, "ema.enabled=true"]
#: the same with each return to go relative to the last 50 episodes' at its decision index, in units of their spread
#: (advantage.baseline_episodes), instead of standardised over each minibatch's online rows
_RETURN_TO_GO_BASELINE_KEEP_LR1E4_EMA = [*(a.replace("standardize_advantage=true", "standardize_advantage=false")
                                          for a in _RETURN_TO_GO_KEEP_LR1E4),
                                         "advantage.baseline_episodes=50", "ema.enabled=true"]
#: and the demonstration windows in the hold after a grasp scored on the gripper alone
_RETURN_TO_GO_KEEP_LR1E4_GRIPPER = [*_RETURN_TO_GO_KEEP_LR1E4, "demos.grasp_hold_gripper_only=true"]
#: and evaluated and saved as the moving average of the weights
_RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA = [*_RETURN_TO_GO_KEEP_LR1E4_GRIPPER, "ema.enabled=true"]
#: the same at the recipe's learning rate
_RETURN_TO_GO_KEEP_GRIPPER_EMA = [a.replace("optim.lr=1e-4", "optim.lr=3e-5") for a in _RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA]
#: path-likelihood PPO with group-relative success advantages (4 episodes per initial state)
_PPO_GROUP = [*_FINETUNE, "algo=ppo", "env.reward=sparse",
              "advantage.estimator=group", "advantage.group_size=4", "optim.lr=1e-5"]
#: the same, replaying 2 of the 10 denoising steps of each path per update
_PPO_GROUP_2STEPS = [*_PPO_GROUP, "loss.ppo.denoising_steps=2"]
#: the imitation baselines' recipe (6000 steps, as the pretraining of ours)
_IMITATION = ["recipes/baselines/imitation.py", "--config-name", "maniskill"]
#: the same four times longer (the learning-rate schedule stretched with it), evaluated halfway and at the end
_IMITATION_24K = ["optim.total_steps=24000", "eval.interval=12000"]
#: the imitation baselines on the privileged state (their demonstrations: ``run --state-demos``)
_STATE_OBS = ["env.obs_mode=state"]
#: method -> (label, observations, recipe command, whether it uses online interaction)
METHODS = {
    "mmada_rwr": ("MMaDA-VLA + reward-weighted diffusion (ours)", "rgb+proprio",
                  [*_FINETUNE, "algo=rwr"], True),
    "mmada_rwr_conservative": ("MMaDA-VLA + reward-weighted diffusion, conservative (ours)", "rgb+proprio",
                               [*_FINETUNE, "algo=rwr",
                                "collector.temperature=0.5", "loss.rwr.standardize_advantage=true",
                                "loss.rwr.temperature=0.5", "loss.rwr.kl_coef=0.5"], True),
    "mmada_rft": ("MMaDA-VLA + filtered self-imitation (ours: binary weights, sparse reward)", "rgb+proprio", _RFT, True),
    "mmada_rft_goal": ("MMaDA-VLA + filtered self-imitation, goals weighted too (ours)", "rgb+proprio",
                       [*_RFT, "loss.rwr.weight_goal=true"], True),
    "mmada_rft_signed": ("MMaDA-VLA + episode-success advantages, zero-mean signed weights (ours)", "rgb+proprio",
                         [a.replace("weighting=binary", "weighting=signed") for a in _RFT] + ["loss.rwr.standardize_advantage=true"],
                         True),
    "mmada_rft_noise": ("MMaDA-VLA + filtered self-imitation of the greedy policy's noisy rollouts (ours: executed "
                        "actions of successful episodes, N(0, 0.1^2) on the arm, goals weighted too)", "rgb+proprio",
                        _RFT_NOISE, True),
    "mmada_rft_noise_small": ("MMaDA-VLA + filtered self-imitation of the greedy policy's noisy rollouts, half the noise "
                              "(ours: N(0, 0.05^2) on the arm)", "rgb+proprio",
                              [a.replace("action_noise=0.1", "action_noise=0.05") for a in _RFT_NOISE], True),
    "mmada_gae_noise_small": ("MMaDA-VLA + per-chunk GAE advantages, zero-mean signed weights, on the greedy policy's "
                              "noisy rollouts (ours: dense reward, N(0, 0.05^2) on the arm, goals weighted too)",
                              "rgb+proprio", _GAE_NOISE, True),
    "mmada_gae_noise_absorbing": ("MMaDA-VLA + per-chunk GAE advantages, success absorbing, zero-mean signed weights, "
                                  "on the greedy policy's noisy rollouts (ours: dense reward, a success worth "
                                  "1 / (1 - gamma) more, N(0, 0.05^2) on the arm, goals weighted too)",
                                  "rgb+proprio", _GAE_NOISE_ABSORBING, True),
    "mmada_gae_noise_vdemo": ("MMaDA-VLA + per-chunk GAE advantages from a critic first fitted to the demonstrations' "
                              "returns, success absorbing, zero-mean signed weights, on the greedy policy's noisy "
                              "rollouts (ours: dense reward, N(0, 0.05^2) on the arm, goals weighted too)",
                              "rgb+proprio", _GAE_NOISE_VDEMO, True),
    "mmada_gae_noise_privileged": ("MMaDA-VLA + per-chunk GAE advantages from a critic reading the simulator's "
                                   "privileged state, success absorbing, zero-mean signed weights, on the greedy "
                                   "policy's noisy rollouts (ours: dense reward, N(0, 0.05^2) on the arm, goals "
                                   "weighted too; the policy reads only its pixels and proprio; the state "
                                   "standardised by running moments)",
                                   "rgb+proprio", _GAE_NOISE_PRIVILEGED, True),
    "mmada_gae_noise_privileged_raw": ("MMaDA-VLA + per-chunk GAE advantages from a critic reading the simulator's "
                                       "privileged state unscaled, success absorbing, zero-mean signed weights, on the "
                                       "greedy policy's noisy rollouts (ours: dense reward, N(0, 0.05^2) on the arm, "
                                       "goals weighted too; the policy reads only its pixels and proprio)",
                                       "rgb+proprio", _GAE_NOISE_PRIVILEGED_RAW, True),
    "mmada_gae_noise_privileged_warmup": ("MMaDA-VLA + per-chunk GAE advantages from a critic reading the simulator's "
                                          "standardised privileged state, which learns alone for the first 10k env "
                                          "steps (the policy waits; those rollouts are not learned from), then as "
                                          "mmada_gae_noise_privileged (ours)", "rgb+proprio",
                                          _GAE_NOISE_PRIVILEGED_WARMUP, True),
    "mmada_demos_only": ("No-RL control: the same fine-tuning updates on demonstrations only", "rgb+proprio",
                         [*_FINETUNE, "algo=rwr", "demos.ratio=1.0",
                          "collector.temperature=0.5"], True),
    "mmada_demos_only_keep": ("No-RL control with the pretraining run's state dropout, expected-bin loss and image "
                              "shift kept", "rgb+proprio",
                              _keep_pretraining_loss([*_FINETUNE, "algo=rwr", "demos.ratio=1.0",
                                                      "collector.temperature=0.5"]), True),
    "mmada_gae_noise_privileged_keep": ("mmada_gae_noise_privileged with the pretraining run's state dropout, "
                                        "expected-bin loss and image shift kept (ours)", "rgb+proprio",
                                        _keep_pretraining_loss(_GAE_NOISE_PRIVILEGED), True),
    "mmada_gae_noise_privileged_keep_valuenorm": ("mmada_gae_noise_privileged_keep with the critic learning its "
                                                  "targets standardised by their running moments (ours: MAPPO's "
                                                  "value normalisation)", "rgb+proprio",
                                                  [*_keep_pretraining_loss(_GAE_NOISE_PRIVILEGED),
                                                   "value.normalize_targets=true"], True),
    "mmada_return_to_go_noise_keep": ("MMaDA-VLA + each chunk's discounted return to the episode's end as its "
                                      "advantage (no critic), success absorbing, zero-mean signed weights, on the "
                                      "greedy policy's noisy rollouts (ours: dense reward, N(0, 0.05^2) on the arm, "
                                      "goals weighted too; the pretraining run's regularisers kept)", "rgb+proprio",
                                      _RETURN_TO_GO_KEEP, True),
    "mmada_return_to_go_noise_keep_ema": ("mmada_return_to_go_noise_keep evaluated and saved as the moving average "
                                          "of its weights (ours: the recipe's 3e-5, WeightEMA's average)",
                                          "rgb+proprio", [*_RETURN_TO_GO_KEEP, "ema.enabled=true"], True),
    "mmada_return_to_go_noise_keep_lr1e4": ("mmada_return_to_go_noise_keep at the learning rate 1e-4 (3.3x the "
                                            "recipe's 3e-5; ours)", "rgb+proprio",
                                            _RETURN_TO_GO_KEEP_LR1E4, True),
    "mmada_return_to_go_noise_keep_lr1e4_cosine": ("mmada_return_to_go_noise_keep_lr1e4 with the learning rate "
                                                   "decayed along a cosine to 1e-5 over the budget (ours)", "rgb+proprio",
                                                   [*_RETURN_TO_GO_KEEP_LR1E4, "optim.lr_decay=cosine",
                                                    "optim.min_lr_ratio=0.1"], True),
    "mmada_return_to_go_noise_keep_lr1e4_ema": ("mmada_return_to_go_noise_keep_lr1e4 evaluated and saved as the moving "
                                                "average of its weights (ours: the same training, WeightEMA's average; "
                                                "for tasks without a grasp hold)", "rgb+proprio",
                                                _RETURN_TO_GO_KEEP_LR1E4_EMA, True),
    "mmada_return_to_go_baseline_noise_keep_lr1e4_ema": ("mmada_return_to_go_noise_keep_lr1e4_ema with each return to "
                                                         "go relative to the last 50 episodes' at the same decision "
                                                         "index, over their spread, instead of standardised over the "
                                                         "minibatch (ours: a baseline of time alone)", "rgb+proprio",
                                                         _RETURN_TO_GO_BASELINE_KEEP_LR1E4_EMA, True),
    "mmada_demos_only_keep_lr1e4_ema": ("No-RL control of mmada_return_to_go_noise_keep_lr1e4_ema: the same updates, "
                                        "learning rate, regularisers and moving average on demonstrations only (the "
                                        "noisy rollouts collected, not learned from)", "rgb+proprio",
                                        [*_RETURN_TO_GO_KEEP_LR1E4_EMA, "demos.ratio=1.0"], True),
    "mmada_return_to_go_noise_keep_lr1e4_ema_demos075": ("mmada_return_to_go_noise_keep_lr1e4_ema with three "
                                                        "demonstration windows in four of each minibatch (ours: "
                                                        "demos.ratio=0.75, 12 demonstration and 4 online rows)",
                                                        "rgb+proprio",
                                                        [*_RETURN_TO_GO_KEEP_LR1E4_EMA, "demos.ratio=0.75"], True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper": ("mmada_return_to_go_noise_keep_lr1e4 with the demonstration "
                                                    "windows that start in the hold after a grasp drawn and scored on "
                                                    "the gripper alone (ours)", "rgb+proprio",
                                                    _RETURN_TO_GO_KEEP_LR1E4_GRIPPER, True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper_ema": ("mmada_return_to_go_noise_keep_lr1e4_gripper evaluated and saved "
                                                        "as the moving average of its weights (ours: the same "
                                                        "training, WeightEMA's average)", "rgb+proprio",
                                                        _RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA, True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_quiet": ("mmada_return_to_go_noise_keep_lr1e4_gripper_ema "
                                                              "exploring with half the noise (ours: N(0, 0.025^2) "
                                                              "on the arm)", "rgb+proprio",
                                                              [a.replace("action_noise=0.05", "action_noise=0.025")
                                                               for a in _RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA], True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_long": ("mmada_return_to_go_noise_keep_lr1e4_gripper_ema with a "
                                                             "longer moving average (ours: ema.power=0.9, about 2200 "
                                                             "updates' horizon after 5080, against 600 at 0.75)",
                                                             "rgb+proprio",
                                                             [*_RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA, "ema.power=0.9"],
                                                             True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_demos075": ("mmada_return_to_go_noise_keep_lr1e4_gripper_ema "
                                                                 "with three demonstration windows in four of each "
                                                                 "minibatch (ours: demos.ratio=0.75, 12 demonstration "
                                                                 "and 4 online rows)", "rgb+proprio",
                                                                 [*_RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA,
                                                                  "demos.ratio=0.75"], True),
    "mmada_return_to_go_noise_keep_lr1e4_gripper_ema_process": ("mmada_return_to_go_noise_keep_lr1e4_gripper_ema "
                                                                "with each next batch collected during the updates, "
                                                                "in a process of its own (ours: "
                                                                "collector.overlap=process, each batch from the "
                                                                "weights one iteration behind; 0.59x the iteration "
                                                                "time at 1 thread)", "rgb+proprio",
                                                                [*_RETURN_TO_GO_KEEP_LR1E4_GRIPPER_EMA,
                                                                 "collector.overlap=process"], True),
    "mmada_return_to_go_noise_keep_gripper_ema": ("mmada_return_to_go_noise_keep_lr1e4_gripper_ema at the recipe's "
                                                  "learning rate (ours: optim.lr=3e-5 instead of 1e-4)", "rgb+proprio",
                                                  _RETURN_TO_GO_KEEP_GRIPPER_EMA, True),
    "mmada_return_to_go_noise_keep_gripper_ema_noise002": ("mmada_return_to_go_noise_keep_gripper_ema exploring with "
                                                           "N(0, 0.02^2) on the arm instead of N(0, 0.05^2) (ours: the "
                                                           "noise that costs the pretrained d_model=256 policies no "
                                                           "success)", "rgb+proprio",
                                                           [a.replace("action_noise=0.05", "action_noise=0.02")
                                                            for a in _RETURN_TO_GO_KEEP_GRIPPER_EMA], True),
    "mmada_gae_noise_privileged_keep_ensemble": ("mmada_gae_noise_privileged_keep acting as one ensemble with the "
                                                 "policies pretrained with the other --ensemble-seeds (ours: the mean "
                                                 "greedy chunk + N(0, 0.05^2) runs; they stay frozen; evaluated alone)",
                                                 "rgb+proprio", _keep_pretraining_loss(_GAE_NOISE_PRIVILEGED), True),
    "mmada_ppo": ("MMaDA-VLA + path-likelihood PPO (ours)", "rgb+proprio",
                  [*_FINETUNE, "algo=ppo"], True),
    "mmada_ppo_group": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages (ours)", "rgb+proprio",
                        _PPO_GROUP, True),
    "mmada_ppo_group_demos": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages, the "
                              "demonstrations' denoising loss in every minibatch (ours; every denoising step replayed, "
                              "for one-step policies)", "rgb+proprio", [*_PPO_GROUP, "loss.ppo.demo_coef=1.0"], True),
    "mmada_ppo_group_2steps": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages, 2 of 10 denoising "
                               "steps replayed per update (ours)", "rgb+proprio", _PPO_GROUP_2STEPS, True),
    "mmada_ppo_group_2steps_demos": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages, 2 of 10 "
                                     "denoising steps replayed, the demonstrations' denoising loss in every minibatch "
                                     "(ours)", "rgb+proprio",
                                     [*_PPO_GROUP_2STEPS, "loss.ppo.demo_coef=1.0"], True),
    "mmada_ppo_group_2steps_4groups": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages, 2 of 10 "
                                       "denoising steps replayed, 160 decisions (about 4 initial-state groups) per "
                                       "update in minibatches of 64 (ours)", "rgb+proprio",
                                       [*_PPO_GROUP_2STEPS, "collector.decisions_per_batch=160",
                                        "replay_buffer.batch_size=64", "checkpoint.interval=2"], True),
    "mmada_ppo_group_2steps_actions": ("MMaDA-VLA + path-likelihood PPO, group-relative success advantages, 2 of 10 "
                                       "denoising steps replayed, the action tokens alone in the ratio (ours)",
                                       "rgb+proprio", [*_PPO_GROUP_2STEPS, "loss.ppo.tokens=action"], True),
    "ppo_rgb": ("PPO from scratch", "rgb+proprio",
                ["recipes/baselines/online.py", "--config-name", "online_maniskill", "algo=ppo"], True),
    "sac_rlpd_state": ("SAC + demos (RLPD)", "privileged state (reference)",
                       ["recipes/baselines/online.py", "--config-name", "online_maniskill", "algo=sac"], True),
    "iql_state": ("IQL offline -> online", "privileged state (reference)",
                  ["recipes/baselines/online.py", "--config-name", "online_maniskill", "algo=iql"], True),
    "bc": ("BC (demos only)", "rgb+proprio", [*_IMITATION, "algo=bc"], False),
    "diffusion_policy": ("Diffusion Policy (demos only)", "rgb+proprio", [*_IMITATION, "algo=diffusion_policy"], False),
    "bc_24k": ("BC, 24k steps (demos only)", "rgb+proprio", [*_IMITATION, "algo=bc", *_IMITATION_24K], False),
    "diffusion_policy_24k": ("Diffusion Policy, 24k steps (demos only)", "rgb+proprio",
                             [*_IMITATION, "algo=diffusion_policy", *_IMITATION_24K], False),
    # the same imitation baselines with perfect perception: what the demonstrations teach at best
    "bc_state": ("BC (demos only)", "privileged state (reference)", [*_IMITATION, "algo=bc", *_STATE_OBS], False),
    "diffusion_policy_state": ("Diffusion Policy (demos only)", "privileged state (reference)",
                               [*_IMITATION, "algo=diffusion_policy", *_STATE_OBS], False),
}


#: the methods that act together with the policies pretrained with the other seeds (``run --ensemble-seeds``)
ENSEMBLE_METHODS = ("mmada_gae_noise_privileged_keep_ensemble",)


def ensemble_partners(method: str, task: str, seed: int, pretrained: str, ensemble_seeds: list[int]) -> list[str]:
    """The pretrained policies a run of ``method`` from seed ``seed`` acts with: ``pretrained`` at each of
    ``ensemble_seeds`` but ``seed`` (none for the other methods); a ``ValueError`` when an ensemble method gets none."""
    if method not in ENSEMBLE_METHODS:
        return []
    partners = [pretrained.format(task=task, seed=s) for s in ensemble_seeds if s != seed]
    if not partners:
        raise ValueError(f"{method} acts with the policies pretrained with other seeds: pass --ensemble-seeds with at "
                         f"least one seed besides {seed} (e.g. --seeds 0 --ensemble-seeds 0 1 2).")
    return partners


def run_dir(runs: Path, task: str, method: str, seed: int) -> Path:
    return runs / task / method / f"s{seed}"


def command(method: str, task: str, seed: int, budget: int, out: Path, pretrained: str, eval_episodes: int,
            eval_every: int, demos: str = "data/{task}", eval_sample_temperature: float | None = None,
            ensemble_seeds: list[int] = (), state_demos: str = "data/state/{task}") -> list[str]:
    """The recipe command of one run; ``pretrained``, ``demos`` and ``state_demos`` are formatted with ``task`` and
    ``seed``.

    ``pretrained`` is our fine-tuning methods' starting point. ``demos`` is the RGB demonstration buffer every
    pixel-based method shares: our methods mix it in, the pixel imitation baselines train on it, and every pixel
    baseline (PPO from pixels too, which learns without demonstrations) is given the camera the buffer was
    recorded with, so every method sees the same images (ours take theirs from the pretrained policy, trained on
    the same buffer). The baselines on the privileged state (SAC, IQL, BC and Diffusion Policy on the state) learn
    from ``state_demos``, the same planner's demonstrations recorded as state vectors (the online recipe collects
    plain planner demonstrations there when the buffer is missing).
    ``eval_sample_temperature`` evaluates our methods' sampled (not greedy) decoding. ``ensemble_seeds``: see
    :func:`ensemble_partners`."""
    _, obs, recipe, online = METHODS[method]
    demos = demos.format(task=task, seed=seed)
    cmd = [sys.executable, *recipe, f"env.task={task}", f"seed={seed}", f"run_dir={out}", f"eval.episodes={eval_episodes}"]
    if method.startswith("mmada"):
        cmd += [f"pretrained={pretrained.format(task=task, seed=seed)}", f"collector.total_env_steps={budget}",
                f"eval.interval_env_steps={eval_every}", f"demos.dir={demos}"]
        if eval_sample_temperature is not None:
            cmd.append(f"eval.sample_temperature={eval_sample_temperature}")
        partners = ensemble_partners(method, task, seed, pretrained, list(ensemble_seeds))
        if partners:
            cmd.append("collector.ensemble_with=[" + ",".join(f"'{p}'" for p in partners) + "]")
    elif online:
        cmd += [f"collector.total_env_steps={budget}", f"eval.interval={eval_every}"]
    elif obs == "rgb+proprio":
        cmd.append(f"data.dir={demos}")
    if obs != "rgb+proprio":  # every state baseline learns from demonstrations
        cmd.append(f"data.dir={state_demos.format(task=task, seed=seed)}")
    if not method.startswith("mmada") and obs == "rgb+proprio":  # ours take the camera from the pretrained policy
        camera_fov = demos_camera_fov(ROOT / demos)
        if camera_fov is not None:
            cmd.append(f"env.camera_fov={camera_fov:g}")
    if (out / "checkpoints").exists():
        cmd.append("checkpoint.resume=true")
    return cmd


def demos_camera_fov(demos: Path) -> float | None:
    """The camera field of view a demonstration buffer was recorded with (None: the task's own, or no buffer)."""
    from mmada_rl.data.metadata import METADATA_FILE, BufferMetadata  # only the pixel baselines' commands need it

    return BufferMetadata.load(demos).camera_fov if (demos / METADATA_FILE).exists() else None


def finished(out: Path, online: bool, budget: int) -> bool:
    """Whether a run is complete: it wrote ``final.json`` and, when it interacts online, reached ``budget`` env
    steps (a run finished at a smaller budget is resumed from its last checkpoint and continued to the new one)."""
    final = out / "final.json"
    if not final.exists():
        return False
    return not online or int(json.loads(final.read_text()).get("env_steps", 0)) >= budget


def run(args: argparse.Namespace) -> int:
    for task in args.task:
        for seed in args.seeds:
            for method in args.methods:
                out = run_dir(args.runs, task, method, seed)
                if finished(out, METHODS[method][3], args.budget):
                    print(f"[compare] {task} {method} s{seed}: done already ({out})")
                    continue
                cmd = command(method, task, seed, args.budget, out, args.pretrained, args.eval_episodes, args.eval_every,
                              args.demos, args.eval_sample_temperature, args.ensemble_seeds, args.state_demos)
                print(f"[compare] {task} {method} s{seed}: {shlex.join(cmd[1:])}", flush=True)
                proc = subprocess.run(cmd, cwd=ROOT)
                if proc.returncode != 0:
                    print(f"[compare] {method} exited with {proc.returncode}; rerun the same command to resume it.")
                    return proc.returncode
    return 0


def history_of(out: Path, online: bool) -> list[dict]:
    """Evaluation records of a run: ``eval_history.json`` (without each record's ``per_episode``, which
    ``benchmarks/paired.py`` reads), or the imitation recipe's final evaluation at env step 0."""
    if (out / "eval_history.json").exists():
        return [{k: v for k, v in r.items() if k != "per_episode"}
                for r in json.loads((out / "eval_history.json").read_text())]
    if not online and (out / "final.json").exists():
        final = json.loads((out / "final.json").read_text())
        if "eval/success_once" in final:
            return [{"env_steps": 0, "success_once": final["eval/success_once"], "episodes": final.get("eval/episodes"),
                     "success_once_ci_low": final.get("eval/success_once_ci_low"),
                     "success_once_ci_high": final.get("eval/success_once_ci_high")}]
    return []


def success_at(history: list[dict], env_steps: int) -> float | None:
    """``success_once`` of the evaluation taken nearest ``env_steps`` online env steps, within 10% of it
    (evaluations fall after whole collection rounds, e.g. at 4135 for 4000); None when there is none."""
    near = [r for r in history if abs(r["env_steps"] - env_steps) <= 0.1 * env_steps]
    return min(near, key=lambda r: abs(r["env_steps"] - env_steps))["success_once"] if near else None


def mean_at(histories: dict[str, list[dict]], env_steps: int, online: bool) -> tuple[float | None, int]:
    """Mean ``success_once`` over the seeds evaluated near ``env_steps`` (see :func:`success_at`), and how many
    seeds that is. Demonstration-only methods use no env steps: their one evaluation counts at every budget."""
    values = [success_at(h, env_steps) if online else h[-1]["success_once"] for h in histories.values()]
    values = [v for v in values if v is not None]
    return (sum(values) / len(values) if values else None), len(values)


def budget_grid(results: dict, every: int = 5_000) -> list[int]:
    """0, every, 2 * every, ... up to the most env steps any run reached (and that, when it lies off the grid)."""
    top = max(r["env_steps"] for t in results.values() for m in t.values() for h in m["histories"].values() for r in h)
    grid = list(range(0, top + 1, every))
    return grid + [top] if top - grid[-1] > every / 4 else grid


def budget_table(results: dict, budgets: list[int]) -> str:
    """Mean ``success_once`` over seeds at equal online env steps, one row per method; a cell averaged over fewer
    seeds than the row has says how many."""
    rows = []
    for task, methods in results.items():
        for entry in methods.values():
            cells = []
            for b in budgets:
                mean, n = mean_at(entry["histories"], b, entry["online"])
                more = "" if n == len(entry["histories"]) else f" ({n})"
                cells.append(f"{mean:.2f}{more}" if mean is not None else "-")
            rows.append([task, entry["label"], entry["observations"], len(entry["histories"]), *cells])
    return markdown_table(["task", "method", "observations", "seeds", *(f"{b:,}" for b in budgets)], rows)


def logged(out: Path, name: str) -> dict[int, float]:
    """One scalar a recipe logged (:func:`pretraining.read_scalar`; a fine-tuning run logs by env step), by env
    step. A resumed run logs again the iterations after its last checkpoint: the later row of a step wins, and
    rows a restart overtook (logged before it, at steps it reached again) are dropped."""
    rows: list[tuple[int, float]] = []
    for step, value in read_scalar(out, name):
        while rows and rows[-1][0] >= step:
            rows.pop()
        rows.append((step, value))
    return dict(rows)


def training_rollouts(out: Path, window: int) -> list[tuple[int, int]]:
    """(successes, episodes) of the episodes a run's acting policy finished while it collected, one pair per window
    of ``window`` online env steps (a batch counts in the window its last env step falls in); empty for runs that do
    not log how many episodes each batch ended (our fine-tuning recipe and the online RL baselines do; imitation
    runs have no rollouts, and online baseline runs older than that log did not). For our methods this is the
    sampled policy that fine-tuning trains, and for the RL baselines their actor sampled, where the evaluations
    act greedily."""
    rates, counts = logged(out, "train/success_rate"), logged(out, "train/episodes")
    if not counts:
        return []
    windows = [[0, 0] for _ in range((max(counts) - 1) // window + 1)]
    for step, n in counts.items():
        windows[(step - 1) // window][0] += round(rates[step] * n)
        windows[(step - 1) // window][1] += int(n)
    return [(k, n) for k, n in windows]


def rollouts_table(results: dict, window: int) -> str:
    """Successes / episodes of the training rollouts per window of env steps, one row per run that logs them."""
    rows = [[task, entry["label"], seed, *(f"{k}/{n}" for k, n in entry["rollouts"][seed])]
            for task, methods in results.items() for entry in methods.values() for seed in entry.get("rollouts", {})]
    if not rows:
        return "(no run logged its training episodes)"
    width = max(len(r) for r in rows)
    rows = [r + [""] * (width - len(r)) for r in rows]
    return markdown_table(["task", "method", "seed", *(f"{i * window:,}–{(i + 1) * window:,}" for i in range(width - 3))],
                          rows)


def decoding_of(history: list[dict]) -> str:
    """How a run's policy was evaluated: greedy (``""``) or sampled at a temperature."""
    sampled = history[-1].get("sample_temperature") or 0.0
    return f", sampled at T={sampled:g}" if sampled else ""


def run_rows(task: str, entry: dict) -> list[list]:
    """One table row per seed of a method's entry in the report: its first and last evaluation."""
    rows = []
    for s, h in entry["histories"].items():
        first, last = h[0], h[-1]
        ci = (f"[{last['success_once_ci_low']:.2f}, {last['success_once_ci_high']:.2f}]"
              if last.get("success_once_ci_low") is not None else "")
        rows.append([task, entry["label"] + decoding_of(h), entry["observations"], s,
                     f"{first['success_once']:.2f} @ {first['env_steps']}" if entry["online"] else "-",
                     f"{last['success_once']:.2f} {ci}", last["env_steps"], last.get("episodes", "")])
    return rows


def named_runs(text: str) -> tuple[str, Path]:
    """``NAME=PATH`` or ``PATH`` (unnamed), one value of ``report --runs``."""
    name, sep, path = text.partition("=")
    if sep and not (name.strip() and path):
        raise argparse.ArgumentTypeError(f"expected PATH or NAME=PATH, got {text!r}")
    return (name.strip(), Path(path)) if sep else ("", Path(text))


def plot_curves(results: dict, tasks: list[str], budgets: list[int], path: Path) -> Path:
    """One panel per task: each online method's ``success_once`` against env steps (with several seeds, each seed
    thin and their mean at ``budgets`` thick), each demonstration-only method a dashed level line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(tasks), figsize=(7 * len(tasks), 4.5), squeeze=False)
    legends = []
    for ax, task in zip(axes[0], tasks):
        entries = list(results.get(task, {}).values())
        palette = plt.get_cmap("tab10" if len(entries) <= 10 else "tab20")  # a colour per method up to 20
        for i, entry in enumerate(entries):
            color, online, n = palette(i % palette.N), entry["online"], len(entry["histories"])
            decoding = decoding_of(next(iter(entry["histories"].values())))
            seen = "" if entry["observations"] == "rgb+proprio" else f", {entry['observations']}"
            name = f"{entry['label']}{decoding}{seen} ({'mean of ' if n > 1 else ''}{', '.join(entry['histories'])})"
            if not online:  # no env steps: a level line
                ax.axhline(mean_at(entry["histories"], 0, False)[0], color=color, linestyle="--", label=name)
                continue
            if n > 1:  # each seed thin, their mean at the common budgets thick
                for h in entry["histories"].values():
                    ax.plot([r["env_steps"] for r in h], [r["success_once"] for r in h], color=color, alpha=0.3, lw=1)
                points = [(b, mean_at(entry["histories"], b, True)) for b in budgets]
                points = [(b, m) for b, (m, k) in points if k == n]
            else:
                points = [(r["env_steps"], r["success_once"]) for r in next(iter(entry["histories"].values()))]
            ax.plot(*zip(*points), color=color, marker="o", lw=2, label=name)
        ax.set_title(task)
        ax.set_xlabel("online env steps")
        ax.set_ylabel("success_once (greedy unless marked)")
        ax.set_ylim(-0.02, 1.02)
        if ax.get_legend_handles_labels()[0]:  # below the curves: the method labels are long
            legend = ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13))
            legend.set_in_layout(False)  # else tight_layout shrinks the axes to fit it; savefig takes it in below
            legends.append(legend)
    return save_figure(fig, path, bbox_inches="tight", bbox_extra_artists=legends)


def report(args: argparse.Namespace) -> int:
    names = [name for name, _ in args.runs]
    if len(set(names)) < len(names):
        raise SystemExit(f"[compare] report --runs: give each run directory but one its own NAME=PATH, got {names}")
    results, rows = {}, []
    for task in args.task:
        for name, runs in args.runs:
            for method, (label, obs, _, online) in METHODS.items():
                runs_of = runs / task / method
                seeds = sorted(p.name for p in runs_of.glob("s*")) if runs_of.exists() else []
                histories = {s: history_of(runs_of / s, online) for s in seeds}
                histories = {s: h for s, h in histories.items() if h}
                if not histories:
                    continue
                entry = results.setdefault(task, {})[f"{method}@{name}" if name else method] = {
                    "method": method, "label": f"{label} [{name}]" if name else label, "observations": obs,
                    "online": online, "runs": str(runs), "histories": histories}
                rollouts = {s: training_rollouts(runs_of / s, args.window) for s in histories}
                if any(rollouts.values()):
                    entry["rollouts"] = {s: r for s, r in rollouts.items() if r}
                rows.extend(run_rows(task, entry))
    if not rows:
        print(f"[compare] no finished evaluations under {', '.join(str(r) for _, r in args.runs)} for {args.task}; "
              "run `compare.py run` first.")
        return 1
    budgets = sorted(args.at) if args.at else budget_grid(results)
    plot_curves(results, args.task, budgets, args.out / "compare.png")
    header = ["task", "method", "observations", "seed", "first evaluation @ env steps", "final success_once [95% CI]",
              "env steps", "eval episodes"]
    table = markdown_table(header, rows)
    budget_rows, rollout_rows = budget_table(results, budgets), rollouts_table(results, args.window)
    write_results("compare", {"runs": {name: str(path) for name, path in args.runs}, "window": args.window,
                              "results": results},
                  f"# Offline-to-online comparison\n\n{table}\n\n"
                  f"## success_once at equal online env steps (mean over seeds)\n\n{budget_rows}\n\n"
                  f"## Training rollouts: successes / episodes the acting policy finished, per {args.window:,} env steps\n\n"
                  "Our methods act with sampled tokens (the policy fine-tuning trains), or with the greedy chunk's actions "
                  "plus Gaussian noise (the methods named for noisy rollouts), the RL baselines with actions sampled "
                  f"from their actors, while the evaluations above act greedily.\n\n{rollout_rows}\n\n"
                  "![curves](compare.png)\n", directory=args.out)
    print(table, budget_rows, rollout_rows, sep="\n\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    methods = "\n".join(f"  {name:<32} {label} [{obs}]" for name, (label, obs, _, _) in METHODS.items())
    p = sub.add_parser("run", help="run (or resume) the methods", epilog=f"methods:\n{methods}",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", nargs="+", default=["PickCube-v1"])
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS), metavar="METHOD",
                   help="the methods to run (default: every one; listed below)")
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--budget", type=int, default=50_000, help="online env steps per run")
    p.add_argument("--eval-every", type=int, default=5_000, help="env steps between evaluations")
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--pretrained", default="runs/pretrain_{task}_s{seed}",
                   help="pretrained MMaDA-VLA run per task and seed ({task}, {seed} are filled in)")
    p.add_argument("--demos", default="data/{task}",
                   help="the RGB demonstration buffer ({task}, {seed} are filled in): our fine-tuning methods mix it "
                        "in, the pixel imitation baselines train on it, every pixel baseline gets its camera; it must match "
                        "the pretrained policy's camera, e.g. data/PushCube-v1-fov60 for a camera_fov=60 policy")
    p.add_argument("--state-demos", default="data/state/{task}",
                   help="the privileged-state demonstration buffer of the state baselines ({task}, {seed} are filled "
                        "in), e.g. data/dart/state/{task} beside --demos data/dart/{task}-fov60 so that every method "
                        "learns from the same planner's demonstrations (the online recipe collects plain planner "
                        "demonstrations when it is missing)")
    p.add_argument("--eval-sample-temperature", type=float, default=None,
                   help="evaluate our fine-tuning methods with tokens sampled at this temperature, the stochastic policy "
                        "they train (default: greedy decoding; the baselines always evaluate their own way)")
    p.add_argument("--ensemble-seeds", nargs="+", type=int, default=[],
                   help="for the methods that act as an ensemble (" + ", ".join(ENSEMBLE_METHODS) + "): the seeds "
                        "whose --pretrained policies act together with each run's own (its own seed is skipped)")
    p.add_argument("--runs", type=Path, default=ROOT / "runs" / "compare")
    p.set_defaults(func=run)
    r = sub.add_parser("report", help="tables and curves from the existing runs")
    r.add_argument("--task", nargs="+", default=["PickCube-v1"])
    r.add_argument("--runs", type=named_runs, nargs="+", default=[("", ROOT / "runs" / "compare")],
                   metavar="[NAME=]PATH",
                   help="run directories (as given to `run --runs`); several are reported side by side, all but one "
                        "named, NAME marking their methods' labels")
    r.add_argument("--out", type=Path, default=RESULTS, help="where compare.{json,md,png} go")
    r.add_argument("--at", type=int, nargs="+", default=None,
                   help="online env-step budgets of the equal-budget table and the mean curves (default: every 5000 "
                        "up to the longest run; use the runs' evaluation points)")
    r.add_argument("--window", type=int, default=4_000,
                   help="env steps per window of the training-rollout table (successes / episodes the acting policy "
                        "finished while collecting)")
    r.set_defaults(func=report)
    args = parser.parse_args(argv)
    if args.command == "report" and args.window < 1:
        parser.error(f"--window must be >= 1 env step, got {args.window}.")
    if args.command == "run":
        try:  # every ensemble method has partners for every seed, before any run starts
            for task in args.task:
                for seed in args.seeds:
                    for method in args.methods:
                        ensemble_partners(method, task, seed, args.pretrained, args.ensemble_seeds)
        except ValueError as err:
            parser.error(str(err))
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
