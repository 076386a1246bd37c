"""The architecture of docs/architecture.md, checked on the code.

* One import name: only ``polrig`` is a top-level package; the repository's ``drivers/``,
  ``sim/``, ``calibration/`` and ``models/`` folders are ``polrig.drivers`` and so on, and no file
  imports them (or a module's pre-layering path such as ``polrig.session``) by an old name.
* Layers: every module belongs to one layer, and a module never imports a module of a higher
  layer (module level, function level, or under ``if TYPE_CHECKING:``).
* No module imports a module that imports it back, directly or through others.
* ``polrig.models.runtime`` never imports torch (inference is onnxruntime only).
* One public face: ``polrig`` (layer 0) re-exports the Python API (``polrig.open_session``...)
  lazily, through its module ``__getattr__`` and the table :data:`PUBLIC_FACE` declared here;
  ``import polrig`` imports nothing of a higher layer, and ``polrig/__init__.py`` has no import
  statement of a project module (the table is the only way up, and this test knows it).
* The shells present, the app layer does: no module of ``polrig.cli`` or ``polrig.gui`` takes
  a capture's steps itself; each calls :func:`polrig.app.capture.run_capture`.
* One single-shot route (issue 30): among the app layer and the shells only
  ``polrig.app.single_shot`` uses the single-shot runtime (imports ``polrig.models.runtime``,
  ``full_resolution`` or ``mirror``, loads a ``SingleShotModel``, runs its passes); processing,
  ``polrig infer``, the plan check and the GUI's live view go through it.
"""

from __future__ import annotations

import ast
import functools
import pathlib
import re
import sys
import tomllib

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]

#: Where each import package lives in the repository.
PACKAGE_DIRS = {"polrig": "polrig", "polrig.drivers": "drivers", "polrig.sim": "sim",
                "polrig.calibration": "calibration", "polrig.models": "models"}

#: The layers, bottom up (docs/architecture.md). A module's layer is that of the longest entry
#: that is the module or one of its packages; ``polrig`` itself (the version) is the bottom.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("polrig", "polrig.errors", "polrig.atomic", "polrig.choices"),  # foundation: version, errors, atomic writes, CLI vocabularies
    ("polrig.optics",),
    ("polrig.sensor",),
    ("polrig.formats",),
    ("polrig.solve",),
    ("polrig.acquisition",),
    ("polrig.drivers",),
    ("polrig.sim",),
    ("polrig.calibration",),
    ("polrig.models",),
    ("polrig.app",),
    ("polrig.gui",),
    ("polrig.cli", "polrig.__main__"),
)

#: The one deliberate lazy re-export (docs/architecture.md, "The public face"): names of
#: ``polrig`` -> the module that defines them, imported by ``polrig.__getattr__`` on first access.
PUBLIC_FACE = {
    "open_session": "polrig.app.dataset",
    "open_result": "polrig.app.dataset",
    "run_capture": "polrig.app.capture",
    "CaptureRequest": "polrig.app.capture",
    "SampleMetadata": "polrig.app.manifest",
    "export": "polrig.app.export",
    "normals_from_mueller": "polrig.optics.shape_from_polarization",
}

#: Top-level names polrig used to install besides ``polrig``, and the pre-layering modules of
#: ``polrig`` (each now lives in a layer's subpackage).
OLD_TOP_LEVEL = ("drivers", "sim", "calibration", "models")
OLD_POLRIG_MODULES = (
    "conventions", "mueller", "conductors", "realizability", "frames", "pbrdf", "layouts",
    "pixelformats", "demosaic", "stokes", "noise", "analyzer", "rawio", "exr", "config",
    "argcheck", "radiometry", "reference", "_reference_kernel", "_reference_numpy", "scoring",
    "quantiles", "hal", "plan", "engine", "rig", "session", "records", "sessionio",
    "calibrations", "processing", "capture", "cluster", "preview", "commands")


def parsed(path: pathlib.Path) -> ast.Module:
    """The syntax tree of ``path``, parsed once per file version in this test process (the
    checks below walk the same few hundred files; a file written by a test is new)."""
    stat = path.stat()
    return _parsed(path, stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=None)
def _parsed(path: pathlib.Path, mtime_ns: int, size: int) -> ast.Module:
    return ast.parse(path.read_text("utf-8"), str(path))


