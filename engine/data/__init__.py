"""Bundled sample scans (see README.md for sources and licences)."""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
HEADSQ_ZIP = DATA_DIR / "headsq_png16.zip"
HEADSQ_SPACING_ZYX_MM = (1.5, 3.2, 3.2)
HEADSQ_BONE_LEVEL = 1150.5
