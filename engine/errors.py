"""Engine exceptions.

EngineError
└── InputError      the caller's input cannot be processed (bad file, bad parameters); exit code 2
"""

from __future__ import annotations


class EngineError(Exception):
    """Base class of the engine's errors."""


class InputError(EngineError, ValueError):
    """Input that the engine cannot process, with a reason a person can act on."""
