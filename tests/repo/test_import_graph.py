"""The package's import graph, read from the source (no module is imported): no import circles,
no room importing a room above it, quietframe imports at the top of a module where the graph
shows them, and no module over 600 lines.

A room is a top-level folder of the repository with an `__init__.py` (quietframe.<room>).
Imports inside functions count as edges too: a circle hidden in a function is still a circle.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = "quietframe"
MAX_LINES = 600

ROOMS = {p.parent.name for p in ROOT.glob("*/__init__.py")}
# Room -> the rooms it never imports: what two rooms share moves down to the lower one. These
# are docs/architecture.md's "may not" column: model/ is not imported by serving code (runtime,
# service, client, wire), experiments/ by no product room.
FORBIDDEN = {
    # a client install has no server, runtime or PyTorch (its one runtime import, for the
    # `serve` command's model listing, is in a function: OPTIONAL)
    "client": {"service", "model", "experiments"},
    "scenes": {"service", "experiments"},
    "runtime": {"service", "client", "model", "experiments"},  # both build on the runtime
    "service": {"model", "experiments"},
    **{room: {"experiments"} for room in ("model", "export", "bench", "models")},
    # The wire protocol and the EXR header's byte layout: a leaf every room may import
    "wire": ROOMS - {"wire"},
}
# Room -> third-party packages it never imports at module level (docs/architecture.md: the
# runtime and the service run without torch; the client installs without a compiler,
# onnxruntime or torch). A function-level import is an optional dependency (OPTIONAL's rule).
FORBIDDEN_PACKAGES = {
    "runtime": {"torch"},
    "service": {"torch"},
    "client": {"torch", "onnxruntime", "onnx"},
    "wire": {"torch", "onnxruntime", "onnx", "numpy"},
}
# Function-level quietframe imports that are there for an optional dependency of the imported
# module, which the importer's install may lack: (importer, imported) -> why.
OPTIONAL = {
    ("quietframe.client.cli", "quietframe.runtime.loaded_models"):
        "onnxruntime and the op library: the serve extra, which a client install lacks",
    ("quietframe.service.cli", "quietframe.service.main"):
        "the serve extra: `quietframe serve` is registered in the client's command",
    ("quietframe.service.cli", "quietframe.service.settings"):
        "the serve extra: `quietframe serve` is registered in the client's command",
    ("quietframe.bench.replicas", "quietframe.service.state_store_redis"):
        "redis, for the `store` command alone (throughput and estimate need none here)",
    ("quietframe.experiments.affinity_ops", "quietframe.model.affinity_kernels"):
        "torch, for the PyTorch reference row alone (--no-torch leaves it out)",
    ("quietframe.experiments.grid_ops", "quietframe.model.grid"):
        "torch, for the PyTorch rows alone (left out where torch is not installed)",
    ("quietframe.experiments.oidn_temporal_speed", "quietframe.export.onnx_export"):
        "torch, to export the untrained cases; --model and --prefilter need none",
    ("quietframe.experiments.oidn_temporal_speed", "quietframe.model.oidn_temporal"):
        "torch, to export the untrained cases; --model and --prefilter need none",
}
# Rooms not yet under a rule, by rule. Tighten as they are brought under it: the test fails
# once a listed room keeps the rule, so that it leaves this list.
PENDING = {
    "circles": set(),
    "function_imports": set(),
}


@dataclass(frozen=True)
class Import:
    importer: str  # module name
    imported: str  # module (or package) name
    line: int
    in_function: bool


def rooms() -> list[str]:
    return sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))


def room_of(module: str) -> str:
    return module.split(".")[1]


@cache
def modules() -> dict[str, Path]:
    """Every module of the package: quietframe.<room>.<path> -> its file."""
    out = {}
    for room in rooms():
        for path in (ROOT / room).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((PACKAGE, *parts))] = path
    return out


def _target(name: str) -> str | None:
    """The package module `name` is, or lies in (an imported attribute: its module)."""
    while name.count(".") >= 1:
        if name in modules():
            return name
        name = name.rsplit(".", 1)[0]
    return None


def _absolute(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".")[: None if is_package else -1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def packages_imported(path: Path) -> Iterator[tuple[str, int]]:
    """(third-party top-level package, line) of every module-level import in `path`."""
    def walk(node: ast.AST) -> Iterator[tuple[str, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, ast.Import):
                yield from ((alias.name.split(".")[0], child.lineno) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                yield child.module.split(".")[0], child.lineno
            yield from walk(child)

    yield from walk(ast.parse(path.read_text(), str(path)))


def _imports_of(module: str, path: Path) -> Iterator[Import]:
    is_package = path.name == "__init__.py"

    def walk(node: ast.AST, in_function: bool) -> Iterator[Import]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                names = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = _absolute(child, module, is_package)
                names = [f"{base}.{alias.name}" for alias in child.names]
            else:
                names = []
            for name in names:
                target = _target(name) if name.startswith(PACKAGE + ".") else None
                if target is not None and target != module:
                    yield Import(module, target, child.lineno, in_function)
            inner = isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            yield from walk(child, in_function or inner)

    yield from walk(ast.parse(path.read_text(), str(path)), False)


@cache
def imports() -> tuple[Import, ...]:
    return tuple(i for module, path in modules().items() for i in _imports_of(module, path))


def circles() -> list[list[str]]:
    """The import graph's strongly connected components of more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {m: set() for m in modules()}
    for i in imports():
        graph[i.importer].add(i.imported)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _check_pending(rule: str, failing_rooms: set[str]) -> None:
    kept = PENDING[rule] - failing_rooms
    assert not kept, f"{sorted(kept)} keep the {rule} rule now: take them off PENDING[{rule!r}]"


