#!/usr/bin/env bash
# Set everything up with scripts/setup.sh, then run `mmada-rl quickstart`
# with the given arguments (`scripts/quickstart.sh --help` lists them).
#
# Usage: scripts/quickstart.sh [mmada-rl quickstart arguments...]
#   scripts/quickstart.sh --help
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${MMADA_RL_VENV:-$REPO/.venv}"
[[ "$VENV" == /* ]] || VENV="$PWD/$VENV"

bash "$REPO/scripts/setup.sh"
cd "$REPO"
exec "$VENV/bin/mmada-rl" quickstart "$@"
