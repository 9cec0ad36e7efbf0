#!/usr/bin/env bash
# Set up a virtual environment with the project, then run the EMC33 pipeline on the bundled CT head (VTK headsq):
# out/headsq/ gets model.stl (watertight, mm), model.glb, phone.glb (Draco), ar.glb and report.json.
set -ex
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e .
.venv/bin/bonemesh reconstruct --demo -o out/headsq "$@"
