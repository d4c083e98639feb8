"""``mmada-rl doctor``: check that this machine can run mmada_rl, and say how to fix what cannot.

Each check returns a :class:`CheckResult` (name, ok, detail, fix). Heavy modules
(torch, SAPIEN, ManiSkill) are imported inside the checks, and every check's
exceptions are caught, so a broken installation still gets a full report.

Run it as ``mmada-rl doctor`` (or ``python -m mmada_rl.doctor`` when the
``mmada-rl`` command itself cannot start).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Callable, Iterator, NamedTuple

#: How to (re)install everything; most fixes end with it.
SETUP_FIX = 'run scripts/setup.sh (or pip install -e ".[test]" in the virtual environment)'

#: The task, camera size and seed of the render check.
RENDER_TASK, RENDER_SIZE, RENDER_SEED = "PickCube-v1", 64, 0

#: Packages whose versions the report lists: (label, distribution names to try).
PACKAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("torch", ("torch",)),
    ("torchrl", ("torchrl",)),
    ("tensordict", ("tensordict",)),
    ("mani-skill", ("mani_skill", "mani-skill")),
    ("sapien", ("sapien",)),
    ("numpy", ("numpy",)),
    ("mplib", ("mplib",)),
)

#: Longest detail shown in the table (the JSON output keeps the full text).
_DETAIL_WIDTH = 100


@dataclass(frozen=True)
class CheckResult:
    """The result of one check.

    Attributes:
        name: short name of the check (the table's first column).
        ok: whether the check passed.
        detail: what was found (a version, a device, a timing, an error).
        fix: one sentence saying how to fix a failure; empty when ``ok``.
    """

    name: str
    ok: bool
    detail: str
    fix: str = ""


class Outcome(NamedTuple):
    """What a check function returns; :func:`run_checks` adds the name."""

    ok: bool
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class Check:
    """A named check, and the fix to print when it raises instead of returning."""

    name: str
    func: Callable[[], Outcome]
    fix_on_error: str = f"{SETUP_FIX[0].upper()}{SETUP_FIX[1:]}, then rerun mmada-rl doctor."


# --------------------------------------------------------------------------- helpers


def _vulkan_fix() -> str:
    """The first sentence of :data:`~mmada_rl.envs.vulkan.VULKAN_FIX`, plus what to run."""
    try:
        from mmada_rl.envs.vulkan import VULKAN_FIX

        first = VULKAN_FIX.split(". ")[0].rstrip(".")
    except Exception:  # noqa: BLE001 - the fix text must never fail
        first = "SAPIEN found no usable Vulkan device"
    return f"{first}: run scripts/setup.sh as root (it installs Mesa 25 from Debian's bookworm-backports)."


def _installed_version(dist_names: tuple[str, ...]) -> str | None:
    """The installed version of the first of ``dist_names`` that is installed, else ``None``."""
    for name in dist_names:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return None


@lru_cache(maxsize=1)
def _project_requirements() -> tuple[str | None, dict]:
    """``(requires_python, {canonical name: Requirement})`` of mmada_rl itself.

    Read from the installed package's metadata, or from ``pyproject.toml`` next to
    the source tree when the package is not installed. Empty when neither is
    readable or ``packaging`` is missing (the version checks then only report).
    """
    try:
        from packaging.requirements import Requirement
        from packaging.utils import canonicalize_name
    except ImportError:
        return None, {}
    try:
        dist = metadata.distribution("mmada_rl")
        requires_python, lines = dist.metadata.get("Requires-Python"), dist.requires or []
    except metadata.PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        try:
            project = tomllib.loads(pyproject.read_text())["project"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return None, {}
        requires_python, lines = project.get("requires-python"), project.get("dependencies", [])
    requirements = {}
    for line in lines:
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate({"extra": ""}):
            requirements[canonicalize_name(req.name)] = req
    return requires_python, requirements


def _requirement(dist_name: str):
    """mmada_rl's requirement on ``dist_name`` (a ``packaging`` Requirement), or ``None``."""
    _, requirements = _project_requirements()
    if not requirements:
        return None
    from packaging.utils import canonicalize_name

    return requirements.get(canonicalize_name(dist_name))


def _first_line(text: str) -> str:
    """The first non-empty line of an error message, trimmed."""
    lines = [line.strip() for line in str(text).strip().splitlines() if line.strip()]
    return lines[0] if lines else ""


# --------------------------------------------------------------------------- checks


def check_python() -> Outcome:
    """The interpreter version, against the project's ``requires-python``."""
    version = platform.python_version()
    spec, _ = _project_requirements()
    if spec:
        from packaging.specifiers import SpecifierSet

        if not SpecifierSet(spec).contains(version, prereleases=True):
            return Outcome(
                False,
                f"{version} (mmada_rl needs {spec})",
                f"Python {version} is not supported: create the virtual environment with python3.11 "
                "(scripts/setup.sh does).",
            )
    return Outcome(True, f"{version} ({sys.executable})")


def check_package(label: str, dist_names: tuple[str, ...]) -> Outcome:
    """Whether ``label`` is installed, and in a version mmada_rl accepts."""
    version = _installed_version(dist_names)
    if version is None:
        return Outcome(False, "not installed", f"{label} is missing: {SETUP_FIX}.")
    req = _requirement(dist_names[0])
    if req is not None and req.specifier and not req.specifier.contains(version, prereleases=True):
        if label == "torch":
            fix = "Install the CPU wheel first: pip install torch==2.13.0 (then scripts/setup.sh)."
        else:
            fix = f'{label} {version} does not satisfy {req.specifier}: pip install "{req}".'
        return Outcome(False, f"{version} (mmada_rl needs {req.specifier})", fix)
    return Outcome(True, version)


def check_numpy_below_2() -> Outcome:
    """numpy must be 1.x: mplib 0.1.1, the motion planner, segfaults under numpy 2."""
    version = _installed_version(("numpy",))
    if version is None:
        return Outcome(False, "numpy is not installed", f"numpy is missing: {SETUP_FIX}.")
    if int(version.split(".")[0]) >= 2:
        return Outcome(False, f"numpy {version}", 'mplib 0.1.1 segfaults under numpy 2: pip install "numpy<2".')
    return Outcome(True, f"numpy {version}")


def check_vulkan() -> Outcome:
    """The Vulkan device SAPIEN reports as supported (it needs one even without cameras)."""
    from mmada_rl.envs.vulkan import supported_device_name

    name = supported_device_name()
    if name is None:
        return Outcome(False, "SAPIEN sees no supported Vulkan device", _vulkan_fix())
    return Outcome(True, name)


def _image_problem(image, size: int) -> str | None:
    """Why ``image`` is not a rendered ``uint8 (3, size, size)`` frame, or ``None`` when it is."""
    import numpy as np

    if image is None:
        return "the observation has no 'camera' entry"
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != (3, size, size):
        return f"the camera image is {image.dtype} {tuple(image.shape)}, expected uint8 (3, {size}, {size})"
    if not image.any():
        return "the camera image is all zeros (nothing was rendered)"
    return None


def check_render() -> Outcome:
    """Build a ManiSkill task with a camera, reset it and check one RGB frame."""
    from mmada_rl.envs.maniskill import EnvConfig, make_gym_env
    from mmada_rl.envs.vulkan import VulkanUnavailableError, is_render_device_error

    start = time.perf_counter()
    try:
        env = make_gym_env(EnvConfig(task=RENDER_TASK, obs_mode="rgb", image_size=RENDER_SIZE))
        try:
            obs, _ = env.reset(seed=RENDER_SEED)
        finally:
            env.close()
    except Exception as err:  # noqa: BLE001 - SAPIEN's device errors get the Vulkan fix
        # "vk::" and "incompatibledriver" also catch Vulkan-loader errors without the word "Vulkan".
        text = str(err).lower()
        if (
            isinstance(err, VulkanUnavailableError)
            or is_render_device_error(err)
            or any(needle in text for needle in ("vk::", "incompatibledriver"))
        ):
            return Outcome(False, f"{RENDER_TASK} cannot render: {_first_line(str(err))}", _vulkan_fix())
        raise
    seconds = time.perf_counter() - start
    image = obs.get("camera") if isinstance(obs, dict) else None
    problem = _image_problem(image, RENDER_SIZE)
    if problem:
        return Outcome(
            False,
            f"{RENDER_TASK}: {problem}",
            "SAPIEN built the scene but rendered no usable frame: check the driver with "
            "`vulkaninfo --summary` (package vulkan-tools) and rerun scripts/setup.sh as root.",
        )
    return Outcome(True, f"{RENDER_TASK} {RENDER_SIZE}x{RENDER_SIZE} RGB frame in {seconds:.1f} s")


#: Imported by the motion-planner check, in a child process.
_PLANNER_IMPORT = (
    "import mplib\n"
    "from mani_skill.examples.motionplanning.panda.solutions import solvePickCube\n"
)


def check_motion_planner() -> Outcome:
    """Whether mplib and ManiSkill's panda motion-planning solutions import.

    Runs in a child process: mplib is a C++ extension, and a crash there (as under
    numpy 2) must not take the doctor down with it.
    """
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run(
        [sys.executable, "-c", _PLANNER_IMPORT], capture_output=True, text=True, timeout=300, env=env
    )
    if proc.returncode == 0:
        return Outcome(True, "mplib and solvePickCube import")
    if proc.returncode < 0:
        detail = f"importing mplib crashed the interpreter (signal {-proc.returncode})"
    else:
        errors = [line for line in proc.stderr.strip().splitlines() if line.strip()]
        detail = errors[-1].strip() if errors else f"exit status {proc.returncode}"
    numpy_version = _installed_version(("numpy",)) or "0"
    if int(numpy_version.split(".")[0]) >= 2:
        fix = 'mplib 0.1.1 segfaults under numpy 2: pip install "numpy<2".'
    else:
        fix = f'The motion planner does not import: pip install "mplib==0.1.1" or {SETUP_FIX}.'
    return Outcome(False, detail, fix)


def _checks() -> list[Check]:
    """All checks, in report order (built at call time so tests can replace one)."""
    checks = [Check("python", check_python)]
    for label, dist_names in PACKAGES:
        checks.append(Check(label, lambda label=label, names=dist_names: check_package(label, names)))
    checks += [
        Check("numpy<2", check_numpy_below_2),
        Check("vulkan", check_vulkan, _vulkan_fix()),
        Check(
            "render",
            check_render,
            f"Building and rendering {RENDER_TASK} failed: rerun scripts/setup.sh (as root on a fresh machine), "
            "then mmada-rl doctor.",
        ),
        Check("motion planner", check_motion_planner),
    ]
    return checks


def check_names() -> list[str]:
    """The names of all checks, in report order."""
    return [check.name for check in _checks()]


@contextlib.contextmanager
def _stdout_to_stderr() -> Iterator[None]:
    """Send what the checks print (Python and C++ code alike) to stderr.

    Keeps stdout for the report, so ``--json`` output stays parseable.
    """
    sys.stdout.flush()
    try:
        out_fd, err_fd = sys.stdout.fileno(), sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # not real files (e.g. captured)
        out_fd = err_fd = None
    saved = os.dup(out_fd) if out_fd is not None else None
    try:
        if saved is not None:
            os.dup2(err_fd, out_fd)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        if saved is not None:
            os.dup2(saved, out_fd)
            os.close(saved)


def run_checks() -> list[CheckResult]:
    """Run every check; a check that raises becomes a failed result, never a crash."""
    results = []
    with _stdout_to_stderr():
        for check in _checks():
            try:
                ok, detail, fix = check.func()
            except Exception as err:  # noqa: BLE001 - report, don't crash
                message = _first_line(str(err))
                ok, detail, fix = False, f"{type(err).__name__}: {message}" if message else type(err).__name__, check.fix_on_error
            results.append(CheckResult(check.name, bool(ok), detail, "" if ok else fix))
    return results


# --------------------------------------------------------------------------- report


def _shorten(text: str, width: int = _DETAIL_WIDTH) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= width else text[: width - 3] + "..."


def format_table(results: list[CheckResult]) -> str:
    """The results as an aligned plain-text table, then one fix line per failure."""
    rows = [("check", "status", "detail")]
    rows += [(r.name, "ok" if r.ok else "FAIL", _shorten(r.detail)) for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(2)]
    lines = [f"{name:<{widths[0]}}  {status:<{widths[1]}}  {detail}".rstrip() for name, status, detail in rows]
    lines.insert(1, f"{'-' * widths[0]}  {'-' * widths[1]}  {'-' * len('detail')}")
    failed = [r for r in results if not r.ok]
    if failed:
        lines += ["", f"{len(failed)} check(s) failed. Fixes:"]
        lines += [f"  {r.name}: {r.fix}" for r in failed]
    else:
        lines += ["", "All checks passed."]
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Run the checks and print the report; 1 if any check failed, else 0."""
    results = run_checks()
    if getattr(args, "json", False):
        report = {"ok": all(r.ok for r in results), "checks": [asdict(r) for r in results]}
        print(json.dumps(report, indent=2))
    else:
        print(format_table(results))
    return 0 if all(r.ok for r in results) else 1


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    parser.set_defaults(func=main)


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``doctor`` sub-command."""
    parser = subparsers.add_parser(
        "doctor",
        help="check the installation (packages, Vulkan device, rendering, motion planner) and say how to fix it",
        description="Check that this machine can run mmada_rl: package versions, numpy < 2, the Vulkan "
        "device SAPIEN renders with, one rendered ManiSkill frame, and the motion planner. "
        "Exits 1 if any check fails, printing one fix per failure.",
    )
    _add_arguments(parser)
    return parser


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(prog="python -m mmada_rl.doctor", description=__doc__.splitlines()[0])
    _add_arguments(_parser)
    sys.exit(main(_parser.parse_args()))
