"""mypy --strict over the engine's public API (``scripts/typecheck.sh``); skipped where mypy is not installed."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None, reason="needs mypy (pip install mypy)")
def test_the_public_api_type_checks_strictly():
    out = subprocess.run(["bash", "scripts/typecheck.sh"], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
