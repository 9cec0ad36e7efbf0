#!/usr/bin/env bash
# Set up a virtual environment with the project, then extract the bone surface of the bundled CT head
# (VTK headsq) with Marching Cubes 33 and write a watertight binary STL in millimetres.
set -ex
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e .
.venv/bin/bonemesh isosurface --demo -o out/headsq_bone.stl "$@"
