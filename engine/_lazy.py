"""PEP 562 lazy attributes for the engine's packages (scikit-image's ``lazy_loader`` idea, without the dependency):
a package names where each public attribute lives, and the module is imported on first use. Importing a package
therefore loads none of its modules (nor Warp), and two packages may name each other's functions without an
import cycle at load time."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def attach(package: str, where: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``, whose attribute ``name`` is ``where[name]``'s (a
    module path, absolute or relative to the package: ``".passes"``). The package lists the same names in a
    literal ``__all__`` and imports them under ``TYPE_CHECKING`` for type checkers and linters."""

    def __getattr__(name: str) -> Any:
        if name in where:
            return getattr(importlib.import_module(where[name], package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(where)

    return __getattr__, __dir__
