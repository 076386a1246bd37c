"""Which onnxruntime execution provider runs the single-shot graph (CPU or CUDA).

``auto`` takes CUDA when the installed onnxruntime offers it (the ``gpu`` extra installs
``onnxruntime-gpu``, which does) and the NVIDIA driver reports a device (:func:`cuda_device_count`),
and the CPU otherwise; ``cpu`` and ``cuda`` force one. A forced
``cuda`` that this onnxruntime cannot offer is refused before any work (:class:`DeviceUnavailable`,
one line, exit 2). The CPU provider always follows CUDA in the list: onnxruntime assigns an
operator CUDA has no kernel for to the next provider, and a CUDA provider that fails to start
(no driver, a library missing) leaves the session on the CPU with only a warning, so the
provider a session *actually* uses is read back from it (:func:`used_device`) and a forced
``cuda`` session that ended on the CPU is refused as well (:func:`check_session`).

Pure functions of the provider lists (and of what a session reports of its options,
:func:`accepted_options`), so the selection and fallback logic is tested on a CPU-only machine
with the real ``onnxruntime.get_available_providers()`` and real sessions.
"""

from __future__ import annotations

from collections.abc import Sequence

from polrig.errors import ConfigError

CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"
#: ``--device`` choices and the provider each names (``auto``: the first available of CUDA, CPU).
DEVICES = {"cpu": CPU, "cuda": CUDA}
CHOICES = ("auto", *DEVICES)


class DeviceUnavailable(ConfigError):
    """A forced device that this onnxruntime cannot run on (exit 2)."""


def cuda_device_count() -> int:
    """NVIDIA devices the driver reports (``cuDeviceGetCount`` of ``libcuda``; 0 where there is no
    driver or it fails to initialise). onnxruntime-gpu lists its CUDA provider whether or not a
    device is present, so ``auto`` asks the driver too (no torch, no CUDA runtime needed)."""
    import ctypes

    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return 0
    count = ctypes.c_int(0)
    try:
        if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
            return 0
    except AttributeError:  # pragma: no cover - not NVIDIA's driver library
        return 0
    return int(count.value)


def choose_providers(device: str, available: Sequence[str], gpus: int | None = None) -> list[str]:
    """Providers to open a session with, in priority order, for ``device`` (``auto``, ``cpu`` or
    ``cuda``) given onnxruntime's ``available`` providers (``get_available_providers()``) and the
    number of NVIDIA devices present, ``gpus`` (default :func:`cuda_device_count`, asked only where
    ``auto`` could take CUDA).

    ``auto``: ``[CUDA, CPU]`` when CUDA is available (the ``gpu`` extra) and a device is present,
    else ``[CPU]``; ``cpu``: ``[CPU]``;
    ``cuda``: ``[CUDA, CPU]`` (CPU for the operators CUDA lacks), :class:`DeviceUnavailable` when
    CUDA is not available. ``ValueError`` for another ``device``."""
    if device not in CHOICES:
        raise ValueError(f"device must be one of {', '.join(CHOICES)}, got {device!r}")
    have = set(available)
    if device == "cpu":
        return [CPU]
    if CUDA in have and device == "cuda":
        return [CUDA, CPU]
    if CUDA in have and (cuda_device_count() if gpus is None else gpus) > 0:
        return [CUDA, CPU]
    if device == "cuda":
        raise DeviceUnavailable(
            "--device cuda: this onnxruntime has no CUDA execution provider (available: "
            f"{', '.join(available) or 'none'}); install the gpu extra (pip uninstall onnxruntime && "
            "pip install 'polrig[gpu]') on a machine with an NVIDIA driver, or use --device cpu")
    return [CPU]


#: Options of the CUDA provider. ``cudnn_conv_algo_search``: onnxruntime's default, EXHAUSTIVE,
#: benchmarks every cuDNN algorithm of every convolution (``cudnnFindConvolutionForwardAlgorithmEx``)
#: when it meets a new input shape; the single-shot graph sees two shapes per frame (the
#: light-direction probe's reduced size and the frame's), and on an NVIDIA H200
#: (onnxruntime-gpu 1.31.1, 2026-11-26, ``benchmarks/results/single_shot_cuda.md``) the networks
#: took 1.1 s of a full-sensor superpixel frame warm, against 0.24 s for one repeated
#: 1224x1024x3 pass and 1.2 s for its first. HEURISTIC asks cuDNN's heuristics
#: (``cudnnGetConvolutionForwardAlgorithm_v7``) instead: no benchmarking run. Reference:
#: onnxruntime's CUDA execution provider options (``OrtCUDAProviderOptions``).
#: ``use_tf32``: off. onnxruntime's CUDA provider computes float32 convolutions and matrix
#: products in TF32 by default (10-bit mantissa; PRs #19357, #19426), which moves the results
#: about 1e-3 from the CPU's; off, CUDA and CPU agree to float32 rounding, and convolutions are
#: a small share of this graph's time.
CUDA_OPTIONS = {"cudnn_conv_algo_search": "HEURISTIC", "use_tf32": "0"}
#: Asked of the CUDA provider for a session with fixed input sizes (:mod:`polrig.models.runtime`):
#: the whole graph captured once and replayed (one launch instead of ~1500). onnxruntime takes it
#: only when every node runs on CUDA (no Memcpy node: why ``Acos`` left the graph) and the run
#: binds its inputs and outputs at fixed device addresses; it may refuse (:func:`accepted_options`).
CUDA_GRAPH_OPTION = {"enable_cuda_graph": "1"}