def _files() -> dict[str, pathlib.Path]:
    """Module name -> file, for every module of the distribution."""
    out = {}
    for pkg, folder in PACKAGE_DIRS.items():
        root = REPO / folder
        for p in sorted(root.rglob("*.py")):
            parts = list(p.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([pkg, *parts])
            if pkg == "polrig" and any(name == k or name.startswith(k + ".")
                                       for k in PACKAGE_DIRS if k != "polrig"):
                continue
            out[name] = p
    return out


def _imports(tree: ast.AST, name: str, is_pkg: bool) -> list[tuple[int, str]]:
    """``(line, dotted name)`` of every import in ``tree`` (any depth, ``TYPE_CHECKING`` blocks
    included; relative imports resolved against module ``name``); ``from pkg import x`` gives
    ``pkg.x`` (the graph reads it as ``pkg`` where ``x`` is no module)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_pkg else name.split(".")[:-1]
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found += [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return found


def import_graph(files: dict[str, pathlib.Path] | None = None) -> dict[str, set[str]]:
    """Module -> the project modules it imports (any depth, ``from pkg import name`` counts as
    importing ``pkg.name`` where that is a module, else ``pkg``)."""
    files = _files() if files is None else files
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        tree = parsed(path)
        edges = set()
        for _, target in _imports(tree, name, path.name == "__init__.py"):
            while target and target not in files:  # a name inside a module
                target = target.rpartition(".")[0]
            if target and target != name:
                edges.add(target)
        graph[name] = edges
    return graph


def layer_of(module: str) -> int:
    """Index into :data:`LAYERS` of ``module`` (KeyError for a module no layer holds)."""
    best, rank = "", None
    for i, names in enumerate(LAYERS):
        for n in names:
            matches = module == n if n == "polrig" else (module == n or module.startswith(n + "."))
            if matches and len(n) > len(best):
                best, rank = n, i
    if rank is None:
        raise KeyError(module)
    return rank


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})"
                  for a, targets in graph.items() for b in targets
                  if b.startswith("polrig") and layer_of(b) > layer_of(a))


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

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10000))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(out)


#: The one single-shot route (frame -> Mueller result with its planes; docs/architecture.md).
SINGLE_SHOT_ROUTE = "polrig.app.single_shot"
#: What a route of its own would be built from: the runtime's modules ...
SINGLE_SHOT_RUNTIME = ("polrig.models.runtime", "polrig.models.full_resolution", "polrig.models.mirror",
                       "polrig.models.device_path")
#: ... and its names: loading the model, its passes, the binned route, the removed duplicates.
SINGLE_SHOT_STEPS = ("SingleShotModel", "DevicePath", "run_rig_frame", "run_normalised", "reconstruct_binned",
                     "infer_frame", "infer_mueller")
#: The modules that must take the route: capture and reconstruct processing, the plan check,
#: ``polrig infer``, the GUI's live view (its display data, its model loader).
SINGLE_SHOT_USERS = ("polrig.app.processing", "polrig.app.calibrations", "polrig.cli.commands.infer",
                     "polrig.gui.pipeline", "polrig.gui.app")


def own_single_shot_route(path: pathlib.Path, name: str) -> list[str]:
    """Where module ``name`` (file ``path``) builds a single-shot route of its own: an import
    of :data:`SINGLE_SHOT_RUNTIME` (any name in it, at any depth), a use of a name of
    :data:`SINGLE_SHOT_STEPS`, or a call of a model's ``reconstruct`` (``....model.reconstruct(...)``)."""
    tree = parsed(path)
    where = path.relative_to(REPO) if path.is_relative_to(REPO) else path
    bad = [f"{where}:{line} imports {mod}" for line, mod in _imports(tree, name, path.name == "__init__.py")
           if any(mod == r or mod.startswith(r + ".") for r in SINGLE_SHOT_RUNTIME)]
    for node in ast.walk(tree):
        ident = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None
        if ident in SINGLE_SHOT_STEPS:
            bad.append(f"{where}:{node.lineno} uses {ident}")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "reconstruct"
                and "model" in ast.unparse(node.func.value).lower()):
            bad.append(f"{where}:{node.lineno} calls {ast.unparse(node.func)}")
    return bad


def old_name_imports(path: pathlib.Path) -> list[str]:
    """Imports in ``path`` of an old top-level name or a pre-layering ``polrig`` module."""
    old = re.compile(r"^(?:(?:%s)(?:\.|$)|polrig\.(?:%s)(?:\.|$))" % (
        "|".join(OLD_TOP_LEVEL), "|".join(OLD_POLRIG_MODULES)))
    bad = []
    for line, mod in _imports(parsed(path), "", False):
        if old.match(mod):
            bad.append(f"{path.relative_to(REPO)}:{line} imports {mod}")
    return bad


