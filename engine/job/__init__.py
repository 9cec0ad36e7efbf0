"""A job, as every edge runs it: its specification (``JobSpec``: parameters, input, outputs; validated once), the
runtime it runs on (``Runtime``: backend, device, budget, decoders; resolved once), and ``run_job`` (the plan, the
stages and the files). The worker and the CLI are thin callers of ``run_job``.

This package is also the job runner's one public face (the worker imports the engine through it and
``engine.errors``): the output registry's names (``FILES``, ``triangle_count``, ...), the warm-up (re-orientation:
``engine.job.reorient``), and the PACS's DICOM encodings of a model (``to_encapsulated_stl``, ``from_stl``,
``is_seg_file``, ``referenced_series``).

Importing this package loads none of its modules (``engine._lazy``); ``engine.job.spec`` never loads Warp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.budget import mib, parse_bytes
    from engine.export.dicom_stl import to_encapsulated_stl
    from engine.export.files import FILES, LABELS_DCM, LABELS_ZIP, MODEL_DCM, PRINT_STL, triangle_count
    from engine.export.stl import from_stl
    from engine.job.run import JobResult, run_job
    from engine.job.runtime import Runtime, resolve_runtime
    from engine.job.spec import InputSpec, JobSpec, OutputSpec
    from engine.job.warmup import warm_up
    from engine.labels.dicom_seg import referenced_series
    from engine.labels.uploads import is_seg_file
    from engine.params import OrientParams
    from engine.types import Volume

__all__ = [
    "FILES",
    "LABELS_DCM",
    "LABELS_ZIP",
    "MODEL_DCM",
    "PRINT_STL",
    "InputSpec",
    "JobResult",
    "JobSpec",
    "OrientParams",
    "OutputSpec",
    "Runtime",
    "Volume",
    "from_stl",
    "is_seg_file",
    "mib",
    "parse_bytes",
    "referenced_series",
    "resolve_runtime",
    "run_job",
    "to_encapsulated_stl",
    "triangle_count",
    "warm_up",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "FILES": "engine.export.files",
        "LABELS_DCM": "engine.export.files",
        "LABELS_ZIP": "engine.export.files",
        "MODEL_DCM": "engine.export.files",
        "PRINT_STL": "engine.export.files",
        "triangle_count": "engine.export.files",
        "InputSpec": "engine.job.spec",
        "JobSpec": "engine.job.spec",
        "OutputSpec": "engine.job.spec",
        "JobResult": "engine.job.run",
        "run_job": "engine.job.run",
        "Runtime": "engine.job.runtime",
        "resolve_runtime": "engine.job.runtime",
        "OrientParams": "engine.params",
        "Volume": "engine.types",
        "from_stl": "engine.export.stl",
        "to_encapsulated_stl": "engine.export.dicom_stl",
        "is_seg_file": "engine.labels.uploads",
        "referenced_series": "engine.labels.dicom_seg",
        "mib": "engine.budget",
        "parse_bytes": "engine.budget",
        "warm_up": "engine.job.warmup",
    },
)
