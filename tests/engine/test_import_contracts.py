"""The engine's floor plan, checked (import-linter's contracts, as a test over the source with ``ast``):

* the engine is a library: it never imports the service, the worker or their frameworks;
* kernel modules (``engine/<package>/kernels/*.py``) hold Warp code only: they import ``warp``, ``numpy``, ``typing``
  and other kernel modules, and no host module;
* no import cycle among the engine's modules at load time (module-level imports; those inside functions or under
  ``TYPE_CHECKING`` run later, and each package's public names load lazily through ``engine._lazy``), nor counting
  the imports inside functions and through the lazy faces;
* the ground floor (``errors``, ``types``, ``params``, ``budget``, ``device``, ``report``) imports no stage package,
  and importing it or a stage package loads no Warp;
* the exporters and the other packages reach a stage package through its public face, never a module inside it
  (the print check uses ``engine.surface``'s functions);
* every engine exception is defined in ``engine.errors`` and drawn in its tree.
"""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENGINE = REPO / "engine"
STAGE_PACKAGES = ("volume", "isosurface", "decimation", "surface", "paper")
GROUND_FLOOR = (
    "engine.errors",
    "engine.types",
    "engine.params",
    "engine.budget",
    "engine.device",
    "engine.report",
    "engine._lazy",
)
KERNEL_ALLOWED = ("__future__", "typing", "warp", "numpy")
FORBIDDEN = ("service", "worker", "core", "celery", "fastapi", "starlette", "redis", "sqlalchemy", "benchmarks")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def _sources() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(ENGINE.rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(module: str, *, top_level_only: bool) -> list[tuple[str, int]]:
    """``(imported module, line)`` of a module's imports: every one, or those that run when it is loaded."""
    path = _sources()[module]
    tree = ast.parse(path.read_text())
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[tuple[str, int]] = []

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, ast.Import):
                found.extend((a.name, node.lineno) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                found.append((base, node.lineno))
                for a in node.names:  # ``from engine.x import y`` may name a submodule
                    if f"{base}.{a.name}" in _sources():
                        found.append((f"{base}.{a.name}", node.lineno))
            elif top_level_only:
                if isinstance(node, ast.If) and not _is_type_checking(node):
                    visit(node.body + node.orelse)
                elif isinstance(node, ast.Try):
                    visit(node.body + node.orelse + node.finalbody + [s for h in node.handlers for s in h.body])
            elif hasattr(node, "body"):
                for field in ("body", "orelse", "finalbody", "handlers"):
                    children = getattr(node, field, [])
                    visit([c for c in children if isinstance(c, ast.stmt)])
                    for h in children:
                        if isinstance(h, ast.ExceptHandler):
                            visit(h.body)

    visit(tree.body)
    return found


def _engine_imports(module: str, *, top_level_only: bool) -> set[str]:
    """The engine modules a module imports, with the packages Python loads first (``engine.a`` for ``engine.a.b``)."""
    mine = module.split(".")
    own = {".".join(mine[:i]) for i in range(1, len(mine) + 1)}  # already loading when this module loads
    out: set[str] = set()
    for name, _ in _imports(module, top_level_only=top_level_only):
        if name == "engine" or name.startswith("engine."):
            parts = name.split(".")
            out |= {".".join(parts[:i]) for i in range(1, len(parts) + 1)} & set(_sources())
    return out - own


def test_the_engine_never_imports_the_service_the_worker_or_their_frameworks():
    bad = [
        f"{mod}:{line} imports {name}"
        for mod in _sources()
        for name, line in _imports(mod, top_level_only=False)
        if name.split(".")[0] in FORBIDDEN
    ]
    assert not bad, bad


def test_kernel_modules_import_warp_numpy_and_other_kernels_only():
    kernels = [m for m in _sources() if ".kernels" in m]
    assert len(kernels) >= 12  # every package's kernels are found
    bad = []
    for mod in kernels:
        for name, line in _imports(mod, top_level_only=False):
            root = name.split(".")[0]
            if root in KERNEL_ALLOWED or (name.startswith("engine.") and ".kernels" in name):
                continue
            bad.append(f"{mod}:{line} imports {name}")
    assert not bad, bad


def test_every_package_keeps_its_kernels_in_a_kernels_folder():
    """One convention: Warp kernels live in ``engine/<package>/kernels/`` and nowhere else."""
    bad = []
    for mod, path in _sources().items():
        if ".kernels" in mod:
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef):
                for d in node.decorator_list:
                    text = ast.unparse(d)
                    if text.startswith(("wp.kernel", "wp.func", "warp.kernel", "warp.func")):
                        bad.append(f"{mod}:{node.lineno} {node.name}")
    assert not bad, bad


