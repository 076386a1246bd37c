"""A capture's result files: writing ``mueller.exr`` and its previews atomically, scoring the
result against the simulator's truth, and recording both in the session's manifest.

The one writer and the one recorder of result files: the serial
:meth:`polrig.app.processing.Processor.process` and the workers and client of
:mod:`polrig.app.cluster` all call them."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import pathlib
from typing import Any, Mapping, Sequence

import numpy as np

from polrig.acquisition.plan import ExrChoice
from polrig.app.preview import write_result_previews
from polrig.app.session import COMPLETE, Session, sha256_file
from polrig.app.single_shot import SingleShotResult
from polrig.formats.exr import MuellerRows, write_result_exr
from polrig.sensor.layouts import MosaicLayout
from polrig.sensor.noise import SensorModel
from polrig.solve.radiometry import StateRadiance
from polrig.solve.reference import MuellerEstimate, ReferenceResult
from polrig.solve.scoring import score_on_output_grid


#: Roles of a result's PNG previews (:func:`polrig.app.preview.write_result_previews`), by the
#: suffix of their file name (``mueller_grid.png``...).
PREVIEW_ROLES = {"preview_grid": "grid", "preview_dolp": "dolp", "preview_aolp": "aolp"}
#: The channels of the manifest's ``uncertainty`` view, per plane group.
_UNCERTAINTY_CHANNELS = {"sigma": "sigma.M{row}{col}.{colour}",
                         "sigma_noise": "sigma_noise.M{row}{col}.{colour}",
                         "residual": "residual.{colour}"}


@dataclasses.dataclass(frozen=True)
class TruthScore:
    """How to score a capture's result against the simulator's truth file ``truth_path``
    (already verified): the truth as a perfect rig at the output resolution measures it
    (:func:`polrig.solve.scoring.score_on_output_grid`: ``layout``, demosaic ``method``, incident
    states ``s_in`` ``(N, 3)``, the capture's own ``states`` as weights, or for the
    single-shot method ``None`` with the noise ``model`` at ``exposure_us``)."""

    truth_path: pathlib.Path
    layout: MosaicLayout
    method: str
    s_in: np.ndarray
    states: Sequence[StateRadiance] | None = None
    model: SensorModel | None = None
    exposure_us: float | None = None

    def run(self, estimate: MuellerEstimate | ReferenceResult) -> dict[str, Any]:
        """The score (:func:`polrig.solve.scoring.score_against_truth`'s keys) of ``estimate``;
        the truth file is read a band of rows at a time (:class:`polrig.formats.exr.MuellerRows`),
        its ``object_mask`` plane whole."""

        with MuellerRows(self.truth_path) as truth:
            obj = truth.plane("object_mask")  # output pixels whose whole support lies on it
            return score_on_output_grid(estimate, truth, self.layout, self.method, self.s_in,
                                        self.states, model=self.model,
                                        exposure_us=self.exposure_us, object_mask=obj)


@dataclasses.dataclass
class CaptureResult:
    """One capture solved by :meth:`Processor.solve`: ``relpath`` (inside the session,
    ``<capture>/mueller.exr`` or ``<capture>/<revision>/mueller.exr``), ``result`` the solve's
    arrays (the reference solve's or the single-shot route's), ``metadata`` the EXR header's
    polrig entries, ``truth`` how to score it against the simulator's truth (``None`` without a
    truth file), ``extra_planes`` further planes of its EXR. :func:`write_and_score` writes and
    scores it."""

    relpath: str
    result: ReferenceResult | SingleShotResult | MuellerEstimate
    metadata: dict[str, Any]
    truth: TruthScore | None
    #: planes written beside :func:`polrig.formats.exr.result_planes`' (name -> ``(H, W)`` array): the
    #: single-shot ``beyond_calibration.{colour}`` flags, with the ``sigma`` group
    #: (:meth:`polrig.app.single_shot.SingleShotResult.extra_planes`)
    extra_planes: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    #: hybrid: the prior's record for the manifest (:class:`polrig.app.manifest.PriorRecord`)
    prior: dict[str, Any] | None = None
    #: single-shot and hybrid: the network's model for the manifest (:class:`polrig.app.manifest.ModelRecord`)
    model: dict[str, Any] | None = None


def write_result_files(root: pathlib.Path, out: CaptureResult, exr: ExrChoice, *,
                       replace: bool = False) -> dict[str, dict[str, Any]]:
    """Write ``out``'s ``mueller.exr`` (the planes and compression of ``exr``) and its PNG
    previews next to it (``mueller_grid.png``, ``mueller_dolp.png``, ``mueller_aolp.png``:
    :func:`polrig.app.preview.write_result_previews`, from the arrays in memory, every
    :func:`polrig.app.preview.preview_stride`-th pixel of a large result) under ``root``,
    each atomically (temporary name in its folder, then renamed); return their records by
    role (``mueller`` and :data:`PREVIEW_ROLES`: ``path``, ``sha256`` hashed from the file
    as it lies on disk, streamed, ``bytes``). The file's bytes are never held in memory.

    ``replace=False`` refuses (``FileExistsError``) a result file already there (session data
    is never overwritten); a worker of :mod:`polrig.app.cluster` passes ``True``: a file there is
    the unrecorded output of an attempt that died, replaced by identical bytes. The one
    writer of result files, serial (:meth:`polrig.app.processing.Processor.process`) and distributed alike."""

    path = new_result_path(root, out.relpath, replace)
    res = out.result
    rel = pathlib.PurePosixPath(out.relpath).parent
    previews = {role: path.with_name(f"{path.stem}_{suffix}.png")
                for role, suffix in PREVIEW_ROLES.items()}
    written = {"mueller": path, **previews}
    try:
        write_result_exr(path, res, planes=exr.planes, uncertainty=exr.uncertainty,
                         compression=exr.compression, extra=out.extra_planes, metadata=out.metadata)
        made = write_result_previews(res.mueller, path.parent, stem=path.stem, flags=res.mask)
        if sorted(made) != sorted(previews.values()):  # pragma: no cover - preview's contract
            raise RuntimeError(f"previews {made} are not the expected {previews}")
        return {role: file_record(root, (rel / p.name).as_posix())
                for role, p in written.items()}
    except BaseException:  # no partial result left behind (each file is whole or absent)
        remove_files(written.values())
        raise


def write_and_score(root: pathlib.Path, out: CaptureResult, exr: ExrChoice, *,
                    replace: bool = False
                    ) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None]:
    """Write ``out``'s result files (:func:`write_result_files`), then score it against the
    truth (``out.truth``; ``None`` without one); return the files' records and the score.

    Consumes ``out``: once the files are written, ``out.result`` is replaced by its
    :class:`polrig.solve.reference.MuellerEstimate`, so that the diagnostic planes are released
    before the truth is read (the peak memory of a scored full-sensor pose is the solve's,
    not the solve's plus the truth's). A score that fails removes the files just written.
    The serial :meth:`polrig.app.processing.Processor.process` and the workers of :mod:`polrig.app.cluster` both call
    it."""
    records = write_result_files(root, out, exr, replace=replace)
    if out.truth is None:
        return records, None
    if not isinstance(out.result, MuellerEstimate):
        out.result = out.result.estimate()
    try:
        return records, out.truth.run(out.result)
    except BaseException:
        remove_files(pathlib.Path(root) / r["path"] for r in records.values())
        raise


def remove_files(paths) -> None:
    """Delete ``paths`` where they exist (best effort: a failure to delete is ignored)."""
    for p in paths:
        with contextlib.suppress(OSError):
            pathlib.Path(p).unlink(missing_ok=True)


def new_result_path(root: pathlib.Path, relpath: str, replace: bool = False) -> pathlib.Path:
    """``root/relpath`` with its folder made; ``FileExistsError`` if a file is there (unless
    ``replace``): session data is never overwritten."""
    path = pathlib.Path(root) / relpath
    if path.exists() and not replace:
        raise FileExistsError(f"{path}: refusing to overwrite session data")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def file_record(root: pathlib.Path, relpath: str) -> dict[str, Any]:
    """The manifest record (``path``, ``sha256``, ``bytes``) of a file written under ``root``,
    hashed by streaming it from disk (:func:`polrig.app.session.sha256_file`)."""
    path = pathlib.Path(root) / relpath
    return {"path": pathlib.PurePosixPath(relpath).as_posix(), "sha256": sha256_file(path),
            "bytes": path.stat().st_size}


def record_result(session: Session, index: int, revision: str | None,
                  records: dict[str, dict[str, Any]], score: dict[str, Any] | None,
                  exr: ExrChoice = ExrChoice(), prior: Mapping[str, Any] | None = None,
                  model: Mapping[str, Any] | None = None,
                  model_map: bool = False) -> None:
    """Record capture ``index``'s written result files (``records`` by role, as
    :func:`write_result_files` returns: ``mueller`` and its previews) with the ``mueller``
    file's ``uncertainty`` and ``mask`` views (of the planes ``exr`` wrote; no view of planes
    not written), and in ``revision`` (if given) its score and status ``complete``; save the
    manifest (under ``session.mutex``: the next capture's acquisition writes the manifest
    meanwhile). ``prior``: a hybrid result's prior model (:class:`polrig.app.manifest.PriorRecord`),
    recorded beside its files, as is ``model``, the network's model of a single-shot or hybrid
    result (:class:`polrig.app.manifest.ModelRecord`). ``model_map``: the file holds the model selection's
    planes (``models`` view). The one place a result enters a manifest: the serial
    :meth:`polrig.app.processing.Processor.process` and the client of :mod:`polrig.app.cluster` (whose workers write
    the files) both call it."""
    with session.mutex:
        cap = session.capture(index)
        entry = cap if revision is None else cap["revisions"][revision]
        files = entry["files"]
        clash = [role for role in records if role in files]
        if clash:
            raise FileExistsError(f"capture {index} already has a {clash[0]!r} file")
        before = copy.deepcopy(entry)
        path = records["mueller"]["path"]
        files.update({role: dict(rec) for role, rec in records.items()})
        sigma = [c for p, c in _UNCERTAINTY_CHANNELS.items() if p in exr.planes]
        if sigma:
            files["uncertainty"] = {"part_of": "mueller", "path": path,
                                    "channels": ", ".join(sigma)}
        if "mask" in exr.planes:
            files["mask"] = {"part_of": "mueller", "path": path,
                             "channels": "mask.{colour} (reason bits, 0 = valid)"}
        if model_map:
            files["models"] = {"part_of": "mueller", "path": path,
                               "channels": "model.{colour} (codes in the header's "
                                           "model_selection), model_chi2.{colour}, model_p.{colour}; "
                                           "with --models diffuse also specular.{colour}"}
        if prior is not None:
            entry["prior"] = dict(prior)
        if model is not None:
            entry["model"] = dict(model)
        if revision is not None:
            entry.update(status=COMPLETE, score=score)
        try:
            session.save()
        except BaseException:  # not recorded after all: the manifest in memory says so too
            entry.clear()
            entry.update(before)
            raise
