#!/usr/bin/env bash
# Run the test suite: set everything up with scripts/setup.sh, then run pytest.
#
# Usage: scripts/test.sh [pytest arguments...]     (default: tests/)
#   scripts/test.sh                      # the whole suite
#   scripts/test.sh -m "not slow"        # skip the simulator/planner tests
#   scripts/test.sh tests/test_doctor.py
#   scripts/test.sh -n 0                 # in one process (pytest-xdist's -n: the last one given wins)
#
# The tests run in one pytest-xdist worker per core, each test file whole in one worker
# (its module-scoped fixtures built once; the session-scoped ones once per worker).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${MMADA_RL_VENV:-$REPO/.venv}"
[[ "$VENV" == /* ]] || VENV="$PWD/$VENV"

bash "$REPO/scripts/setup.sh"
cd "$REPO"
if [[ $# -eq 0 ]]; then
    set -- tests/
fi
exec "$VENV/bin/python" -m pytest -q --durations=15 -n auto --dist loadfile "$@"
