"""Imports flow one way (docs/architecture.md): ``drivers``, ``sim``, ``calibration`` and
``models`` build on polrig's core modules and never import the app modules (rig, session,
capture, processing, cli, commands, gui); ``models/runtime.py`` never imports torch."""

from __future__ import annotations

import ast
import pathlib

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
APP = ("polrig.rig", "polrig.session", "polrig.capture", "polrig.processing", "polrig.cli",
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
