"""The package's shape: floors without circles or arrows back up, and its size limits.

The import graph is built from the source (every `import` and `from ... import`, at module
level or inside a function), so a lazy import counts like any other.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "drake_grasp"

# Lowest first. A module may import its own subpackage and the floors below it.
FLOORS = ("core", "objects", "geometry", "cnn", "config", "systems", "world", "policies",
          "learning", "evaluation", "cli", "api")
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100
MAX_TOP_LEVEL_MODULES = 12


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that module `name` imports."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                here = here[:len(here) - (node.level - 1)]
                base = ".".join(here + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                       for a in node.names]
        for target in targets:
            while target not in modules and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in modules and target != name and target.startswith("drake_grasp"):
                found.add(target)
    return found


def _floor(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None  # None: the package's own __init__


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def test_every_module_is_on_a_floor():
    unknown = sorted(m for m in _modules() if _floor(m) not in (None, *FLOORS))
    assert not unknown, f"modules outside the floors {FLOORS}: {unknown}"


def test_no_import_from_a_higher_floor():
    rank = {floor: i for i, floor in enumerate(FLOORS)}
    upward = []
    for module, targets in _graph().items():
        here = _floor(module)
        for target in targets:
            there = _floor(target)
            if here is None and there is not None:
                upward.append(f"{module} -> {target} (the package's __init__ imports nothing)")
            elif there is not None and rank[there] > rank[here]:
                upward.append(f"{module} ({here}) -> {target} ({there})")
    assert not upward, "imports from a higher floor:\n" + "\n".join(sorted(upward))


def test_no_import_circle():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                circles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert not circles, "import circles:\n" + "\n".join(circles)


def test_the_graph_sees_lazy_imports():
    """The checks above would pass on a graph that missed imports inside functions."""
    graph = _graph()
    # episode_diagram imports the station inside a function only
    assert "drake_grasp.world.station" in graph["drake_grasp.evaluation.episode_diagram"]
    assert "drake_grasp.cnn.network" in graph["drake_grasp.learning.training"]


def test_module_sizes():
    big = {m: n for m, p in _modules().items()
           if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not big, f"modules over {MAX_MODULE_LINES} lines: {big}"


def _is_table(node: ast.AST) -> bool:
    """A function without branches or loops: a declarative table (e.g. a parser's flags)."""
    branchy = (ast.If, ast.For, ast.While, ast.Try, ast.With, ast.comprehension, ast.IfExp,
               ast.Match, ast.BoolOp)
    return not any(isinstance(n, branchy) for n in ast.walk(node))


def test_function_sizes():
    long = []
    for module, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES and not _is_table(node):
                    long.append(f"{module}.{node.name}: {n} lines")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(sorted(long))


def test_top_level_modules():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, f"{len(top)} top-level modules: {top}"
