"""Run a recipe several times in one process: its configurations one after another, each with its own output.

A recipe started from the command line pays, before its first step, for Python, torch, TorchRL and ManiSkill
imports (about 5 s on 2 cores) and for its first env and the first frame its process renders (about 3.5 s,
with SAPIEN's BRDF look-up table read from the machine's cache: mmada_rl/envs/brdf_lut.py). A toy run does
about 6 s of work after that. These helpers start one subprocess for a list of runs instead. It composes each run's
configuration with Hydra's compose API (the same config files and override grammar as the command line)
and calls the recipe's ``main`` on it, in the order given, so a later run may resume an earlier one. Each
run's stdout and stderr (file descriptors 1 and 2, so what its child processes, env workers or a collector
process, write as well; each run starts its own fork server for them) are captured on their own; an
exception ends that run alone, with exit status 1 and its traceback on its stderr, as the command line would.

Each recipe's tests keep runs from the command line as well: the end-to-end run and a bad configuration, for
the path through Hydra's entry point to the user's terminal.

    python tests/recipe_runs.py recipes/finetune/finetune.py toy OUT.json < runs.json   # [[override, ...], ...]

writes to OUT.json one ``{"returncode", "stdout", "stderr", "error"}`` per run.
"""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]


@dataclass
class RecipeRun:
    """One run's exit status and output, as :class:`subprocess.CompletedProcess` names them."""

    returncode: int
    stdout: str
    stderr: str
    error: str | None  # "TypeName: message" of the exception that ended the run; None if it ran through


def run_in_one_process(recipe: str | Path, runs: list[list[str]], config_name: str = "toy",
                       timeout: float = 900) -> list[RecipeRun]:
    """Each list of overrides in ``runs``, run in order by ``recipe`` (a script under ``recipes/``, on its config
    ``config_name``) in one subprocess; one :class:`RecipeRun` per run."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "runs.json"
        proc = subprocess.run([sys.executable, __file__, str(recipe), config_name, str(out)], input=json.dumps(runs),
                              cwd=REPO, capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"recipe_runs.py failed (exit status {proc.returncode}):\n{proc.stderr[-3000:]}")
        return [RecipeRun(**run) for run in json.loads(out.read_text())]


def errors_by_config(recipe: str | Path, bad_configs: list[tuple[list[str], str]],
                     command: Callable[[Path, list[str]], list[str]], root: Path,
                     config_name: str = "toy") -> dict[str, str | None]:
    """The error each ``(overrides, message)`` of ``bad_configs`` ends ``recipe`` with, all run in one process
    (:func:`run_in_one_process`) as ``command(run_dir, overrides)`` (the whole list of overrides) with a run
    directory of its own under ``root``; keyed by :func:`config_key`."""
    runs = [command(root / str(i), overrides) for i, (overrides, _) in enumerate(bad_configs)]
    results = run_in_one_process(recipe, runs, config_name)
    return {config_key(overrides): result.error for (overrides, _), result in zip(bad_configs, results)}


def config_key(overrides: list[str]) -> str:
    return " ".join(overrides)


def check_error(errors: dict[str, str | None], overrides: list[str], message: str) -> None:
    """Assert that the configuration ``overrides`` ended with an error that says ``message``."""
    error = errors[config_key(overrides)]
    assert error is not None and message in error, error


@contextlib.contextmanager
def _fd_to_file(fd: int, path: Path):
    """Point file descriptor ``fd`` (and so whatever writes to it, child processes included) at ``path``."""
    sys.stdout.flush(), sys.stderr.flush()
    saved = os.dup(fd)
    with open(path, "wb") as file:
        os.dup2(file.fileno(), fd)
    try:
        yield
    finally:
        sys.stdout.flush(), sys.stderr.flush()
        os.dup2(saved, fd)
        os.close(saved)


def _run_all(recipe: Path, config_name: str, runs: list[list[str]], out_dir: Path) -> list[dict]:
    import importlib.util

    from hydra import compose, initialize_config_dir

    from mmada_rl.envs.workers import stop_server

    sys.path.insert(0, str(recipe.parent))  # the recipe imports its own utils module
    spec = importlib.util.spec_from_file_location(recipe.stem, recipe)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = []
    for i, overrides in enumerate(runs):
        stdout, stderr = out_dir / f"{i}.stdout", out_dir / f"{i}.stderr"
        returncode, error = 0, None
        with _fd_to_file(1, stdout), _fd_to_file(2, stderr):
            try:
                with initialize_config_dir(config_dir=str(recipe.parent / "config"), version_base=None):
                    cfg = compose(config_name=config_name, overrides=overrides)
                module.main(cfg)  # hydra.main passes a given config straight to the recipe's function
            except (Exception, SystemExit) as err:  # noqa: BLE001 - each run's error is its own, as on the command line
                if not (isinstance(err, SystemExit) and err.code in (0, None)):  # sys.exit(0) ran through
                    traceback.print_exc()
                    returncode, error = 1, f"{type(err).__name__}: {err}"
            finally:
                # the fork server that a run's simulator workers come from (mmada_rl.envs.workers) writes where this
                # run's descriptors 1 and 2 pointed when it started: the next run starts its own
                stop_server()
        results.append({"returncode": returncode, "stdout": stdout.read_text(errors="replace"),
                        "stderr": stderr.read_text(errors="replace"), "error": error})
    return results


if __name__ == "__main__":
    recipe_path, config, out_path = Path(sys.argv[1]).resolve(), sys.argv[2], Path(sys.argv[3])
    out_path.write_text(json.dumps(_run_all(recipe_path, config, json.load(sys.stdin), out_path.parent)))
