#!/usr/bin/env bash
# Set up, then run the product on one machine: Redis, the API (http://127.0.0.1:8000) and a worker (GPU when
# present, else CPU); upload the bundled CT head (VTK headsq) over HTTP, wait for the job, print the download
# links (model.stl in mm, model.glb, phone.glb with Draco, ar.glb, report.json). Ctrl-C or kill -TERM stops
# everything; the data go to ~/.cache/bonemesh-demo (--data-dir DIR to change it), not into the repository.
# The terminal shows the demo's lines only: the worker's output (Celery's banner and log) goes to worker.log in
# the data folder (service/demo.py says why).
set -e
cd "$(dirname "$0")/.."
source scripts/_setup.sh
exec "$VENV/bin/python" -m service.demo "$@"
