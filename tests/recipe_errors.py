"""Run a recipe on many bad configurations in one process and collect the error each one ends with.

A recipe started from the command line pays for Python, torch, TorchRL and ManiSkill imports before it
reads its config (about 5 s here); a test per bad configuration, each its own subprocess, paid that each
time. This helper starts one subprocess per recipe instead, which composes each configuration with
Hydra's compose API (the same config files and override grammar as the command line) and calls the
recipe's ``main`` on it, each configuration in a run directory of its own. Each recipe's tests keep one
bad configuration run from the command line, for the path from the exception to the user's terminal.

    python tests/recipe_errors.py recipes/finetune/finetune.py toy < cases.json   # [[override, ...], ...]

prints one JSON list: per case, ``"TypeName: message"`` of the exception it raised, or null if it ran
through.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]


def recipe_errors(recipe: str | Path, cases: list[list[str]], config_name: str = "toy",
                  timeout: float = 600) -> list[str | None]:
    """The error each list of overrides in ``cases`` ends ``recipe`` (a script under ``recipes/``, on its config
    ``config_name``) with, from one subprocess; ``None`` where it ran through."""
    proc = subprocess.run([sys.executable, __file__, str(recipe), config_name], input=json.dumps(cases), cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"recipe_errors.py failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def errors_by_config(recipe: str | Path, bad_configs: list[tuple[list[str], str]],
                     command: Callable[[Path, list[str]], list[str]], root: Path,
                     config_name: str = "toy") -> dict[str, str | None]:
    """:func:`recipe_errors` of each ``(overrides, message)`` of ``bad_configs``, run as ``command(run_dir, overrides)``
    (the whole list of overrides) with a run directory of its own under ``root``; keyed by :func:`config_key`."""
    cases = [command(root / str(i), overrides) for i, (overrides, _) in enumerate(bad_configs)]
    errors = recipe_errors(recipe, cases, config_name)
    return {config_key(overrides): error for (overrides, _), error in zip(bad_configs, errors)}


def config_key(overrides: list[str]) -> str:
    return " ".join(overrides)


def check_error(errors: dict[str, str | None], overrides: list[str], message: str) -> None:
    """Assert that the configuration ``overrides`` ended with an error that says ``message``."""
    error = errors[config_key(overrides)]
    assert error is not None and message in error, error


def _main(recipe: Path, config_name: str, cases: list[list[str]]) -> list[str | None]:
    import importlib.util

    from hydra import compose, initialize_config_dir

    sys.path.insert(0, str(recipe.parent))  # the recipe imports its own utils module
    spec = importlib.util.spec_from_file_location(recipe.stem, recipe)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    errors = []
    for overrides in cases:
        try:
            with initialize_config_dir(config_dir=str(recipe.parent / "config"), version_base=None):
                cfg = compose(config_name=config_name, overrides=overrides)
            module.main(cfg)  # hydra.main passes a given config straight to the recipe's function
            errors.append(None)
        except Exception as err:  # noqa: BLE001 - every error is reported, as the command line would
            errors.append(f"{type(err).__name__}: {err}")
    return errors


if __name__ == "__main__":
    results = _main(Path(sys.argv[1]).resolve(), sys.argv[2], json.load(sys.stdin))
    print(json.dumps(results))
