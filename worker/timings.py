"""Where a job's time goes in the worker: seconds per step of one attempt, logged as one line per attempt
(``benchmarks/throughput.py`` reads them; so can an operator's log search)."""

from __future__ import annotations

import json
import time
from typing import Any

from core.logsafe import safe_logger

log = safe_logger("bonemesh.worker")


class Timings:
    """Seconds per step of one attempt, each from the end of the step before (they add up to ``total``), logged
    as one line ``job <id> timings {json}`` when the attempt ends (``benchmarks/throughput.py`` reads it)."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step] = self.seconds.get(step, 0.0) + now - self.last
        self.last = now

    def log(self, job: Any) -> None:
        seconds = {**self.seconds, "total": time.perf_counter() - self.start}
        if getattr(job, "created_at", None) and getattr(job, "started_at", None):  # upload recorded -> claimed
            seconds["queue_wait"] = (job.started_at - job.created_at).total_seconds()
        log.info("job %s timings %s", job.id, json.dumps({k: round(v, 4) for k, v in seconds.items()}))