def test_no_import_circles():
    found = circles()
    failing = {room_of(m) for c in found for m in c}
    unexpected = [c for c in found if not {room_of(m) for m in c} <= PENDING["circles"]]
    assert not unexpected, f"import circles: {unexpected}"
    _check_pending("circles", failing)


def test_no_room_imports_a_room_above_it():
    wrong = sorted(f"{i.importer} -> {i.imported} (line {i.line})" for i in imports()
                   if room_of(i.imported) in FORBIDDEN.get(room_of(i.importer), ()))
    assert not wrong, "imports of a room above: " + "; ".join(wrong)


def test_forbidden_packages_are_not_imported_at_module_level():
    wrong = sorted(f"{module} imports {package} (line {line})"
                   for module, path in modules().items()
                   for package, line in packages_imported(path)
                   if package in FORBIDDEN_PACKAGES.get(room_of(module), ()))
    assert not wrong, "; ".join(wrong)


def test_the_client_reaches_no_onnxruntime_or_torch_through_the_rooms_it_imports():
    """What a client module imports at module level, and so on down, never imports torch,
    onnxruntime or onnx at module level: `pip install quietframe[client]` has none of them."""
    top = {}
    for i in imports():
        if not i.in_function:
            top.setdefault(i.importer, set()).add(i.imported)
    seen, todo = set(), [m for m in modules() if room_of(m) == "client"]
    while todo:
        module = todo.pop()
        if module not in seen:
            seen.add(module)
            todo.extend(top.get(module, ()))
    heavy = {"torch", "onnxruntime", "onnx"}
    wrong = sorted(f"{module} imports {package}" for module in seen
                   for package, _ in packages_imported(modules()[module]) if package in heavy)
    assert not wrong, "; ".join(wrong)


def test_the_rules_see_what_they_forbid():
    """A check of the check: the package reader finds a module-level torch import in model/,
    and a function-level import is not module-level."""
    assert "torch" in dict(packages_imported(ROOT / "model" / "nbg.py"))
    speedup = ROOT / "bench" / "oidn_speedup.py"  # pyoidn, imported in plain_oidn() only
    assert "import pyoidn" in speedup.read_text()
    assert "pyoidn" not in dict(packages_imported(speedup))


def test_quietframe_imports_inside_functions_only_for_optional_dependencies():
    inner = [i for i in imports()
             if i.in_function and (i.importer, i.imported) not in OPTIONAL]
    failing = {room_of(i.importer) for i in inner}
    wrong = sorted(f"{i.importer}:{i.line} -> {i.imported}" for i in inner
                   if room_of(i.importer) not in PENDING["function_imports"])
    assert not wrong, "quietframe imports inside functions: " + "; ".join(wrong)
    _check_pending("function_imports", failing)


def test_the_optional_imports_listed_still_exist():
    present = {(i.importer, i.imported) for i in imports() if i.in_function}
    assert set(OPTIONAL) <= present, f"no longer imported: {sorted(set(OPTIONAL) - present)}"


def test_no_module_is_over_600_lines():
    long = {m: n for m, path in modules().items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_the_graph_sees_imports_of_every_kind():
    """The reader resolves relative, aliased and function-level imports (a check of the check)."""
    found = {(i.importer, i.imported, i.in_function) for i in imports()}
    assert ("quietframe.scenes.render", "quietframe.scenes.mitsuba_trace", False) in found
    assert ("quietframe.runtime.card", "quietframe.runtime.receptive", False) in found
    assert ("quietframe.client.cli", "quietframe.runtime.loaded_models", True) in found
