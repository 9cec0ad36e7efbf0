"""The committed OpenAPI document is the app's, and the API process never imports Warp or the worker."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service.openapi import DEFAULT, render

ROOT = Path(__file__).resolve().parents[2]


def test_committed_openapi_matches_the_app() -> None:
    assert DEFAULT.read_text() == render(), "openapi/openapi.json is out of date: run python -m service.openapi"


def test_the_api_and_the_worker_parent_never_import_warp() -> None:
    """Warp (CUDA) must start in the worker's pool child, after the fork, never in the API or the worker parent."""
    code = (
        "import sys, service.app, service.cli, worker.app, worker.tasks; "
        "print(sorted(m for m in sys.modules if m == 'warp' or m.startswith(('warp.', 'worker')) and 'service' in m))"
        "; print('warp' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False", out.stdout + out.stderr
    code = "import sys, service.app; print(any(m == 'worker' or m.startswith('worker.') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", "the API imports the worker"
