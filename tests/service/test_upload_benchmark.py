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