# -- the checkers themselves -------------------------------------------------------------------
def test_the_cycle_finder_finds_cycles():
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}, "g": set()}
    assert import_cycles(graph) == [["a", "b"], ["c", "d", "e"]]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_the_layer_check_finds_an_upward_import():
    graph = {"polrig.sensor.stokes": {"polrig.optics.mueller"},
             "polrig.optics.mueller": {"polrig.app.processing"},
             "polrig.app.processing": {"polrig.models.runtime", "polrig"}}
    assert upward_imports(graph) == [
        "polrig.optics.mueller (layer 1) imports polrig.app.processing (layer 10)"]
    assert layer_of("polrig") == 0 and layer_of("polrig.errors") == 0
    assert layer_of("polrig.cli.commands.capture") == layer_of("polrig.cli")
    with pytest.raises(KeyError):
        layer_of("polrig.newthing")


def test_the_old_name_check_finds_old_names(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    f = tmp_path / "m.py"
    f.write_text("import models.runtime as rt\nfrom sim import devices\n"
                 "from polrig.session import Session\nfrom polrig import errors\n"
                 "def f():\n    from calibration.calset import load\n"
                 "from polrig.cli.commands import capture\nfrom polrig.app import session\n")
    assert [b.split(" imports ")[1] for b in old_name_imports(f)] == [
        "models.runtime", "sim.devices", "polrig.session.Session", "calibration.calset.load"]


def test_the_single_shot_check_finds_a_route_of_its_own(tmp_path):
    f = tmp_path / "shell.py"
    f.write_text("from polrig.models.runtime import SingleShotModel\n"
                 "def view(frame, m):\n    from polrig.models import full_resolution\n"
                 "    return m.model.reconstruct(frame)\n"
                 "import polrig.models.mirror as mirror\nfrom polrig.models.uncertainty import how_to_calibrate\n"
                 "from polrig.app.single_shot import SingleShot\nr = SingleShot.open('cpu')\n"
                 "cluster.reconstruct([])\nmodel = SingleShotModel.load()\n")
    found = [b.split(".py:", 1)[1] for b in own_single_shot_route(f, "polrig.gui.shell")]
    assert sorted(found, key=lambda b: int(b.split()[0])) == [
        "1 imports polrig.models.runtime.SingleShotModel", "3 imports polrig.models.full_resolution",
        "4 calls m.model.reconstruct", "5 imports polrig.models.mirror", "10 uses SingleShotModel"]


def test_the_import_graph_sees_every_kind_of_import():
    graph = import_graph()
    assert "polrig.app.session" in graph["polrig.app.capture"]  # module level
    assert "polrig.cli.commands.capture" in graph["polrig.cli.commands.reconstruct"]
    # relative imports, under TYPE_CHECKING and inside functions
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import q\n"
                     "def f():\n    from .q import g\n")
    assert {m for _, m in _imports(tree, "p", True)} >= {"p.q", "p.q.g"}


# -- the code -----------------------------------------------------------------------------------
def test_every_module_has_a_layer():
    missing = [m for m in _files() if not _has_layer(m)]
    assert not missing, f"modules no layer holds (add them to LAYERS and the docs): {missing}"


def _has_layer(module: str) -> bool:
    try:
        layer_of(module)
    except KeyError:
        return False
    return True


