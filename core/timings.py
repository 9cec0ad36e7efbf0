"""Where a job's time goes: seconds per step, logged as one line (``job <id> timings {json}`` in the worker, per
attempt; ``job <id> upload timings {json}`` in the API, per upload). ``benchmarks/throughput.py`` and
``benchmarks/service.py`` read them; so can an operator's log search."""

from __future__ import annotations

import json
import logging
import time
from typing import Any


class Timings:
    """Seconds per step, each from the end of the step before (they add up to ``total``), logged by ``log`` as one
    line ``job <id> <what> {json}``."""

    def __init__(self, logger: logging.Logger, what: str = "timings") -> None:
        self.start = self.last = time.perf_counter()
        self.seconds: dict[str, float] = {}
        self.logger, self.what = logger, what

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step] = self.seconds.get(step, 0.0) + now - self.last
        self.last = now

    def log(self, job: Any) -> None:
        """The line for ``job`` (a record, or its id); with the record's times, its wait in the queue too."""
        seconds = {**self.seconds, "total": time.perf_counter() - self.start}
        if getattr(job, "created_at", None) and getattr(job, "started_at", None):  # upload recorded -> claimed
            seconds["queue_wait"] = (job.started_at - job.created_at).total_seconds()
        job_id = getattr(job, "id", job)
        self.logger.info("job %s %s %s", job_id, self.what, json.dumps({k: round(v, 4) for k, v in seconds.items()}))
