#!/usr/bin/env bash
# Set up a virtual environment with the project and its test extras, then run the whole test suite (CPU).
set -ex
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
# MeshLab (pymeshlab, the decimation) needs the system's OpenGL loader; install it where a slim image lacks it
if ! .venv/bin/python -c "import pymeshlab" 2>/dev/null && command -v apt-get >/dev/null; then
  apt-get update -qq && apt-get install -y -qq libgl1 libglib2.0-0 >/dev/null
fi
.venv/bin/python -m pytest -q "$@"
