#!/usr/bin/env bash
# Set up (or check) everything mmada_rl needs on a Debian 12 machine:
#   1. a Python 3.11 virtual environment (default: <repo>/.venv; override with MMADA_RL_VENV),
#   2. torch 2.13.0 (the CPU wheel) before anything else,
#   3. this package and its test extras (pip install -e ".[test]"),
#   4. a Vulkan device SAPIEN accepts (Mesa 25 from bookworm-backports).
#
# Idempotent: a second run only checks (a second or two). Steps that need root
# (Debian packages) run only as root; otherwise the script says what to run.
#
# Environment variables:
#   MMADA_RL_VENV            virtual environment location (default: <repo>/.venv)
#   MMADA_RL_PYTHON          interpreter that creates it (default: python3.11)
#   MMADA_RL_FAKE_NO_VULKAN  set to 1 to make the Vulkan check report no device
#                            (exercises the no-device branches in tests)
#
# The functions below can be sourced (`source scripts/setup.sh`) without running
# anything; executing the file runs `main`.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${MMADA_RL_VENV:-$REPO/.venv}"
[[ "$VENV" == /* ]] || VENV="$PWD/$VENV"  # functions below run commands from other folders
PYTHON="${MMADA_RL_PYTHON:-python3.11}"
TORCH_SPEC="torch==2.13.0"
STAMP="$VENV/.mmada_rl-install.sha256"
APT_UPDATED=0

log() { echo "[setup] $*"; }
die() { echo "[setup] error: $*" >&2; exit 1; }
is_root() { [[ "$(id -u)" -eq 0 ]]; }

#: apt-get update once per run, then install the given packages.
apt_install() {
    if [[ "$APT_UPDATED" -eq 0 ]]; then
        DEBIAN_FRONTEND=noninteractive apt-get update
        APT_UPDATED=1
    fi
    DEBIAN_FRONTEND=noninteractive apt-get install -y "$@"
}

#: Make sure $PYTHON exists and can create virtual environments.
ensure_python() {
    if command -v "$PYTHON" >/dev/null 2>&1 && "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1; then
        return 0
    fi
    if ! is_root; then
        die "$PYTHON with the venv module is missing; as root run: apt-get install -y python3.11 python3.11-venv"
    fi
    log "installing python3.11 and python3.11-venv (apt)"
    apt_install python3.11 python3.11-venv ca-certificates
    "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1 \
        || die "$PYTHON still cannot create virtual environments after installing python3.11-venv"
}

#: Create the virtual environment if it does not exist yet.
ensure_venv() {
    if [[ -x "$VENV/bin/python" ]]; then
        return 0
    fi
    ensure_python
    log "creating virtual environment $VENV"
    "$PYTHON" -m venv "$VENV"
}

#: Install the CPU torch wheel first: with no torch present, resolving the
#: package's requirements would pull a multi-GB CUDA build instead.
ensure_torch() {
    local version
    if version="$("$VENV/bin/python" -c 'import importlib.metadata as m; print(m.version("torch"))' 2>/dev/null)"; then
        log "torch $version already installed"
        return 0
    fi
    log "installing $TORCH_SPEC (CPU wheel) before anything else"
    "$VENV/bin/python" -m pip install "$TORCH_SPEC"
}

#: The stamp content: the sha256 of pyproject.toml (and its path).
pyproject_digest() {
    sha256sum "$REPO/pyproject.toml"
}

#: pip install -e ".[test]" unless the stamp says this pyproject.toml is installed.
ensure_package() {
    if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$(pyproject_digest)" ]]; then
        log "mmada_rl already installed (pyproject.toml unchanged)"
        return 0
    fi
    log "installing mmada_rl and its test extras (pip install -e \".[test]\")"
    "$VENV/bin/python" -m pip install -e "$REPO[test]"
    pyproject_digest >"$STAMP"
}

#: Print the name of the Vulkan device SAPIEN accepts, or nothing; fail if the check cannot run.
vulkan_device() {
    if [[ "${MMADA_RL_FAKE_NO_VULKAN:-0}" == "1" ]]; then
        return 0
    fi
    local out err
    err="$(mktemp)"
    if ! out="$(cd "$REPO" && "$VENV/bin/python" -c \
        'from mmada_rl.envs.vulkan import supported_device_name; print(supported_device_name() or "")' \
        2>"$err")"; then
        tail -n 5 "$err" >&2
        rm -f "$err"
        die "the Vulkan check could not run in $VENV (error above); rerun scripts/setup.sh after fixing it"
    fi
    rm -f "$err"
    printf '%s\n' "$out" | tail -n 1
}

#: The project's own explanation of how to get a Vulkan device.
vulkan_fix_text() {
    (cd "$REPO" && "$VENV/bin/python" -c 'from mmada_rl.envs.vulkan import VULKAN_FIX; print(VULKAN_FIX)' 2>/dev/null) \
        || echo "SAPIEN found no usable Vulkan device: install mesa-vulkan-drivers and libvulkan1 from bookworm-backports as root."
}

#: Install Mesa 25 (lavapipe) from bookworm-backports (root, Debian 12 only).
install_mesa() {
    local codename
    codename="$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-unknown}")" || codename="unknown"
    if [[ "$codename" != "bookworm" ]]; then
        vulkan_fix_text >&2
        die "automatic Mesa installation supports Debian 12 (bookworm) only; this system is '$codename'"
    fi
    log "installing Mesa 25 (mesa-vulkan-drivers, libvulkan1) from bookworm-backports"
    local sources=/etc/apt/sources.list.d/backports.sources suite
    suite="Types: deb
URIs: http://deb.debian.org/debian
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg"
    if [[ ! -f "$sources" || "$(cat "$sources")" != "$suite" ]]; then
        log "adding the bookworm-backports suite ($sources)"
        printf '%s\n' "$suite" >"$sources"
    fi
    APT_UPDATED=0  # the suite may be new: refresh the package lists
    apt_install -t bookworm-backports mesa-vulkan-drivers libvulkan1
}

#: Make sure SAPIEN sees a supported Vulkan device; install Mesa as root if not.
ensure_vulkan() {
    local device
    device="$(vulkan_device)" || exit 1
    if [[ -n "$device" ]]; then
        log "Vulkan device: $device"
        return 0
    fi
    if ! is_root; then
        vulkan_fix_text >&2
        die "no Vulkan device SAPIEN accepts; run the commands above as root, or run scripts/setup.sh as root"
    fi
    install_mesa
    device="$(vulkan_device)" || exit 1
    if [[ -z "$device" ]]; then
        vulkan_fix_text >&2
        die "SAPIEN still sees no supported Vulkan device after installing Mesa; run 'vulkaninfo --summary' (package vulkan-tools) to see why"
    fi
    log "Vulkan device: $device"
}

#: Compute SAPIEN's BRDF look-up table once for this machine, so that no process that renders computes it
#: (mmada_rl/envs/brdf_lut.py: ~6 s the first time, read from the cache after).
ensure_brdf_lut() {
    local path
    path="$(cd "$REPO" && "$VENV/bin/python" -c \
        'from mmada_rl.envs.brdf_lut import brdf_lut, cache_path; brdf_lut(); print(cache_path())')" \
        || die "could not compute the BRDF look-up table (error above)"
    log "BRDF look-up table: $path"
}

main() {
    log "repository $REPO, virtual environment $VENV"
    ensure_venv
    ensure_torch
    ensure_package
    ensure_vulkan
    ensure_brdf_lut
    log "done"
}

if [[ "${BASH_SOURCE[0]}" == "$0" ]]; then
    main "$@"
fi