def session_providers(providers: Sequence[str], cuda_graph: bool = False) -> list[tuple[str, dict[str, str]]]:
    """``providers`` (:func:`choose_providers`) with each one's options, as
    ``onnxruntime.InferenceSession(providers=...)`` takes them (:data:`CUDA_OPTIONS` for CUDA, with
    :data:`CUDA_GRAPH_OPTION` when ``cuda_graph``; none for the CPU)."""
    cuda = dict(CUDA_OPTIONS, **(CUDA_GRAPH_OPTION if cuda_graph else {}))
    return [(p, dict(cuda) if p == CUDA else {}) for p in providers]


def accepted_options(requested: dict[str, str], reported: dict[str, str] | None,
                     error: str | None = None) -> tuple[dict[str, str], list[str]]:
    """What a provider really runs with: ``(options, notes)`` from the options ``requested`` of
    it, those the session ``reported`` (``InferenceSession.get_provider_options()[provider]``;
    None: the provider did not start) and the ``error`` onnxruntime raised when the options were
    tried (creating the session or its first run), if any.

    ``options``: each requested option as the provider reports it (the requested value where it
    reports nothing). ``notes``: one line per refusal: the error (every requested option counts
    as refused then: the caller runs without them), or an option the provider reports with
    another value. Pure, so the refusal path is tested without a GPU."""
    if error is not None:
        why = (str(error).strip().splitlines() or ["refused"])[0][:200]
        asked = ", ".join(f"{k}={v}" for k, v in requested.items())
        return {}, [f"onnxruntime refused {asked} ({why}); running without"]
    if reported is None:
        return {}, ["the provider did not start: none of its options apply"]
    options, notes = {}, []
    for k, v in requested.items():
        got = str(reported.get(k, v))
        options[k] = got
        if got != str(v):
            notes.append(f"onnxruntime runs {k}={got} (asked {v})")
    return options, notes


def load_cuda_libraries(ort_module) -> None:
    """Load the CUDA and cuDNN libraries onnxruntime-gpu needs from NVIDIA's pip packages
    (``nvidia-cuda-runtime``, ``nvidia-cudnn-cu13``, ...; the ``gpu`` extra installs them), before
    a CUDA session opens. onnxruntime-gpu >= 1.21 offers ``preload_dlls`` for this; an older one,
    or a machine whose CUDA is installed system-wide (found through the loader's paths), needs
    nothing. Without it a pip-installed CUDA is not found and the CUDA provider fails to start.
    What it reports (libraries it could not load) goes to stderr."""
    import contextlib
    import sys

    preload = getattr(ort_module, "preload_dlls", None)  # a version difference of onnxruntime, not ours
    if preload is not None:
        # it prints what it could not load on stdout, where a command's own output goes
        with contextlib.redirect_stdout(sys.stderr):
            preload(cuda=True, cudnn=True, msvc=False)


def used_device(session_providers: Sequence[str]) -> str:
    """The provider that runs a session's graph: the first of the providers the session reports
    (``InferenceSession.get_providers()``: the ones it really registered, in priority order)."""
    if not session_providers:
        raise ValueError("a session with no execution provider")
    return session_providers[0]


def check_session(device: str, requested: Sequence[str], session_providers: Sequence[str]) -> str:
    """The provider a session opened with ``requested`` really uses; :class:`DeviceUnavailable`
    when ``device`` forced CUDA and the session fell back to the CPU (CUDA listed as available
    but failing to start: no driver, a missing CUDA or cuDNN library). With ``auto`` such a
    fallback is accepted: the CPU runs it, and the provider used says so."""
    used = used_device(session_providers)
    if device == "cuda" and used != CUDA:
        raise DeviceUnavailable(f"--device cuda: the CUDA execution provider did not start (the session runs on "
                                f"{used}; requested {', '.join(requested)}): check the NVIDIA driver and the "
                                "CUDA/cuDNN libraries onnxruntime-gpu needs, or use --device cpu")
    return used


def short_name(provider: str) -> str:
    """``cuda`` / ``cpu`` / the provider's own name for another one (for one-line reports)."""
    return {v: k for k, v in DEVICES.items()}.get(provider, provider)
