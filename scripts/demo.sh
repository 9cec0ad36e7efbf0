#!/usr/bin/env bash
# Set up a virtual environment with the project, then run the EMC33 pipeline on the bundled CT head (VTK headsq):
# out/headsq/ gets model.stl (watertight, mm), model.glb, phone.glb (Draco), ar.glb and report.json.
set -ex
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e .
# MeshLab (pymeshlab, the decimation) needs the system's OpenGL loader; install it where a slim image lacks it
if ! .venv/bin/python -c "import pymeshlab" 2>/dev/null && command -v apt-get >/dev/null; then
  apt-get update -qq && apt-get install -y -qq libgl1 libglib2.0-0 >/dev/null
fi
.venv/bin/bonemesh reconstruct --demo -o out/headsq "$@"
