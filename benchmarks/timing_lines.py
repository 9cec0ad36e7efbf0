"""The services' own timing lines in their logs, by job id: the worker's ``job <id> timings {json}``
(``worker.tasks``) and the API's ``job <id> upload timings {json}`` (``service.intake``). Read by
``benchmarks.service`` and ``benchmarks.throughput``."""

from __future__ import annotations

import json
import re

from tests.service.procs import Proc, ServiceStack

TIMINGS = re.compile(r"job (\S+) timings (\{.*\})")  # the worker's line per attempt (worker.tasks._Timings)
UPLOAD_TIMINGS = re.compile(r"job (\S+) upload timings (\{.*\})")  # the API's line per upload (service.intake)


def worker_timings(workers: list[Proc]) -> dict[str, tuple[int, dict[str, float]]]:
    """The workers' lines by job id: (worker index, seconds per step); a job run twice keeps its last attempt."""
    found: dict[str, tuple[int, dict[str, float]]] = {}
    for index, w in enumerate(workers):
        for match in TIMINGS.finditer(w.log.read_text(errors="replace")):
            found[match.group(1)] = (index, json.loads(match.group(2)))
    return found


def api_timings(stack: ServiceStack) -> dict[str, dict[str, float]]:
    """The API's lines by job id: the upload's seconds per step on the API's clock (opening, the body received and
    written, the fsync, the inspection, the decoder's end, the record)."""
    found: dict[str, dict[str, float]] = {}
    for log in sorted(stack.log_dir.glob("server-*.log")):
        for match in UPLOAD_TIMINGS.finditer(log.read_text(errors="replace")):
            found[match.group(1)] = json.loads(match.group(2))
    return found
