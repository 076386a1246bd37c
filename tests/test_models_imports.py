"""The models package has no import cycle (issue 22, item 5), at module level and with
function-level imports counted, and its runtime path (what ``polrig infer`` and a single-shot
capture load) imports nothing from evaluation or training and no torch.

The import graph is read from the source (:mod:`ast`: every ``import`` statement, wherever it
sits), so an import inside a function counts as an edge as much as one at the top."""

from __future__ import annotations

import ast
import pathlib

REPO = pathlib.Path(__file__).resolve().parents[1]
MODELS = REPO / "models"
#: What the runtime path may never reach: the evaluation and training code, and torch.
NOT_AT_RUNTIME = ("polrig.models.evaluate", "polrig.models.train", "polrig.models.data", "polrig.models.uncertainty_fit",
                  "polrig.models.diagnose", "polrig.models.export", "polrig.models.recover", "polrig.models.paper_scale",
                  "polrig.models.pipnet", "polrig.models.pmmnet", "polrig.models.layers", "polrig.models.pbrdf_torch",
                  "polrig.models.light_fit", "torch", "onnx")
RUNTIME = ("polrig.models.runtime", "polrig.models.uncertainty", "polrig.models.mirror", "polrig.models.size", "polrig.models.devices")


def _module_names() -> dict[str, pathlib.Path]:
    return {("models." + p.stem) if p.stem != "__init__" else "models": p for p in sorted(MODELS.glob("*.py"))}


def _imported(path: pathlib.Path, known: set[str]) -> set[str]:
    """Modules (top-level names and ``models.*`` modules in ``known``) imported anywhere in
    ``path``; ``from models import x`` counts as ``models.x`` when that is a module."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text("utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in known)
    return out


def _graph() -> dict[str, set[str]]:
    names = _module_names()
    known = set(names)
    graph = {}
    for mod, path in names.items():
        deps = _imported(path, known)
        # a models.* edge, or the top-level package of anything else (torch.nn -> torch)
        graph[mod] = {d for d in deps if d in known and d != mod} | {d.split(".")[0] for d in deps
                                                                    if not d.startswith("models")}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every elementary cycle found by depth-first search (each reported once per start)."""
    found, state = [], {}

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == 1:
                found.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])
    return found


def test_the_models_package_has_no_import_cycle():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles in models/: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    """The finder itself: a function-level back edge closes a circle it must report."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_runtime_path_reaches_no_evaluation_training_or_torch():
    graph = _graph()
    seen, todo = set(), list(m for m in RUNTIME if m in graph)
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(graph.get(m, ()))
    bad = sorted(seen & set(NOT_AT_RUNTIME))
    assert not bad, f"the runtime path ({', '.join(RUNTIME)}) reaches {bad}"


def test_function_level_imports_are_edges(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from polrig.models.evaluate import network_inputs\n    import torch.nn\n")
    assert _imported(src, {"polrig.models.evaluate"}) == {"polrig.models.evaluate", "torch.nn"}
