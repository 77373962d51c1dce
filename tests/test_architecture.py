"""The package's layers, read from the code's own imports: each layer imports only from the layers below it, and no
module imports itself through others (no circles), counting imports inside functions too."""

import ast
from pathlib import Path

import pytest

import virtual_vehicle

PACKAGE = Path(virtual_vehicle.__file__).parent
LAYERS = ["model", "physics", "engine", "cells", "config", "run", "analysis", "ui"]
"""From the bottom up; ``virtual_vehicle`` itself and ``virtual_vehicle.errors`` lie below them all."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every package module ``path`` imports, at any depth of the file, but not under ``if TYPE_CHECKING:``."""
    tree = ast.parse(path.read_text())
    here = _module_name(path)
    package = here if path.name == "__init__.py" else here.rsplit(".", 1)[0]
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            for n in ast.walk(node)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            found.add(base)
            found |= {f"{base}.{a.name}" for a in node.names}  # ``from pkg import module``
    return {m for m in found if m.split(".")[0] == "virtual_vehicle" and m in MODULES}


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def layer_of(module: str) -> int:
    """-1 for the package root, its errors, its compiled code's cache folder and how it compiles leaves, else the
    index of the module's layer in :data:`LAYERS`."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in ("errors", "compiled_cache", "compiled"):
        return -1
    if parts[1] not in LAYERS:
        raise AssertionError(f"{module} is in no layer: put it in one of {LAYERS}")
    return LAYERS.index(parts[1])


GRAPH = {m: _imports(p) - {m} for m, p in MODULES.items()}


def upward(graph: dict[str, set[str]], module: str) -> list[str]:
    """The modules ``module`` imports from layers above its own."""
    return sorted(d for d in graph[module] if layer_of(d) > layer_of(module))


def find_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` as a path that ends where it starts, or None (a submodule importing its own
    package's face is no circle: Python resolves it)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if m.startswith(d + "."):
                continue
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state and (found := visit(d)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


@pytest.mark.parametrize("module", sorted(MODULES))
def test_module_imports_only_its_layer_and_below(module):
    assert not upward(GRAPH, module), f"{module} imports from layers above its own: {upward(GRAPH, module)}"


def test_no_import_circles():
    circle = find_circle(GRAPH)
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_the_checks_see_an_upward_import_and_a_circle():
    bad = {"virtual_vehicle.model.a": {"virtual_vehicle.ui.b"}, "virtual_vehicle.ui.b": {"virtual_vehicle.model.a"}}
    assert upward(bad, "virtual_vehicle.model.a") == ["virtual_vehicle.ui.b"]
    assert upward(bad, "virtual_vehicle.ui.b") == []
    assert find_circle(bad) == ["virtual_vehicle.model.a", "virtual_vehicle.ui.b", "virtual_vehicle.model.a"]
    assert find_circle({"virtual_vehicle.model": {"virtual_vehicle.errors"}}) is None
