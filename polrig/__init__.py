"""polrig: drive a DoFP polarimetric imaging rig and turn its captures into Mueller matrices.

Conventions (angles, Stokes frames, Mueller layout) are written once in
``docs/conventions.md``; :mod:`polrig.optics.conventions` holds the version string.

The Python API (``docs/api.md``) is this package's public face: :func:`open_session`,
:func:`open_result` (sessions and result files as lazily loaded ``xarray.Dataset`` s,
:mod:`polrig.app.dataset`), :func:`run_capture` with its :class:`CaptureRequest` and
:class:`SampleMetadata` (the one capture call of ``polrig capture`` and the GUI,
:mod:`polrig.app.capture`). They live in the app layer; this package (layer 0) re-exports them
lazily, by the module ``__getattr__`` below, which imports their module on first access:
``import polrig`` imports nothing of the layers above it. ``tests/test_architecture.py`` holds
this table as the one declared public face and checks it.
"""

__version__ = "0.1.0"

#: The public face: name -> the module that defines it (imported on first access).
PUBLIC_FACE = {
    "open_session": "polrig.app.dataset",
    "open_result": "polrig.app.dataset",
    "run_capture": "polrig.app.capture",
    "CaptureRequest": "polrig.app.capture",
    "SampleMetadata": "polrig.app.manifest",
    "export": "polrig.app.export",
    "normals_from_mueller": "polrig.optics.shape_from_polarization",
}

__all__ = ["__version__", *PUBLIC_FACE]


def __getattr__(name: str):
    module = PUBLIC_FACE.get(name)
    if module is None:
        raise AttributeError(f"module 'polrig' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once: the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *PUBLIC_FACE})
