"""``mmada-rl doctor`` and the set-up scripts."""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from mmada_rl import doctor
from mmada_rl.doctor import Outcome

BASH = shutil.which("bash")
SCRIPTS = ("scripts/setup.sh", "scripts/test.sh", "scripts/quickstart.sh", ".ci/run")


# --------------------------------------------------------------------------- the real doctor


@pytest.fixture(scope="module")
def doctor_table(run_cli):
    """``mmada-rl doctor`` on this machine (runs the real simulator and planner)."""
    return run_cli("doctor")


@pytest.fixture(scope="module")
def doctor_json(run_cli):
    """``mmada-rl doctor --json`` on this machine."""
    return run_cli("doctor", "--json")


@pytest.mark.slow
def test_doctor_passes_and_names_every_check(doctor_table):
    proc = doctor_table
    assert proc.returncode == 0, f"doctor failed:\n{proc.stdout}\n{proc.stderr}"
    for name in doctor.check_names():
        assert name in proc.stdout, f"check {name!r} missing from the table:\n{proc.stdout}"
    assert "All checks passed." in proc.stdout
    assert "FAIL" not in proc.stdout


@pytest.mark.slow
def test_doctor_json_parses(doctor_json):
    proc = doctor_json
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["ok"] is True
    assert [c["name"] for c in report["checks"]] == doctor.check_names()
    for check in report["checks"]:
        assert set(check) == {"name", "ok", "detail", "fix"}
        assert check["ok"] is True and check["detail"]


# --------------------------------------------------------------------------- in-process, with fakes


@pytest.fixture
def fast_checks(monkeypatch):
    """Replace the slow checks (device, simulator, planner subprocess) by instant passes."""
    monkeypatch.setattr(doctor, "check_vulkan", lambda: Outcome(True, "fake device"))
    monkeypatch.setattr(doctor, "check_render", lambda: Outcome(True, "fake frame"))
    monkeypatch.setattr(doctor, "check_motion_planner", lambda: Outcome(True, "fake planner"))


def test_failing_check_returns_1_and_prints_its_fix(fast_checks, monkeypatch, capsys):
    fix = 'mplib 0.1.1 segfaults under numpy 2: pip install "numpy<2".'
    monkeypatch.setattr(doctor, "check_numpy_below_2", lambda: Outcome(False, "numpy 2.1.0", fix))

    assert doctor.main(argparse.Namespace(json=False)) == 1

    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("numpy<2"))
    assert "FAIL" in row and "numpy 2.1.0" in row
    assert f"numpy<2: {fix}" in out
    assert "1 check(s) failed" in out


def test_all_passing_returns_0(fast_checks, capsys):
    assert doctor.main(argparse.Namespace(json=False)) == 0
    assert "All checks passed." in capsys.readouterr().out


def test_raising_check_is_reported_not_raised(fast_checks, monkeypatch):
    def broken():
        raise RuntimeError("vk::createInstanceUnique: ErrorIncompatibleDriver\nmore lines")

    monkeypatch.setattr(doctor, "check_vulkan", broken)
    results = {r.name: r for r in doctor.run_checks()}

    assert list(results) == doctor.check_names()
    vulkan = results["vulkan"]
    assert not vulkan.ok
    assert vulkan.detail == "RuntimeError: vk::createInstanceUnique: ErrorIncompatibleDriver"
    assert "run scripts/setup.sh as root" in vulkan.fix
    assert all(r.ok for name, r in results.items() if name != "vulkan")


def test_json_flag_prints_only_json(fast_checks, monkeypatch, capsys):
    monkeypatch.setattr(doctor, "check_render", lambda: Outcome(False, "blank frame", "Fix the renderer."))

    assert doctor.main(argparse.Namespace(json=True)) == 1

    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is False
    render = next(c for c in report["checks"] if c["name"] == "render")
    assert render == {"name": "render", "ok": False, "detail": "blank frame", "fix": "Fix the renderer."}


def test_missing_package_is_a_failure_with_a_fix():
    outcome = doctor.check_package("nonexistent-pkg", ("nonexistent_pkg_for_doctor_test",))
    assert not outcome.ok and outcome.detail == "not installed"
    assert "scripts/setup.sh" in outcome.fix


def test_table_columns_are_aligned():
    results = [
        doctor.CheckResult("python", True, "3.11.7"),
        doctor.CheckResult("motion planner", False, "x" * 500, "Do this."),
    ]
    lines = doctor.format_table(results).splitlines()
    status_column = lines[0].index("status")
    detail_column = lines[0].index("detail")
    for line in lines[2:4]:
        assert line[status_column:].split()[0] in {"ok", "FAIL"}
        assert line[detail_column - 2 : detail_column] == "  "
    assert len(lines[3]) < 200  # long details are shortened
    assert "  motion planner: Do this." in lines


