#!/usr/bin/env bash
# Set up a virtual environment with the project and its test extras, then run the whole test suite (CPU).
set -ex
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
.venv/bin/python -m pytest -q "$@"
