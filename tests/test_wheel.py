"""The built wheel, installed (not editable) into an environment of its own, works next to a
user's own ``models``, ``sim``, ``calibration`` and ``drivers`` packages (issue 30).

The wheel is built from a copy of the sources with this environment's setuptools (no build
isolation, no network) and its top-level names are checked: ``polrig`` and its metadata only,
with every module and the shipped weights. It is installed with pip (``--no-deps
--no-index``) into a new virtual environment, which borrows this environment's installed
dependencies through a ``.pth`` file of plain path lines: such lines are not themselves
scanned for ``.pth`` files, so the editable install of the sources (its finder is registered
by an ``__editable__*.pth``) stays out and ``polrig`` can only come from the wheel.

From a folder holding the user's packages (the current folder is first on ``sys.path``, as
for any ``python -m``), with no ``PYTHONPATH``: ``python -m polrig sim render``, ``polrig infer``
of the render, a small ``polrig capture`` and ``polrig info`` of it succeed, and the user's
packages still import as theirs, beside polrig's own.
"""

from __future__ import annotations

import importlib.metadata
import os
import pathlib
import re
import shutil
import subprocess
import sys
import textwrap
import tomllib
import zipfile

import pytest
from test_architecture import PACKAGE_DIRS, _files

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

REPO = pathlib.Path(__file__).resolve().parents[1]
USER_PACKAGES = ("models", "sim", "calibration", "drivers")
#: A module of each of polrig's packages of those names: the user's package has one too,
#: which fails on import (polrig importing the user's package instead of its own).
TRAPS = {"models": "runtime", "sim": "devices", "calibration": "calset",
         "drivers": "genicam_camera"}


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(v) for v in re.findall(r"\d+", text)[:3])


def setuptools_folder() -> pathlib.Path:
    """The folder of the newest setuptools this environment can import (a virtual environment
    may hold an old one of its own before its dependencies' newer one), which must be at least
    the one ``[build-system] requires``."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text("utf-8"))
    requires = pyproject["build-system"]["requires"]
    minimum = next(_version(r) for r in requires if re.match(r"setuptools\s*>=", r))
    found = [(_version(d.version), pathlib.Path(d.locate_file("")))
             for d in importlib.metadata.distributions(name="setuptools")]
    best = max(found, default=None)
    if best is None or best[0] < minimum:
        pytest.fail(f"building the wheel needs setuptools >= {'.'.join(map(str, minimum))} "
                    f"(pyproject.toml); this environment has {sorted(v for v, _ in found)}")
    return best[1]


def clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONSAFEPATH",
                        "VIRTUAL_ENV", "PIP_REQUIRE_VIRTUALENV")}
    env["PYTHONNOUSERSITE"] = "1"
    env.update(extra)
    return env


def run(argv, *, cwd, env, timeout=600) -> subprocess.CompletedProcess:
    out = subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True,
                         text=True, timeout=timeout)
    assert out.returncode == 0, (f"{' '.join(map(str, argv))} (in {cwd}) exited "
                                 f"{out.returncode}\nstdout:\n{out.stdout}\nstderr:\n{out.stderr}")
    return out


def build_wheel(tmp: pathlib.Path) -> pathlib.Path:
    """``pip wheel`` of a copy of the sources (the build writes ``build/`` and
    ``*.egg-info`` next to them), with this environment's setuptools."""
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build", "dist")
    for name in ("pyproject.toml", "README.md", *sorted(p.name for p in REPO.glob("LICEN[CS]E*"))):
        shutil.copy2(REPO / name, src / name)
    for folder in sorted(set(PACKAGE_DIRS.values())):
        shutil.copytree(REPO / folder, src / folder, ignore=ignore)
    dist = tmp / "dist"
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "--no-index", "--disable-pip-version-check", "-q", "-w", dist, src], cwd=tmp,
        env=clean_env(PYTHONPATH=str(setuptools_folder())))
    wheels = sorted(dist.glob("polrig-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def check_wheel_contents(wheel: pathlib.Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    info = [t for t in top if t.endswith(".dist-info")]
    assert len(info) == 1 and re.fullmatch(r"polrig-[^-/]+\.dist-info", info[0]), top
    assert top == {"polrig", info[0]}, f"top-level names besides polrig: {sorted(top)}"
    # every module of the distribution (tests/test_architecture.py's list), under polrig/
    for module, path in _files().items():
        tail = "/__init__.py" if path.name == "__init__.py" else ".py"
        rel = "/".join(module.split(".")) + tail
        assert rel in names, f"{rel} ({path.relative_to(REPO)}) is not in the wheel"
    # the shipped models of every size (polrig.models.sizes: the small one in models/weights,
    # the large one in models/weights/large once a GPU lease shipped it): their graphs and JSON
    # files; never a training checkpoint (read by the training code only, which needs torch)
    models = REPO / "models"
    weights = sorted(p.relative_to(models).as_posix() for p in (models / "weights").rglob("*")
                     if p.suffix in (".onnx", ".json"))
    assert "weights/single_shot.onnx" in weights and "weights/model.json" in weights
    for w in weights:
        assert f"polrig/models/{w}" in names, f"models/{w} is not in the wheel"
    assert not [n for n in names if n.endswith(".pt")], "a training checkpoint is in the wheel"
    assert "polrig/models/MODEL_CARD.md" in names
    entry_points = zipfile.ZipFile(wheel).read(f"{info[0]}/entry_points.txt").decode()
    assert re.search(r"^polrig\s*=\s*polrig\.cli:main\s*$", entry_points, re.M), entry_points


def borrowed_site_folders() -> list[str]:
    """This environment's folders of installed packages (its own and those its ``.pth`` files
    add), without the editable install's sources or anything else that is no package folder."""
    out = []
    for p in sys.path:
        parts = pathlib.Path(p).parts
        if p and ("site-packages" in parts or "dist-packages" in parts) and os.path.isdir(p) \
                and p not in out:
            out.append(p)
    return out


def make_venv(tmp: pathlib.Path, wheel: pathlib.Path) -> pathlib.Path:
    """A new virtual environment with the wheel installed, then this environment's
    dependencies borrowed; returns its ``bin`` folder."""
    venv = tmp / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp, env=clean_env())
    scripts = venv / ("Scripts" if os.name == "nt" else "bin")
    python = scripts / ("python.exe" if os.name == "nt" else "python")
    # pip of this environment, run by the new interpreter: it sees only the new environment
    run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index",
         "--disable-pip-version-check", "-q", wheel], cwd=tmp, env=clean_env())
    purelib = run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                  cwd=tmp, env=clean_env()).stdout.strip()
    assert pathlib.Path(purelib).is_relative_to(venv)
    (pathlib.Path(purelib) / "zz_borrowed_dependencies.pth").write_text(
        "".join(f"{p}\n" for p in borrowed_site_folders()))
    return scripts


