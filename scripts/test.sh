#!/usr/bin/env bash
# Set up (virtual environment with the test extras, system libraries, redis-server), then run every test on CPU.
set -ex
cd "$(dirname "$0")/.."
BONEMESH_EXTRAS="[test]"
source scripts/_setup.sh
.venv/bin/python -m pytest -q "$@"
