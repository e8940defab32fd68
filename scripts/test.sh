#!/usr/bin/env bash
# Set up (idempotently) and run the whole test suite.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
# two test processes (pytest-xdist): the suite took 15 min on one process of a slow 2-core machine (session 80's
# CI), 7-9 on two (session 81); PYTEST_WORKERS sets another count (0: one process, no workers)
exec .venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" "$@"
