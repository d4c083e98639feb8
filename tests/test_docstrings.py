"""Every ``>>>`` example in the package's docstrings runs and prints what it shows.

Examples that need what a test cannot make in seconds (a demonstration buffer on
disk, a trained checkpoint, an evaluation of many episodes) carry
``# doctest: +SKIP``; every other example is executed here.
"""
from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import mmada_rl


def _modules() -> list[str]:
    names = [mmada_rl.__name__]
    names += [info.name for info in pkgutil.walk_packages(mmada_rl.__path__, prefix=f"{mmada_rl.__name__}.")]
    return sorted(names)


MODULES = _modules()
# the modules whose examples run (not all skipped); a module that loses all of them fails the test
RUNNABLE = {f"mmada_rl.{name}" for name in (
    "baselines.bc", "baselines.ddpm", "baselines.diffusion_policy", "baselines.encoders", "baselines.normalization",
    "baselines.rl", "data.augment", "diffusion.denoiser", "diffusion.forward_process", "diffusion.sampler",
    "diffusion.schedules", "diffusion.visual", "envs.brdf_lut", "envs.maniskill", "envs.workers", "objectives.advantages",
    "objectives.masked_diffusion", "objectives.path_ppo", "objectives.reward_weighted", "policy.actor",
    "policy.execution", "policy.value", "tokenizers.action_bins", "tokenizers.action_fsq", "tokenizers.action_vq",
    "tokenizers.fit", "tokenizers.image", "tokenizers.layout", "tokenizers.normalize", "tokenizers.text",
    "tokenizers.vocabulary", "training.ema")}


def test_modules_found():
    # the walk must see every subpackage, or the test below would check almost nothing
    assert RUNNABLE <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in {name} failed"
    if name in RUNNABLE:
        assert result.attempted > 0, f"every example in {name} is skipped"