def test_no_import_cycle_among_the_engines_modules_at_load_time():
    graph = {m: _engine_imports(m, top_level_only=True) for m in _sources()}
    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def walk(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                cycles.append([*stack[stack.index(n) :], n])
            elif n not in state:
                walk(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            walk(m)
    assert not cycles, [" -> ".join(c) for c in cycles]


def test_the_ground_floor_imports_no_stage_package():
    stages = (*(f"engine.{p}" for p in STAGE_PACKAGES), "engine.job.pipeline", "engine.job.plans", "engine.job.outputs")
    bad = [
        f"{mod} imports {name}"
        for mod in GROUND_FLOOR
        for name in _engine_imports(mod, top_level_only=False)
        if name.startswith(stages) or name in ("engine.io", "engine.export")
    ]
    assert not bad, bad


def test_importing_the_ground_floor_and_the_stage_packages_loads_no_warp():
    names = [*GROUND_FLOOR, *(f"engine.{p}" for p in STAGE_PACKAGES), "engine"]
    code = f"import sys\nfor n in {names!r}: __import__(n)\nprint('warp' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_other_packages_reach_a_stage_package_through_its_public_face():
    """Inside a stage package anything goes; from outside (the exporters above all), only ``engine.<package>`` and
    its kernels' owners themselves. The pipeline, its plans, the outputs, the CLI and the paper's wing are the
    stages' orchestrators and may use their modules."""
    orchestrators = ("engine.job.pipeline", "engine.job.plans", "engine.job.outputs", "engine.cli", "engine.job.warmup")
    bad = []
    for mod in _sources():
        if not mod.startswith("engine.export"):
            continue
        for name in _engine_imports(mod, top_level_only=False):
            parts = name.split(".")
            if len(parts) > 2 and parts[1] in STAGE_PACKAGES:
                bad.append(f"{mod} imports {name}")
    assert not bad, bad
    assert orchestrators  # (documented above: they are not held to this)


@pytest.mark.parametrize("package", STAGE_PACKAGES)
def test_each_packages_public_names_resolve(package):
    mod = importlib.import_module(f"engine.{package}")
    assert sorted(mod.__all__) == mod.__dir__()  # the lazy table and the literal list name the same
    for name in mod.__all__:
        assert getattr(mod, name) is not None, name


def test_every_engine_exception_lives_in_the_error_tree():
    import engine.errors as errors

    names = set(errors.__all__)
    bad = []
    for mod, path in _sources().items():
        if mod == "engine.errors":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and {ast.unparse(b).split(".")[-1] for b in node.bases} & names:
                bad.append(f"{mod}:{node.lineno} {node.name}")
    assert not bad, bad
    for name in names:
        assert issubclass(getattr(errors, name), errors.EngineError)
        assert name in (errors.__doc__ or ""), f"{name} is not drawn in engine.errors' tree"


def _runtime_edges() -> dict[str, set[str]]:
    """Every engine module's imports that can run, at load time or later inside a function (``TYPE_CHECKING``
    blocks left out), each to the module that defines the name: a name taken from a package's lazy public face
    (``engine._lazy.attach``) counts as an import of the module it names."""
    sources = _sources()
    faces: dict[str, dict[str, str]] = {}
    for module, path in sources.items():
        if path.name != "__init__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "attach" and len(node.args) == 2:
                where = node.args[1]
                if isinstance(where, ast.Dict):
                    faces[module] = {
                        k.value: (module + v.value if v.value.startswith(".") else v.value)
                        for k, v in zip(where.keys, where.values, strict=True)
                        if isinstance(k, ast.Constant) and isinstance(v, ast.Constant)
                    }
    edges: dict[str, set[str]] = {}
    for module, path in sources.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        found: set[str] = set()

        def add(name: str, module: str = module, found: set[str] = found) -> None:
            while name and name not in sources:
                name = name.rpartition(".")[0]
            if name and name != module:
                found.add(name)

        def visit(node: ast.AST, add=add, package=package) -> None:
            if isinstance(node, ast.If) and _is_type_checking(node):
                for child in node.orelse:
                    visit(child)
                return
            if isinstance(node, ast.Import):
                for a in node.names:
                    add(a.name)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                for a in node.names:
                    if f"{base}.{a.name}" in sources:
                        add(f"{base}.{a.name}")
                    else:
                        add(faces.get(base, {}).get(a.name, base))
            for child in ast.iter_child_nodes(node):
                visit(child)

        visit(ast.parse(path.read_text()))
        edges[module] = found
    return edges


def test_no_import_cycle_among_the_engines_modules_counting_imports_inside_functions():
    """No two engine modules need each other, even through an import inside a function or a package's lazy face
    (such cycles hide in the import order: ``backend.select`` and ``device`` once resolved each other)."""
    edges = _runtime_edges()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def strong(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    assert not cycles, cycles
