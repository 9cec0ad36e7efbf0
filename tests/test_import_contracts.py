"""The floor plan of the packages, checked over the source with ``ast`` (import-linter's contracts, no new
dependency):

    service -> core -> engine        worker -> core, engine

* ``engine`` imports none of ``service``, ``worker``, ``core``, or the service's frameworks (Celery, FastAPI,
  Starlette, SQLAlchemy, Redis), at any level;
* ``core`` (what the API, the worker and the PACS gateway share) imports no ``service``, no ``worker``, no
  FastAPI/Starlette at any level, and loads no GPU code (Warp, PyOpenCL) when it is imported: neither its own
  module-level imports nor those of the engine modules they load reach it;
* ``worker`` imports no ``service`` at any level, and loads no GPU code when imported (Warp starts in the pool's
  child, inside the task, after the fork);
* ``service`` imports no ``worker``, except the one console-script dispatch named in ``ALLOWED``
  (``bonemesh worker``, looked up inside ``service.cli.main``), and no GPU code at any level;
* no import cycle among the modules of ``core``, ``service`` or ``worker`` at load time (module-level imports;
  those inside functions or under ``if TYPE_CHECKING:`` run later).

``importlib.import_module`` / ``__import__`` with a literal name count as imports. The engine's own contracts
(kernels import no host module, no cycle among its modules, ...) are in ``tests/engine/test_import_contracts.py``.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("engine", "core", "service", "worker")
GPU = ("warp", "pyopencl")
FORBIDDEN: dict[str, tuple[str, ...]] = {  # at any level, TYPE_CHECKING imports included
    "engine": ("service", "worker", "core", "celery", "fastapi", "starlette", "sqlalchemy", "redis"),
    "core": ("service", "worker", "fastapi", "starlette"),
    "worker": ("service",),
    "service": ("worker", *GPU),
}
# (importing module, imported module): the exceptions, each imported inside a function, never at module level
ALLOWED = {("service.cli", "worker.cli")}  # `bonemesh worker`: the console script's dispatch to the worker


@dataclass(frozen=True)
class Import:
    module: str  # ``a.b`` for ``import a.b`` and ``from a.b import c`` (and ``a.b.c`` where c is a module)
    line: int
    at_load: bool  # runs when the importing module loads (not in a function, not under TYPE_CHECKING)


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def _sources() -> dict[str, Path]:
    return {
        _module_name(p): p
        for package in PACKAGES
        for p in sorted((REPO / package).rglob("*.py"))
        if "__pycache__" not in p.parts
    }


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _literal_import(node: ast.Call) -> str | None:
    """The module named by ``importlib.import_module("x")`` / ``import_module("x")`` / ``__import__("x")``."""
    name = ast.unparse(node.func)
    if name in ("importlib.import_module", "import_module", "__import__") and node.args:
        arg = node.args[0]
        if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
            return arg.value
    return None


def _parse_imports(source: str, package: str, modules: frozenset[str] = frozenset()) -> tuple[Import, ...]:
    """Every import in ``source`` (a module of ``package``; ``modules``: the known module names), each marked by
    whether it runs when the module loads."""
    found: list[Import] = []

    def absolute(node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        parts = package.split(".")
        base = parts[: len(parts) - node.level + 1]
        return ".".join(base + ([node.module] if node.module else []))

    def visit(node: ast.AST, at_load: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend(Import(a.name, node.lineno, at_load) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = absolute(node)
            found.append(Import(base, node.lineno, at_load))
            found.extend(
                Import(f"{base}.{a.name}", node.lineno, at_load)
                for a in node.names
                if f"{base}.{a.name}" in modules  # ``from core.pacs import records`` names a module
            )
        elif isinstance(node, ast.Call) and (name := _literal_import(node)):
            found.append(Import(name, node.lineno, at_load))
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, False)
            for child in node.orelse:
                visit(child, at_load)
            return
        later = isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        for child in ast.iter_child_nodes(node):
            visit(child, at_load and not later)

    visit(ast.parse(source), True)
    return tuple(found)


@cache
def _imports(module: str) -> tuple[Import, ...]:
    """Every import of one of our modules (see :func:`_parse_imports`)."""
    path = _sources()[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    return _parse_imports(path.read_text(), package, frozenset(_sources()))


def _loaded_with(module: str) -> set[str]:
    """What Python loads to import ``module`` (``a``, ``a.b`` and ``a.b.c`` for ``a.b.c``) among our modules, or
    the top-level name of anything else."""
    parts = module.split(".")
    if parts[0] not in PACKAGES:
        return {parts[0]}
    return {".".join(parts[:i]) for i in range(1, len(parts) + 1)} & set(_sources())


@cache
def _load_closure(module: str) -> frozenset[str]:
    """Every module (ours) and top-level package (others) that importing ``module`` loads, by the module-level
    imports of ``module``, of its parent packages and of what they load in turn."""
    seen: set[str] = set()
    todo = list(_loaded_with(module))
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        if name in _sources():
            for imp in _imports(name):
                if imp.at_load:
                    todo.extend(_loaded_with(imp.module) - seen)
    return frozenset(seen)


def _top(name: str) -> str:
    return name.split(".")[0]


def test_the_sources_are_found() -> None:
    counts = {p: sum(1 for m in _sources() if _top(m) == p) for p in PACKAGES}
    assert all(n >= 3 for n in counts.values()), counts
    assert {"core.settings", "core.db", "core.pacs.dicomweb", "service.cli", "worker.tasks"} <= set(_sources())


@pytest.mark.parametrize("package", PACKAGES)
def test_each_package_imports_only_what_its_layer_allows(package: str) -> None:
    bad = [
        f"{mod}:{imp.line} imports {imp.module}" + ("" if imp.at_load else " (inside a function)")
        for mod in _sources()
        if _top(mod) == package
        for imp in _imports(mod)
        if _top(imp.module) in FORBIDDEN[package] and not ((mod, imp.module) in ALLOWED and not imp.at_load)
    ]
    assert not bad, bad


def test_the_allowed_exceptions_are_still_needed_and_lazy() -> None:
    """Each entry of ``ALLOWED`` is a real import, and inside a function: an unused exception is removed."""
    for mod, target in ALLOWED:
        found = [imp for imp in _imports(mod) if imp.module == target]
        assert found, f"{mod} no longer imports {target}: drop it from ALLOWED"
        assert not any(imp.at_load for imp in found), f"{mod} imports {target} at module level"


@pytest.mark.parametrize("package", ("core", "worker", "service"))
def test_importing_core_the_worker_or_the_service_loads_no_gpu_code(package: str) -> None:
    bad = {
        mod: sorted(set(GPU) & _load_closure(mod))
        for mod in _sources()
        if _top(mod) == package and set(GPU) & _load_closure(mod)
    }
    assert not bad, bad


def test_core_and_the_worker_never_load_the_service_or_a_web_framework_through_another_module() -> None:
    bad = [
        f"{mod} loads {name}"
        for mod in _sources()
        for name in _load_closure(mod)
        if (_top(mod) == "core" and _top(name) in FORBIDDEN["core"])
        or (_top(mod) == "worker" and _top(name) == "service")
    ]
    assert not bad, bad


@pytest.mark.parametrize("package", ("core", "service", "worker"))
def test_no_import_cycle_among_a_packages_modules_at_load_time(package: str) -> None:
    mods = sorted(m for m in _sources() if _top(m) == package)
    graph: dict[str, set[str]] = {}
    for m in mods:
        own = _loaded_with(m)  # the module and its parent packages: already loading when it loads
        graph[m] = {t for imp in _imports(m) if imp.at_load for t in _loaded_with(imp.module) if _top(t) == package}
        graph[m] -= own
    cycles: list[str] = []
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def walk(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                cycles.append(" -> ".join([*stack[stack.index(n) :], n]))
            elif n not in state:
                walk(n)
        stack.pop()
        state[m] = 2

    for m in mods:
        if m not in state:
            walk(m)
    assert not cycles, cycles


def test_the_checker_tells_load_time_imports_from_later_ones() -> None:
    """A module-level import is found under ``try`` and in a class body; one in a function or under
    ``TYPE_CHECKING`` runs later; relative and literal ``import_module`` imports are resolved."""
    source = (
        "from typing import TYPE_CHECKING\n"
        "try:\n    import warp\nexcept ImportError:\n    pass\n"
        "class A:\n    import worker.app\n"
        "def f():\n    import service.app\n"
        "if TYPE_CHECKING:\n    import fastapi\n"
        "from .db import Database\n"
        "from . import storage\n"
        "import importlib\n"
        "q = importlib.import_module('celery')\n"
    )
    got = {(imp.module, imp.at_load) for imp in _parse_imports(source, "core", frozenset({"core.storage"}))}
    assert {
        ("warp", True),
        ("worker.app", True),
        ("service.app", False),
        ("fastapi", False),
        ("core.db", True),
        ("core.storage", True),
        ("celery", True),
    } <= got


def test_importing_core_and_the_worker_parent_really_loads_no_gpu_code_and_no_service() -> None:
    """The same, by importing them in a fresh interpreter (what the static checks stand for)."""
    names = [*sorted(m for m in _sources() if _top(m) == "core"), "worker.app", "worker.cli", "worker.tasks"]
    code = (
        f"import sys\nfor n in {names!r}: __import__(n)\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'warp', 'pyopencl', 'service', 'fastapi'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