def user_folder(tmp: pathlib.Path) -> pathlib.Path:
    """A folder of the user's own packages named as polrig's, each with a marker."""
    home = tmp / "user"
    for name in USER_PACKAGES:
        pkg = home / name
        pkg.mkdir(parents=True)
        (pkg / "__init__.py").write_text(f'WHO = "the user\'s {name}"\n')
        (pkg / f"{TRAPS[name]}.py").write_text(
            f'raise ImportError("the user\'s {name}.{TRAPS[name]} was imported")\n')
    (home / "rig.toml").write_text(textwrap.dedent("""\
        # the simulated rig, small and on a virtual clock
        [sim]
        size = [64, 64]
        clock_speed = inf
        """))
    return home


CHECK_IMPORTS = textwrap.dedent("""\
    import pathlib, sys
    import calibration, drivers, models, sim
    import polrig, polrig.calibration, polrig.drivers, polrig.models, polrig.sim
    import polrig.calibration.calset, polrig.drivers.genicam_camera, polrig.models.runtime
    import polrig.sim.devices
    venv = pathlib.Path(sys.argv[1]).resolve()
    for name in ("models", "sim", "calibration", "drivers"):
        user, ours = sys.modules[name], sys.modules["polrig." + name]
        assert user.WHO == "the user's " + name, (name, user)
        assert pathlib.Path(user.__file__).resolve().parent == pathlib.Path.cwd() / name
        assert user is not ours and not hasattr(ours, "WHO")
        assert pathlib.Path(ours.__file__).resolve().is_relative_to(venv), ours.__file__
    assert pathlib.Path(polrig.__file__).resolve().is_relative_to(venv), polrig.__file__
    print("imports ok")
    """)


def test_the_installed_wheel_runs_beside_the_users_own_packages(tmp_path):
    wheel = build_wheel(tmp_path)
    check_wheel_contents(wheel)
    scripts = make_venv(tmp_path, wheel)
    python, polrig_script = scripts / "python", scripts / "polrig"
    assert polrig_script.is_file(), "the wheel's console script was not installed"
    home = user_folder(tmp_path)
    # the kernels compile in the new environment (its first solve): unoptimised, since what is
    # tested here is the installed package, not the kernels' speed (NUMBA_OPT=0: about 40 %
    # less compile time, the same results to rounding)
    env = clean_env(NUMBA_OPT="0")

    # where polrig comes from in the new environment: the wheel, never the sources
    where = run([python, "-c", "import polrig; print(polrig.__file__)"], cwd=home, env=env)
    assert pathlib.Path(where.stdout.strip()).is_relative_to(tmp_path / "venv"), where.stdout
    assert not pathlib.Path(where.stdout.strip()).is_relative_to(REPO / "polrig")

    run([python, "-m", "polrig", "sim", "render", "--size", "64x64", "--seed", "3",
         "--out", "render"], cwd=home, env=env)
    frame = home / "render" / "pose0000p00_state00.png"
    assert frame.is_file() and (home / "render" / "truth.json").is_file()

    out = run([polrig_script, "infer", frame, "--state-deg", "0", "--device", "cpu",
               "--out", "result.exr"], cwd=home, env=env)
    assert (home / "result.exr").stat().st_size > 0, out.stdout

    run([polrig_script, "capture", "--config", "rig.toml", "--poses", "0",
         "--mode", "single-shot", "--device", "cpu", "--no-progress", "--out", "session"],
        cwd=home, env=env)
    info = run([polrig_script, "info", "session"], cwd=home, env=env)
    assert "status: complete" in info.stdout and "checksums: all" in info.stdout, info.stdout

    version = run([polrig_script, "--version"], cwd=home, env=env)
    assert version.stdout.startswith("polrig ")

    check = run([python, "-c", CHECK_IMPORTS, tmp_path / "venv"], cwd=home, env=env)
    assert check.stdout.strip() == "imports ok"
