#!/usr/bin/env bash
# Set up (virtual environment with the test extras, system libraries, redis-server), then run every test on CPU.
# PYTHON (default python3) and VENV (default .venv) pick the interpreter and the environment (scripts/_setup.sh).
set -ex
cd "$(dirname "$0")/.."
BONEMESH_EXTRAS="[test]"
source scripts/_setup.sh
"$VENV/bin/python" -m pytest -q "$@"
