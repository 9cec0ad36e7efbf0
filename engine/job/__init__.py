"""A job, as every edge runs it: its specification (``JobSpec``: parameters, input, outputs; validated once), the
runtime it runs on (``Runtime``: backend, device, budget, decoders; resolved once), and ``run_job`` (the plan, the
stages and the files). The worker and the CLI are thin callers of ``run_job``.

Importing this package loads none of its modules (``engine._lazy``); ``engine.job.spec`` never loads Warp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.job.run import JobResult, run_job
    from engine.job.runtime import Runtime, resolve_runtime
    from engine.job.spec import InputSpec, JobSpec, OutputSpec

__all__ = ["InputSpec", "JobResult", "JobSpec", "OutputSpec", "Runtime", "resolve_runtime", "run_job"]
__getattr__, __dir__ = attach(
    __name__,
    {
        "InputSpec": "engine.job.spec",
        "JobResult": "engine.job.run",
        "JobSpec": "engine.job.spec",
        "OutputSpec": "engine.job.spec",
        "Runtime": "engine.job.runtime",
        "resolve_runtime": "engine.job.runtime",
        "run_job": "engine.job.run",
    },
)
