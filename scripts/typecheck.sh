#!/usr/bin/env bash
# mypy --strict on the engine's public API, its ground floor, the report's type (engine/report.py) and the registry
# of output files (engine/export/files.py) (issue 26). Warp and scikit-image have no type information: calls into
# them are not held to the untyped-call rule, and modules outside this list are read for their types but not
# reported (follow-imports=silent). Needs mypy in the virtual environment (the `test` extra installs it; the tests
# run this script: tests/engine/test_typecheck.py).
set -ex
cd "$(dirname "$0")/.."
"${VENV:-.venv}/bin/python" -m mypy --strict --follow-imports=silent --ignore-missing-imports \
    --untyped-calls-exclude=warp --untyped-calls-exclude=skimage \
    engine/__init__.py engine/_lazy.py engine/errors.py engine/types.py engine/params.py engine/budget.py \
    engine/device.py engine/backend/memory.py engine/level.py engine/orient.py engine/job/progress.py engine/staging.py engine/heap.py engine/isosurface/multi.py \
    engine/job/plans.py engine/job/pipeline.py engine/job/outputs.py engine/report.py engine/job/warmup.py engine/cli/__init__.py \
    engine/export/__init__.py engine/export/files.py engine/export/viewers.py \
    engine/volume/__init__.py engine/isosurface/__init__.py engine/decimation/__init__.py \
    engine/surface/__init__.py engine/paper/__init__.py \
    engine/defect/__init__.py engine/defect/params.py engine/defect/step.py engine/defect/template.py \
    engine/backend/__init__.py engine/backend/base.py engine/backend/select.py engine/backend/warp_backend.py \
    engine/backend/opencl_backend.py engine/io/png_rows.py engine/io/kernels/steps.py engine/io/zipstream.py \
    engine/io/predecode.py engine/io/predecode_proc.py \
    engine/job/__init__.py engine/job/spec.py engine/job/runtime.py engine/job/run.py engine/backend/warp_device.py \
    engine/cli/args.py
