"""The GenTL test producer's camera (``viky.cti``, shipped in the ``genicam`` wheel) as the
``[camera]`` table of a rig config, shared by the tests that open a real-driver rig."""

from __future__ import annotations

from pathlib import Path

import genicam

VIKY = Path(genicam.__file__).parent / "viky.cti"


def viky_camera(serial: str = "0", roi: tuple[int, int] = (128, 100),
                layout: str | None = "imx250mzr") -> str:
    """The ``[camera]`` table (TOML text, no indentation) of device ``serial`` of the test
    producer: Mono8 at 200 Hz, an ``roi`` of (width, height) at the origin, ``layout`` (none:
    the config's default)."""
    text = (f'[camera]\ndriver = "genicam"\ncti = "{VIKY}"\nserial = "{serial}"\n'
            f'pixel_format = "Mono8"\nframe_rate_hz = 200.0\nroi = [{roi[0]}, {roi[1]}, 0, 0]\n')
    return text + (f'layout = "{layout}"\n' if layout else "")
