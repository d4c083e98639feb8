"""Load the project's scripts (benchmarks, recipe utilities) as modules: they are files, not a package."""
from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load_script(path: str | Path, name: str | None = None):
    """The script at ``path`` (relative to the repository root, or absolute) as a fresh module named ``name``
    (default: the file's stem)."""
    path = REPO / path
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
