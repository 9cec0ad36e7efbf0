"""Engine exceptions.

EngineError
├── InputError            the caller's input cannot be processed (bad file, bad parameters); exit code 2
│   ├── EmptySurfaceError the iso level does not cross the data: there is no surface to build
│   ├── IncompleteSeriesError  the series is not whole (missing slice, clashing duplicates, too few images)
│   └── BudgetError       the device memory budget is too small for this scan
└── StageError            a pipeline stage failed for a reason that is not the input's fault (names the stage)
"""

from __future__ import annotations


class EngineError(Exception):
    """Base class of the engine's errors."""


class InputError(EngineError, ValueError):
    """Input that the engine cannot process, with a reason a person can act on."""


class EmptySurfaceError(InputError):
    """The iso level does not cross the data: there is no surface to build."""


class StageError(EngineError):
    """A pipeline stage failed for a reason that is not the input's fault."""

    def __init__(self, stage: str, cause: BaseException) -> None:
        super().__init__(f"stage '{stage}' failed: {type(cause).__name__}: {cause}")
        self.stage = stage


class BudgetError(InputError):
    """The device memory budget (``max_device_bytes``) is too small for this scan; ``needed`` is the smallest
    budget that would work, as far as the engine can tell."""

    def __init__(self, message: str, needed: int) -> None:
        super().__init__(message)
        self.needed = int(needed)


class IncompleteSeriesError(InputError):
    """The series is not whole (a slice missing, two different images at one position, too few images): refused
    before anything is reconstructed, since a model built across the hole would look right and be wrong."""
