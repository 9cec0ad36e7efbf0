"""The paper's wing: the parameter sweep of EMC33GPU against MC33, MC33GPU and GMC33GPU (``sweep``, its command
``cli_sweep``), its tables and scores (``sweep_report``) and the accuracy metrics (``metrics``: surface distances,
slice similarity, mesh quality). Nothing in the pipeline imports it.

Public names load lazily (``engine._lazy``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from engine._lazy import attach

if TYPE_CHECKING:
    from engine.paper.sweep import SweepConfig, run_sweep
    from engine.paper.sweep_report import enhancement_score, scores, write_tables

__all__ = [
    "SweepConfig",
    "enhancement_score",
    "run_sweep",
    "scores",
    "write_tables",
]
__getattr__, __dir__ = attach(
    __name__,
    {
        "SweepConfig": ".sweep",
        "run_sweep": ".sweep",
        "enhancement_score": ".sweep_report",
        "scores": ".sweep_report",
        "write_tables": ".sweep_report",
    },
)
