"""Shared pytest fixtures."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest
import torch

#: The repository root (holds pyproject.toml, scripts/ and tests/).
REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """Every test runs torch on one intra-op thread: the tiny models gain nothing from threads, and
    spinning threads crawl on a busy 2-core machine (recipes run as subprocesses set their own)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def run_cli() -> Callable[..., subprocess.CompletedProcess]:
    """Run ``python -m mmada_rl.cli ARGS...`` from the repository root; returns the finished process.

    Keyword arguments: ``timeout`` (seconds, default 600) and ``env`` (extra
    environment variables). Output is captured as text.
    """

    def run(*args, timeout: float = 600, env: dict | None = None) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "mmada_rl.cli", *map(str, args)],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=timeout,
            env={**os.environ, **(env or {})},
        )

    return run


@pytest.fixture(scope="session")
def pick_demos(tmp_path_factory) -> Path:
    """Two PickCube-v1 motion-planner demonstrations (pd_ee_delta_pose, 64x64 RGB), collected once per session."""
    from mmada_rl.data.collect import collect
    from mmada_rl.envs.maniskill import EnvConfig

    out = tmp_path_factory.mktemp("demos") / "PickCube-v1"
    result = collect(out, EnvConfig(task="PickCube-v1"), episodes=2, progress=False)
    assert result.new_episodes == 2
    return out


@pytest.fixture(scope="session")
def state_demos(tmp_path_factory) -> Path:
    """Two PickCube-v1 planner demonstrations recorded with the privileged state (what SAC, IQL and the
    state-observation imitation references read)."""
    from mmada_rl.data.collect import collect
    from mmada_rl.envs.maniskill import EnvConfig

    out = tmp_path_factory.mktemp("state_demos") / "PickCube-v1"
    assert collect(out, EnvConfig(task="PickCube-v1", obs_mode="state"), episodes=2, progress=False).new_episodes == 2
    return out


@pytest.fixture(scope="session")
def push_demos(pick_demos) -> Path:
    """One PushCube-v1 planner demonstration beside ``pick_demos`` (same parent: ``<parent>/{task}`` names both)."""
    from mmada_rl.data.collect import collect
    from mmada_rl.envs.maniskill import EnvConfig

    out = pick_demos.parent / "PushCube-v1"
    result = collect(out, EnvConfig(task="PushCube-v1"), episodes=1, progress=False)
    assert result.new_episodes == 1
    return out


@pytest.fixture(scope="session")
def toy_pretrain_run(pick_demos, tmp_path_factory) -> Path:
    """The pretraining recipe's toy config on ``pick_demos``: six steps, checkpoints at 3 and 6,
    a one-episode evaluation at the end (a tiny pretrained policy for the fine-tuning tests too)."""
    run_dir = tmp_path_factory.mktemp("pretrain") / "run"
    proc = subprocess.run(
        [sys.executable, str(REPO_ROOT / "recipes" / "pretrain" / "pretrain.py"), f"run_dir={run_dir}",
         f"data.dir={pick_demos}", "data.collect_episodes=0", "optim.total_steps=6", "checkpoint.interval=3",
         "checkpoint.keep=5", "logger.log_interval=1", "num_threads=1", "eval.episodes=1", "eval.max_episode_steps=10"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir
