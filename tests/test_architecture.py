"""Imports flow one way (docs/architecture.md): ``drivers``, ``sim``, ``calibration`` and
``models`` build on polrig's core modules and never import the app modules (rig, session,
capture, processing, cli, commands, gui); ``models/runtime.py`` never imports torch; and no
module imports a module that imports it back (module- or function-level, any package)."""

from __future__ import annotations

import ast
import pathlib

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
APP = ("polrig.rig", "polrig.session", "polrig.capture", "polrig.processing", "polrig.records",
       "polrig.sessionio", "polrig.calibrations", "polrig.cli",
       "polrig.commands", "polrig.gui")
LOWER = ("drivers", "sim", "calibration", "models")


def _imports(path: pathlib.Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in ``path``, function-level imports included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text("utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.append((node.lineno, node.module))
            found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return found


@pytest.mark.parametrize("package", LOWER)
def test_lower_packages_never_import_the_app(package):
    bad = [f"{p.relative_to(REPO)}:{line} imports {mod}"
           for p in sorted((REPO / package).rglob("*.py"))
           for line, mod in _imports(p)
           if any(mod == app or mod.startswith(app + ".") for app in APP)]
    assert not bad, "\n".join(bad)


def test_runtime_never_imports_torch():
    mods = [m for _, m in _imports(REPO / "models" / "runtime.py")]
    assert not [m for m in mods if m == "torch" or m.startswith("torch.")]


# -- no import cycles ---------------------------------------------------------------------------
PACKAGES = ("polrig", "drivers", "sim", "calibration", "models")


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except those under ``if TYPE_CHECKING:`` (never imported at
    run time)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                todo.extend(child.orelse)
                continue
            todo.append(child)


def import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (module-level and function-level imports,
    relative ones resolved; ``from pkg import name`` counts as importing ``pkg.name`` where
    that is a module, else ``pkg``)."""
    files = {_module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_pkg = path.name == "__init__.py"
        edges: set[str] = set()
        for node in _runtime_nodes(ast.parse(path.read_text("utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = name.split(".") if is_pkg else name.split(".")[:-1]
                    anchor = anchor[:len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base
                           for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in files:  # a name inside a module
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.add(target)
        graph[name] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    import sys

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10000))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(out)


def test_the_cycle_finder_finds_cycles():
    """The checker itself: a two-module and a three-module cycle are found, a chain is not."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}, "g": set()}
    assert import_cycles(graph) == [["a", "b"], ["c", "d", "e"]]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_the_import_graph_sees_function_level_and_relative_imports():
    graph = import_graph()
    assert "polrig.session" in graph["polrig.capture"]  # module level
    assert "sim.options" in graph["polrig.rig"]  # function level (the [sim] table check)
    assert "sim.devices" not in graph["sim.truth"]  # only under TYPE_CHECKING: never runs
    assert "polrig.commands.capture" in graph["polrig.commands.reconstruct"]


def test_no_import_cycle_between_modules():
    """No module imports (directly or through others, at module or function level) a module
    that imports it back, in any of polrig, drivers, sim, calibration, models."""
    cycles = import_cycles(import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)
