"""Writing a benchmark's JSON result."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _json_default(obj: Any) -> Any:
    return obj.item() if isinstance(obj, np.generic) else str(obj)


def write_json(path: Path, report: dict[str, Any]) -> None:
    """``report`` as indented JSON at ``path`` (its folder made; numpy scalars as numbers, anything else as text)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=_json_default) + "\n")
