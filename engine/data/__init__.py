"""Bundled sample scans (see README.md for sources and licences)."""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
HEADSQ_ZIP = DATA_DIR / "headsq_png16.zip"
HEADSQ_SPACING_ZYX_MM = (1.5, 3.2, 3.2)
HEADSQ_BONE_LEVEL = 1150.5  # between integer samples: no ties (the isosurface demo)
HEADSQ_LEVEL = 1150.0  # the bone level of VTK's examples (reconstruct and sweep demos)
HEADSQ_FIRST_SLICE = "superior"  # slice 0 is the top of the head (engine.params.OrientParams.first_slice)