def test_no_upward_import():
    """A module never imports a module of a higher layer, at any depth."""
    bad = upward_imports(import_graph())
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_import_cycle_between_modules():
    cycles = import_cycles(import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_file_imports_an_old_name():
    """polrig, its packages, the tests and the benchmarks import only ``polrig.*`` names."""
    roots = [*PACKAGE_DIRS.values(), "tests", "benchmarks"]
    bad = [b for r in roots for p in sorted((REPO / r).rglob("*.py")) for b in old_name_imports(p)]
    assert not bad, "\n".join(bad)


def test_no_doc_or_script_runs_an_old_module_name():
    """READMEs, docs, scripts and code name modules to run as ``python -m polrig...``."""
    pattern = re.compile(r"-m\s+(?:%s)\." % "|".join(OLD_TOP_LEVEL))
    paths = [p for p in REPO.rglob("*") if p.is_file() and ".git" not in p.parts
             and ".venv" not in p.parts and "results" not in p.parts
             and p.suffix in (".md", ".py", ".sh", ".toml", "")]
    bad = [f"{p.relative_to(REPO)}: {m.group(0)}" for p in paths
           for m in pattern.finditer(p.read_text("utf-8", errors="replace"))]
    assert not bad, "\n".join(bad)


def test_the_package_list_is_every_package_folder():
    """pyproject's explicit package list (the wheel's contents) names every folder with an
    ``__init__.py`` under each package directory, and maps them under ``polrig``."""
    conf = tomllib.loads((REPO / "pyproject.toml").read_text("utf-8"))["tool"]["setuptools"]
    assert conf["package-dir"] == PACKAGE_DIRS
    found = {m for m, p in _files().items() if p.name == "__init__.py"}
    assert sorted(conf["packages"]) == sorted(found)


def test_the_public_face_is_declared_lazy_and_the_only_way_up():
    """``polrig``'s public face is exactly :data:`PUBLIC_FACE`: each name is the object its
    module defines; ``polrig/__init__.py`` imports no project module itself (only
    ``importlib``, inside ``__getattr__``); a fresh ``import polrig`` loads no module above
    layer 0; an unknown name is an ``AttributeError``."""
    import subprocess

    import polrig

    assert polrig.PUBLIC_FACE == PUBLIC_FACE
    assert set(PUBLIC_FACE) <= set(polrig.__all__) and set(PUBLIC_FACE) <= set(dir(polrig))
    for name, module in PUBLIC_FACE.items():
        assert _files()[module] and getattr(polrig, name) is _resolve(f"{module}.{name}"), name
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        polrig.nothing_here  # noqa: B018
    init = _files()["polrig"]
    tree = parsed(init)
    assert [m for _, m in _imports(tree, "polrig", True)] == ["importlib"]
    getattr_fn = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "__getattr__"]
    assert getattr_fn and any(isinstance(n, ast.Import) for n in ast.walk(getattr_fn[0]))
    code = ("import sys, polrig\n"
            "up = sorted(m for m in sys.modules if m.startswith('polrig.') and m not in "
            "('polrig.errors', 'polrig.atomic'))\nprint(up)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=REPO).stdout.strip()
    assert out == "[]", f"import polrig loads {out}"


def test_runtime_never_imports_torch():
    path = _files()["polrig.models.runtime"]
    mods = [m for _, m in _imports(parsed(path), "polrig.models.runtime",
                                   False)]
    assert not [m for m in mods if m == "torch" or m.startswith("torch.")]


# -- the shells present, the app layer does ---------------------------------------------------------
#: Module name prefixes of the shells (docs/architecture.md, "Shells").
SHELLS = ("polrig.cli", "polrig.gui", "polrig.__main__")
#: The steps of a capture that only :func:`polrig.app.capture.run_capture` takes: a shell that
#: names one of them (under any name it is imported as, re-exports included) builds its own
#: capture instead of calling the one capture call.
CAPTURE_STEPS = (
    "polrig.app.capture.prepare_capture", "polrig.app.capture.open_session",
    "polrig.app.capture.run_session", "polrig.app.capture.interrupted_result",
    "polrig.app.capture.PreparedCapture", "polrig.app.sessionio.create_session",
    "polrig.app.sessionio.check_resume_space", "polrig.app.session.Session.create",
    "polrig.app.processing.Processor", "polrig.app.processing.make_processor",
    "polrig.app.records.check_resume_rig", "polrig.app.records.check_rig_for_plan",
    "polrig.app.records.session_sensor_model",
    "polrig.app.calibrations.check_calibration_fits_rig")


def _resolve(dotted: str):
    """The object ``dotted`` names (the longest importable module, then attributes), or
    ``None`` where it names nothing."""
    import importlib

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return getattr(obj, "__func__", obj)  # a classmethod: its function, one object
    return None


def _names_used(tree: ast.AST, name: str, is_pkg: bool) -> list[tuple[int, str]]:
    """``(line, dotted name)`` of every project name a module's code refers to: imported names
    (``from polrig.app.capture import run_session as rs``) and attribute chains on imported
    modules (``capture.run_session``, ``polrig.app.capture.run_session``), resolved through
    the module's imports (any depth)."""
    aliases: dict[str, str] = {}
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.asname:
                    aliases[a.asname] = a.name
                else:
                    aliases.setdefault(a.name.split(".")[0], a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom):
            for line, target in _imports(ast.Module(body=[node], type_ignores=[]), name, is_pkg):
                local = next(a.asname or a.name for a in node.names
                             if target.endswith("." + a.name))
                aliases[local] = target
                found.append((line, target))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            chain = []
            inner = node
            while isinstance(inner, ast.Attribute):
                chain.append(inner.attr)
                inner = inner.value
            if isinstance(inner, ast.Name) and inner.id in aliases:
                found.append((node.lineno, ".".join([aliases[inner.id], *reversed(chain)])))
    return [(line, d) for line, d in found if d.startswith("polrig")]


def capture_steps_used(path: pathlib.Path, module: str) -> list[str]:
    """The capture steps (:data:`CAPTURE_STEPS`, compared as objects: a re-export is the same
    step) that the code of ``module`` in ``path`` refers to."""
    steps = {id(obj): dotted for dotted in CAPTURE_STEPS if (obj := _resolve(dotted)) is not None}
    tree = parsed(path)
    bad = []
    for line, dotted in _names_used(tree, module, path.name == "__init__.py"):
        obj = _resolve(dotted)
        if obj is not None and id(obj) in steps:
            bad.append(f"{path.relative_to(REPO)}:{line} uses {dotted} ({steps[id(obj)]})")
    return sorted(set(bad))


def test_the_shell_check_finds_a_shell_that_builds_its_own_capture(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    f = tmp_path / "m.py"
    f.write_text("import polrig.app.capture\nimport polrig.app.session as ses\n"
                 "from polrig.app import capture, processing as proc\n"
                 "from polrig.app.capture import open_session as opened, run_capture\n"
                 "from polrig.app.processing import session_sensor_model\n"
                 "def f(request, rig):\n"
                 "    p = capture.prepare_capture(request)\n"
                 "    s = opened(p, rig, [])\n"
                 "    proc.make_processor(p.plan, p.calibration, session_sensor_model(s))\n"
                 "    polrig.app.capture.run_session(rig, s)\n"
                 "    ses.Session.create\n"
                 "    return run_capture(request, command_line=[])\n")
    found = {b.split(" uses ")[1].split(" (")[0] for b in capture_steps_used(f, "polrig.cli.x")}
    assert found == ({
        "polrig.app.capture.prepare_capture", "polrig.app.capture.open_session",
        "polrig.app.processing.make_processor", "polrig.app.processing.session_sensor_model",
        "polrig.app.capture.run_session", "polrig.app.session.Session.create"}), found
    g = tmp_path / "g.py"
    g.write_text("from polrig.app.capture import run_capture, CaptureRequest\n"
                 "from polrig.app import processing\nprocessing.adc_scale\n")
    assert capture_steps_used(g, "polrig.gui.g") == []


def test_every_shell_captures_through_the_one_capture_call():
    """No module of ``polrig.cli`` or ``polrig.gui`` takes a capture's steps itself (prepare,
    open the session, make the processor, run it, report a stop): each calls
    :func:`polrig.app.capture.run_capture` and presents its events. ``polrig capture`` and the
    GUI's capture panel do call it."""
    files = {m: p for m, p in _files().items() if m.startswith(SHELLS)}
    bad = [b for m, p in sorted(files.items()) for b in capture_steps_used(p, m)]
    assert not bad, "a shell builds its own capture:\n" + "\n".join(bad)
    for shell in ("polrig.cli.commands.capture", "polrig.gui.capture_panel"):
        tree = parsed(files[shell])
        used = {d for _, d in _names_used(tree, shell, False)}
        assert "polrig.app.capture.run_capture" in used, shell


def test_every_shell_and_processing_take_the_one_single_shot_route():
    """Issue 30: the app layer and the shells (``polrig.gui``, ``polrig.cli``) build no
    single-shot route of their own (:func:`own_single_shot_route`); only
    :data:`SINGLE_SHOT_ROUTE` uses the runtime, and the modules of :data:`SINGLE_SHOT_USERS`
    import it."""
    files = _files()
    shells = [m for m in files if layer_of(m) >= layer_of("polrig.app") and m != SINGLE_SHOT_ROUTE]
    assert "polrig.cli.commands.infer" in shells and "polrig.gui.pipeline" in shells
    bad = [b for m in shells for b in own_single_shot_route(files[m], m)]
    assert not bad, "single-shot routes outside polrig.app.single_shot:\n" + "\n".join(bad)
    graph = import_graph(files)
    missing = [m for m in SINGLE_SHOT_USERS if SINGLE_SHOT_ROUTE not in graph[m]]
    assert not missing, f"modules that should run single-shot through {SINGLE_SHOT_ROUTE}: {missing}"
    assert own_single_shot_route(files[SINGLE_SHOT_ROUTE], SINGLE_SHOT_ROUTE)  # it does use the runtime
