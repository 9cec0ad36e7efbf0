"""Writing a benchmark's JSON result, and the process's memory as Linux reports it."""

from __future__ import annotations

import json
import signal
from pathlib import Path
from typing import Any

import numpy as np


def _json_default(obj: Any) -> Any:
    return obj.item() if isinstance(obj, np.generic) else str(obj)


def write_json(path: Path, report: dict[str, Any]) -> None:
    """``report`` as indented JSON at ``path`` (its folder made; numpy scalars as numbers, anything else as text)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=_json_default) + "\n")


def stop_on_sigterm() -> None:
    """SIGTERM (``timeout``) exits through ``SystemExit``, so the benchmark's with-blocks stop every process it
    started and the JSON written so far stays."""

    def _exit(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _exit)


def proc_status(key: str) -> int:
    """A size in bytes from ``/proc/self/status`` (``VmRSS``: resident now, ``VmHWM``: its high-water mark)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)
