"""``benchmarks/upload.py`` runs end to end on a small archive (real redis-server and API processes), so the
benchmark the H100 host runs does not rot between GPU sessions."""

from __future__ import annotations

import json
from pathlib import Path


def test_upload_benchmark_times_both_servers(tmp_path: Path) -> None:
    from benchmarks.upload import main
    from tests.service.procs import REPO

    out = tmp_path / "upload.json"
    args = ["--phantom", "8,64,64", "--repeat", "2", "--clients", "httpx", "--baseline", str(REPO)]
    assert main([*args, "--workdir", str(tmp_path / "work"), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    entry = result["clients"]["httpx"]
    assert result["input"]["archive_bytes"] > 0
    for label in ("current", "baseline"):
        assert len(entry[label]["seconds"]) == 2 and entry[label]["median_mb_per_s"] > 0
    assert entry["speedup"] > 0


def test_upload_benchmark_compares_settings_side_by_side(tmp_path: Path) -> None:
    """``--compare-env`` (a second server of this code with other settings) and ``--side-by-side`` (POSTs at once):
    every POST of every round timed, each round's wall time kept."""
    from benchmarks.upload import main

    out = tmp_path / "upload.json"
    args = ["--phantom", "8,64,64", "--repeat", "2", "--clients", "httpx", "--side-by-side", "3"]
    args += ["--compare-env", "BONEMESH_PREDECODE_MIN_BYTES=0"]
    assert main([*args, "--workdir", str(tmp_path / "work"), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["compare_env"] == {"BONEMESH_PREDECODE_MIN_BYTES": "0"} and result["side_by_side"] == 3
    entry = result["clients"]["httpx"]
    for label in ("current", "compare"):
        assert len(entry[label]["seconds"]) == 6 and len(entry[label]["round_seconds"]) == 2
        assert max(entry[label]["seconds"]) <= max(entry[label]["round_seconds"])
    assert entry["compare_over_current"] > 0
