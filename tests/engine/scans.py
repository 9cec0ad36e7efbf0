"""Real scans for the engine tests: ../shared/data, except headsq, which ships in the package (engine/data)."""

from __future__ import annotations

from pathlib import Path

from engine.data import HEADSQ_ZIP
from tests.conftest import shared_file

BUNDLED = {("headsq_ct", "headsq_png16.zip"): HEADSQ_ZIP}


def scan_file(folder: str, name: str) -> Path:
    """The bundled copy when there is one, else the ../shared/data file (the test skips, saying so, if absent)."""
    return BUNDLED.get((folder, name)) or shared_file(folder, name)
