"""The floor plan: no import cycles between labrig's modules, function-local imports included, and
no function-local import of a labrig module outside ``cli/`` unless that module is heavy.

The layer contracts themselves are import-linter's (pyproject.toml, run by `make test`); this
checks what they cannot: that no two modules reach each other, so a function-local import
never hides a cycle (grimp counts function-local and TYPE_CHECKING imports alike), and that a
function-local import only defers a heavy dependency's import chain.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module, iteratively."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))
    return components


def test_the_helper_finds_a_cycle() -> None:
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_module_imports_cycle_back_to_itself() -> None:
    grimp = pytest.importorskip("grimp", reason="grimp comes with import-linter (the test extras)")
    graph = grimp.build_graph("labrig")
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    cycles = strongly_connected(edges)
    assert cycles == [], "import cycles (break them by moving code down a layer, never by a function-local import): " + \
        "; ".join(" <-> ".join(c) for c in cycles)


PACKAGE = Path(__file__).resolve().parents[1] / "labrig"
#: Third-party packages slow or optional enough that importing them is worth deferring (and the
#: Metavision SDK's packages, metavision_*).
HEAVY_DEPENDENCIES = frozenset({"torch", "cv2", "onnxruntime", "dask", "distributed", "matplotlib", "numba"})
#: The labrig modules a module outside ``cli/`` may import inside a function: each imports a heavy
#: dependency at its top. numba's kernels stay behind the codecs' first use, since ``import labrig``
#: loads ``labrig.devices.raw`` and ``labrig --help`` must not load numba.
DEFERRABLE_MODULES = frozenset({
    "labrig.devices.raw._evt2_kernels",  # numba
    "labrig.devices.raw._evt3_kernels",  # numba
    "labrig.devices.raw._state",  # numba
    "labrig.calibration.extrinsics",  # cv2
})


def is_heavy(package: str) -> bool:
    return package in HEAVY_DEPENDENCIES or package.startswith("metavision")


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str, package: Path = PACKAGE) -> bool:
    inner = package.joinpath(*name.split(".")[1:])
    return inner.with_suffix(".py").exists() or (inner / "__init__.py").exists()


def imported_modules(node: ast.Import | ast.ImportFrom, package: Path = PACKAGE) -> set[str]:
    """The modules ``node`` imports (labrig uses absolute imports only): ``from a import b`` names
    ``a.b`` when that is a module, else ``a``."""
    if isinstance(node, ast.Import):
        return {alias.name for alias in node.names}
    base = node.module or ""
    return {f"{base}.{alias.name}" if is_module(f"{base}.{alias.name}", package) else base for alias in node.names}


def function_local_imports(source: str, package: Path = PACKAGE) -> list[tuple[int, str]]:
    """(line, module) of every labrig module imported inside a function of ``source``."""
    found = set()
    for function in ast.walk(ast.parse(source)):
        if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
            for node in ast.walk(function):
                if isinstance(node, ast.Import | ast.ImportFrom):
                    found |= {(node.lineno, name) for name in imported_modules(node, package)
                              if name.split(".")[0] == "labrig"}
    return sorted(found)


def top_level_imports(source: str) -> set[str]:
    """The top-level packages ``source`` imports when it is imported (outside functions and TYPE_CHECKING)."""
    found: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import):
                found.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module:
                found.add(node.module.split(".")[0])
            elif isinstance(node, ast.If) and "TYPE_CHECKING" not in ast.unparse(node.test):
                visit(node.body + node.orelse)
            elif isinstance(node, ast.Try | ast.ClassDef):
                visit(node.body)

    visit(ast.parse(source).body)
    return found


def test_the_scan_finds_function_local_imports(tmp_path: Path) -> None:
    package = tmp_path / "labrig"
    (package / "sub").mkdir(parents=True)
    for name in ("__init__.py", "light.py", "sub/__init__.py", "sub/kernels.py"):
        (package / name).write_text("")
    source = ("from labrig import light\n"
              "def f():\n    from labrig.sub import kernels\n    import numpy\n"
              "class C:\n    def g(self):\n        from labrig.light import name\n")
    assert function_local_imports(source, package) == [(3, "labrig.sub.kernels"), (7, "labrig.light")]
    assert top_level_imports("import numba\nif TYPE_CHECKING:\n    import torch\ndef f():\n    import cv2\n") == {"numba"}


def test_labrig_modules_are_imported_at_the_top_unless_heavy() -> None:
    """Outside ``cli/`` (whose commands defer everything to keep ``labrig --help`` fast) a labrig module is
    imported inside a function only when it is in DEFERRABLE_MODULES."""
    offenders = [f"{path.relative_to(PACKAGE.parent)}:{line}: {name}"
                 for path in sorted(PACKAGE.rglob("*.py")) if "cli" not in path.relative_to(PACKAGE).parts
                 for line, name in function_local_imports(path.read_text())
                 if name not in DEFERRABLE_MODULES]
    assert offenders == [], "move these imports to the module's top (or, for a module that imports a heavy " + \
        "dependency at its top, add it to DEFERRABLE_MODULES): " + "; ".join(offenders)


@pytest.mark.parametrize("name", sorted(DEFERRABLE_MODULES))
def test_every_deferrable_module_imports_a_heavy_dependency(name: str) -> None:
    inner = PACKAGE.joinpath(*name.split(".")[1:])
    source = (inner.with_suffix(".py") if inner.with_suffix(".py").exists() else inner / "__init__.py").read_text()
    assert any(is_heavy(package) for package in top_level_imports(source)), \
        f"{name} imports nothing heavy at its top: import it at the top of its users"


def test_every_serial_test_module_exists() -> None:
    """`make test` runs the modules of conftest.SERIAL_MODULES alone; a renamed module would silently join the
    parallel run."""
    from conftest import SERIAL_MODULES

    missing = sorted(m for m in SERIAL_MODULES if not (Path(__file__).parent / f"{m}.py").exists())
    assert missing == [], f"SERIAL_MODULES names modules that are gone: {missing}"
