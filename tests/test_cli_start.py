"""``polrig``'s start-up: building the parser (every command's ``register``) imports no heavy
module (docs/architecture.md, "Command-line start-up"), and the vocabularies the parser declares
from :mod:`polrig.choices` are those of the modules that use them.

The import checks run in a fresh interpreter and look at ``sys.modules``: robust, not timed
(the times are in ``python -m benchmarks cli_start``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

#: Third-party modules the parser must not import: the GUI toolkit, the network runtimes and
#: training stack, the numerical and image stacks, the cluster and labelled-array libraries.
HEAVY_THIRD_PARTY = ("PySide6", "onnxruntime", "torch", "numba", "dask", "distributed", "xarray",
                     "mitsuba", "numpy", "scipy", "cv2", "OpenEXR", "Imath", "tqdm", "zarr",
                     "tifffile", "serial", "usb")
#: polrig layers the parser must not import (everything but the foundation, the argument types
#: of ``polrig.formats.argcheck`` and the model-size names of ``polrig.models.sizes``).
HEAVY_POLRIG = ("polrig.optics", "polrig.sensor", "polrig.solve", "polrig.acquisition",
                "polrig.drivers", "polrig.sim", "polrig.calibration", "polrig.app", "polrig.gui")
#: The light modules of otherwise heavy packages that the parser uses.
LIGHT_EXCEPTIONS = ("polrig.formats", "polrig.formats.argcheck", "polrig.models",
                    "polrig.models.sizes")

_PROBE = """
import json, sys
import polrig.cli
argv = json.loads(sys.argv[1])
parser = polrig.cli.build_parser()
if argv is not None:
    try:
        parser.parse_args(argv)
    except SystemExit:
        pass
print(json.dumps(sorted(sys.modules)))
"""


def _modules_after(argv: list[str] | None) -> list[str]:
    """Every module in ``sys.modules`` of a fresh interpreter after building the parser (and
    parsing ``argv``, without running the command)."""
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(argv)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def _heavy(modules: list[str]) -> list[str]:
    def heavy(m: str) -> bool:
        if m.split(".")[0] in HEAVY_THIRD_PARTY:
            return True
        if m in LIGHT_EXCEPTIONS:
            return False
        return any(m == p or m.startswith(p + ".") for p in
                   HEAVY_POLRIG + ("polrig.models", "polrig.formats"))
    return [m for m in modules if heavy(m)]


@pytest.mark.parametrize("argv", [
    None,  # build_parser() alone
    ["--version"],
    ["--help"],
    ["infer", "--help"],
    ["gui", "--help"],
    ["sim", "render", "--help"],
    ["infer", "frame.png", "--state-deg", "0", "--out", "out.exr", "--device", "cuda"],
    ["stokes", "frame.png", "--out", "out.exr", "--layout", "imx250myr", "--demosaic", "newton"],
    ["capture", "--poses", "0", "--out", "s", "--exr-compression", "piz", "--network-binning", "2"],
    ["info", "session"],
], ids=lambda a: "build_parser" if a is None else " ".join(a))
def test_building_and_parsing_imports_nothing_heavy(argv):
    modules = _modules_after(argv)
    assert "polrig.cli.commands.gui" in modules  # every command registered
    heavy = _heavy(modules)
    roots = sorted({".".join(m.split(".")[:2 if m.startswith("polrig.") else 1]) for m in heavy})
    assert not heavy, f"building the parser imported {roots} ({len(heavy)} modules)"


def test_the_heavy_check_sees_a_heavy_import():
    """The check itself: a module of each kind it must catch is caught, the light ones are not."""
    assert _heavy(["numpy.core", "PySide6", "polrig.sim.scene", "polrig.app", "polrig.models.runtime",
                   "polrig.formats.exr"]) == ["numpy.core", "PySide6", "polrig.sim.scene",
                                              "polrig.app", "polrig.models.runtime",
                                              "polrig.formats.exr"]
    assert _heavy(["argparse", "polrig", "polrig.choices", "polrig.errors", "polrig.cli",
                   *LIGHT_EXCEPTIONS]) == []


# -- the declared vocabularies are the users' ------------------------------------------------------
def _options(parser: argparse.ArgumentParser, *path: str) -> dict[str, argparse.Action]:
    for name in path:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return {s: a for a in parser._actions for s in a.option_strings}


def test_the_parser_offers_what_the_library_accepts():
    """Each choice list and default the parser takes from :mod:`polrig.choices` is the one the
    module that acts on it holds (where that module keeps heavy values, only the names are in
    ``polrig.choices``: these can drift apart, and this test says so)."""
    import polrig.cli
    from polrig.acquisition.plan import NETWORK_BINNINGS
    from polrig.formats.exr import COMPRESSIONS, PLANE_GROUPS, UNCERTAINTY_PRECISIONS
    from polrig.formats.ome import UNITS
    from polrig.gui.app import DEFAULT_SIM_SIZE
    from polrig.models.sizes import CHOICES as MODEL_SIZES
    from polrig.sensor.demosaic import METHODS
    from polrig.sensor.layouts import LAYOUTS
    from polrig.sim.materials import MATERIAL_MIXES
    from polrig.sim.scene import SCENES, make_scene
    from polrig.solve.reference import MIN_SNR

    parser = polrig.cli.build_parser()
    stokes = _options(parser, "stokes")
    assert stokes["--layout"].choices == sorted(LAYOUTS)
    assert tuple(stokes["--demosaic"].choices) == METHODS
    for command in ("capture", "infer", "reconstruct"):
        assert tuple(_options(parser, command)["--demosaic"].choices) == METHODS
    assert stokes["--min-snr"].default == MIN_SNR
    capture = _options(parser, "capture")
    assert tuple(capture["--exr-compression"].choices) == tuple(COMPRESSIONS)
    assert tuple(capture["--exr-uncertainty"].choices) == tuple(UNCERTAINTY_PRECISIONS)
    assert ",".join(PLANE_GROUPS) in capture["--exr-planes"].help
    assert tuple(capture["--network-binning"].choices) == NETWORK_BINNINGS
    assert tuple(capture["--model-size"].choices) == MODEL_SIZES
    assert tuple(_options(parser, "infer")["--network-binning"].choices) == NETWORK_BINNINGS
    assert tuple(_options(parser, "export")["--unit"].choices) == tuple(UNITS)
    assert _options(parser, "gui")["--sim-size"].default == DEFAULT_SIM_SIZE
    render, dataset = _options(parser, "sim", "render"), _options(parser, "sim", "dataset")
    assert tuple(render["--scene"].choices) == SCENES
    assert tuple(dataset["--materials"].choices) == tuple(MATERIAL_MIXES)
    make_scene(SCENES[-1], 16, 16)  # the last name offered is a scene the simulator makes