# --------------------------------------------------------------------------- set-up scripts


def _venv_env() -> dict:
    """Environment that points the scripts at the virtual environment running these tests."""
    if sys.prefix == sys.base_prefix:
        pytest.skip("the set-up script tests need pytest to run inside a virtual environment")
    return {**os.environ, "MMADA_RL_VENV": sys.prefix}


def _source_setup(repo_root, body: str, **env) -> subprocess.CompletedProcess:
    """Source scripts/setup.sh (defines its functions, runs nothing) and run ``body`` after it.

    ``apt_install`` is replaced by a stub first, so no test ever touches the system's packages.
    """
    guard = 'apt_install() { echo "APT_INSTALL_CALLED $*"; return 99; }'
    script = f'source "{repo_root}/scripts/setup.sh"\n{guard}\n{body}\n'
    return subprocess.run(
        [BASH, "-c", script], capture_output=True, text=True, timeout=120, env={**_venv_env(), **env}
    )


@pytest.mark.parametrize("path", SCRIPTS)
def test_scripts_are_executable_bash(repo_root, path):
    script = repo_root / path
    assert os.access(script, os.X_OK), f"{path} is not executable: chmod +x {path}"
    subprocess.run([BASH, "-n", str(script)], check=True)


def test_setup_twice_is_quick_the_second_time(repo_root):
    env = _venv_env()
    runs = []
    for _ in range(2):
        start = time.perf_counter()
        proc = subprocess.run(
            [BASH, str(repo_root / "scripts/setup.sh")], capture_output=True, text=True, timeout=900, env=env
        )
        runs.append((proc, time.perf_counter() - start))
        assert proc.returncode == 0, f"setup.sh failed:\n{proc.stdout}\n{proc.stderr}"
    second, seconds = runs[1]
    assert seconds < 30, f"second setup.sh run took {seconds:.1f} s:\n{second.stdout}"
    assert "already installed" in second.stdout
    assert "installing" not in second.stdout.replace("already installed", "")
    assert "[setup] Vulkan device:" in second.stdout


def test_setup_vulkan_check_finds_this_machines_device(repo_root):
    proc = _source_setup(repo_root, "ensure_vulkan")
    assert proc.returncode == 0, proc.stderr
    assert "[setup] Vulkan device:" in proc.stdout


def test_setup_without_vulkan_as_user_prints_the_fix(repo_root):
    from mmada_rl.envs.vulkan import VULKAN_FIX

    body = "is_root() { return 1; }\ninstall_mesa() { echo INSTALL_MESA_CALLED; exit 3; }\nensure_vulkan"
    proc = _source_setup(repo_root, body, MMADA_RL_FAKE_NO_VULKAN="1")

    assert proc.returncode == 1
    assert VULKAN_FIX in proc.stderr
    assert "run scripts/setup.sh as root" in proc.stderr
    assert "INSTALL_MESA_CALLED" not in proc.stdout + proc.stderr


def test_setup_without_vulkan_as_root_installs_mesa_then_rechecks(repo_root):
    body = "is_root() { return 0; }\ninstall_mesa() { echo INSTALL_MESA_CALLED; }\nensure_vulkan"
    proc = _source_setup(repo_root, body, MMADA_RL_FAKE_NO_VULKAN="1")

    assert "INSTALL_MESA_CALLED" in proc.stdout
    assert proc.returncode == 1  # the fake still reports no device after the "install"
    assert "still sees no supported Vulkan device" in proc.stderr


def test_setup_reports_a_vulkan_check_that_cannot_run(repo_root, tmp_path):
    fake_python = tmp_path / "bin" / "python"
    fake_python.parent.mkdir()
    fake_python.write_text("#!/bin/sh\necho 'ImportError: broken install' >&2\nexit 1\n")
    fake_python.chmod(0o755)
    body = "is_root() { return 0; }\ninstall_mesa() { echo INSTALL_MESA_CALLED; }\nensure_vulkan"
    proc = _source_setup(repo_root, body, MMADA_RL_VENV=str(tmp_path))

    assert proc.returncode == 1
    assert "ImportError: broken install" in proc.stderr
    assert "the Vulkan check could not run" in proc.stderr
    assert "INSTALL_MESA_CALLED" not in proc.stdout
