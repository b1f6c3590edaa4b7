"""Projector codes without a calibration: per-pixel projector column/row maps of Gray-code
and phase-shifting views.

The column and row a Gray-code (or phase-shifting) decoder reads at each camera pixel are
the most reused output of such a decoder (camera-projector calibration, matching two
cameras through the projector); they need no calibration. This module turns a
:class:`~slscan.decode.graycode.GrayResult` (or a phase decode) into
:class:`ProjectorCodes`, writes them as maps with a small JSON per view, reads them back
(:func:`read_codes`), and says what limited the share of decoded pixels (:func:`valid_share`).

Files, in the decode output folder (``slscan decode SESSION --out DIR --codes``)::

    DIR/projector_codes.json      manifest: session, projector size, sentinel, encoding, views
    DIR/VIEW/columns.png          Gray code: 16-bit grey projector column, 65535 where not decoded
    DIR/VIEW/rows.png             16-bit grey: projector row, 65535 where not decoded
                                  (absent when the set has no row codes)
    DIR/VIEW/columns.tiff         phase shifting, instead: 32-bit float sub-pixel projector
    DIR/VIEW/rows.tiff            column / row (pixel centres at whole numbers), NaN where not
                                  decoded (``"encoding": "float32-tiff"`` in the JSON files)
    DIR/VIEW/mask.png             8-bit grey: 255 where the column and the row decoded
    DIR/VIEW/codes.json           projector size, bits, valid share, noise, what limited it
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slscan import __version__
from slscan.capture.session import SESSION_FILE, Session, ViewRecord, load_session
from slscan.decode.budget import fit_workers, warn_if_lossy
from slscan.decode.graycode import GrayResult, decode_gray, gray_pairs
from slscan.decode.masks import full_scale
from slscan.errors import SlscanError, about_file
from slscan.executor import LOCAL, Executor
from slscan.fsio import (
    atomic_output_dir,
    read_float_tiff,
    read_json,
    read_png,
    write_float_tiff,
    write_json,
    write_png,
)
from slscan.patterns import families_in

log = logging.getLogger(__name__)

CODES_FORMAT = "slscan.projector-codes"
CODES_VERSION = 1
MANIFEST = "projector_codes.json"
VIEW_FILE = "codes.json"
INVALID = 65535
"""Value of ``columns.png`` and ``rows.png`` where nothing decoded (projectors up to 65535 px)."""
PNG_ENCODING = "uint16-png"
FLOAT_ENCODING = "float32-tiff"
"""How the column and row maps are stored: 16-bit PNG of whole projector pixels (Gray code;
the files say nothing, as before there was a choice), or 32-bit float TIFF of sub-pixel
coordinates with NaN where not decoded (phase shifting: ``"encoding"`` says so)."""
MIN_CONTRAST = 0.03
NOISE_SIGMAS = 3.0
"""The defaults of :func:`~slscan.decode.graycode.decode_gray_images` the estimate assumes."""
CODES_ONLY = "projector codes are written for Gray-code and phase-shifting pattern sets only"


@dataclass(frozen=True)
class ValidShare:
    """How many camera pixels decoded, and what the others lost to.

    decoded : share of all camera pixels whose column (and row) decoded (the mask)
    lit : share of all camera pixels lit by the projector (white - black above 3 % of
        full scale); the pixels the decoder tried
    noise_dn : standard deviation of ``pattern - inverse``, in digital numbers of the captures
    low_contrast : share of the lit pixels lost because white - black is below the noise
        threshold (``3 sigma``): too dark a surface, or too much noise
    weak_bits : share of the lit pixels lost because some bit's ``|pattern - inverse|``
        stayed under the threshold (stripe edges, blur, inter-reflections); when
        ``out_of_range`` is None it also holds codes beyond the projector's size
    out_of_range : share of the lit pixels whose code lies beyond the projector's size,
        when the decoder reports it apart (None otherwise)
    unreliable : share of the lit pixels left out by robust decoding: a bit global light
        may have flipped, or a code disagreeing with its neighbours (0 without it)
    source : {"decoder", "estimated"}: counts reported by the decoder
        (``GrayResult.diagnostics``), or estimated here from the decoder's contrast, noise
        and mask with its default thresholds
    """

    decoded: float
    lit: float
    noise_dn: float
    low_contrast: float
    weak_bits: float
    out_of_range: float | None
    source: str
    unreliable: float = 0.0

    @property
    def limited_by(self) -> str:
        """{"weak bits", "low contrast", "nothing"}: what lost the most lit pixels."""
        if max(self.low_contrast, self.weak_bits) <= 0:
            return "nothing"
        return "weak bits" if self.weak_bits >= self.low_contrast else "low contrast"

    def describe(self) -> str:
        """One line for the decode summary."""
        lost = f"{self.low_contrast:.1%} to low contrast, {self.weak_bits:.1%} to weak bits"
        if self.out_of_range is not None:
            lost += f", {self.out_of_range:.1%} out of range"
        if self.unreliable:
            lost += f", {self.unreliable:.1%} unreliable (global light, inconsistent codes)"
        return (
            f"{self.decoded:.1%} of pixels decoded ({self.lit:.1%} lit); noise {self.noise_dn:.1f} DN; "
            f"lit pixels lost {lost} (most: {self.limited_by})"
        )


@dataclass(frozen=True)
class ProjectorCodes:
    """The projector column and row seen by each camera pixel of one view.

    column : (h, w) int32 projector column (px), -1 where not decoded; or (phase
        shifting) float sub-pixel column, NaN where not decoded
    row : (h, w) likewise the projector row; None without row codes
    mask : (h, w) bool, the column and (when there are row codes) the row decoded
    projector_size : (width, height) px
    bits : (column bits, row bits) read; row bits 0 without row codes
    valid_share : what limited the decoded share
    """

    view: str
    column: np.ndarray
    row: np.ndarray | None
    mask: np.ndarray
    projector_size: tuple[int, int]
    bits: tuple[int, int]
    valid_share: ValidShare

    @property
    def encoding(self) -> str:
        """{"uint16-png", "float32-tiff"}: how :func:`write_view_codes` stores the maps."""
        return FLOAT_ENCODING if np.issubdtype(self.column.dtype, np.floating) else PNG_ENCODING

    def summary(self) -> dict[str, Any]:
        """The JSON-ready description written as ``VIEW/codes.json`` (files not included)."""
        h, w = self.mask.shape
        return {
            "view": self.view,
            "camera": {"width": w, "height": h},
            "projector": {"width": self.projector_size[0], "height": self.projector_size[1]},
            "bits": {"columns": self.bits[0], "rows": self.bits[1]},
            "valid_share": self.valid_share.decoded,
            "column_share": float((self.column >= 0).mean()),
            "noise_dn": self.valid_share.noise_dn,
            "limits": asdict(self.valid_share),
        }


# --- what limited the valid share ------------------------------------------------------------


def _from_diagnostics(diag: dict[str, Any], pixels: int, decoded: float) -> ValidShare:
    """A :class:`ValidShare` from the decoder's own counts (``GrayResult.diagnostics``).

    Counts above 1 are pixel counts; otherwise they are taken as shares of the lit pixels
    (``lit`` then as a share of all pixels).
    """
    if "pixels" in diag and "dark" in diag:  # the decoder's counts (GrayResult.diagnostics)
        total = float(diag["pixels"])
        lit_any = total - float(diag["dark"])  # passed the minimum contrast
        share = (lambda v: float(v) / lit_any if lit_any else 0.0)
        return ValidShare(
            decoded=decoded,
            lit=lit_any / total if total else 0.0,
            noise_dn=float(diag["noise_dn"]),
            low_contrast=share(float(diag["low_contrast"]) - float(diag["dark"])),
            weak_bits=share(float(diag["weak_bit_noise"]) + float(diag["weak_bit_ratio"])),
            out_of_range=share(diag["out_of_range"]),
            source="decoder",
            unreliable=share(float(diag.get("unreliable_global", 0)) + float(diag.get("inconsistent", 0))),
        )
    lit = float(diag["lit"])
    counts = lit > 1
    per_lit = (lambda v: float(v) / lit if lit else 0.0) if counts else float
    weak = per_lit(diag.get("weak_bit_noise", 0)) + per_lit(diag.get("weak_bit_ratio", 0))
    return ValidShare(
        decoded=decoded,
        lit=lit / pixels if counts else lit,
        noise_dn=float(diag["noise_dn"]),
        low_contrast=per_lit(diag.get("low_contrast", 0)),
        weak_bits=weak,
        out_of_range=per_lit(diag["out_of_range"]) if "out_of_range" in diag else None,
        source="decoder",
    )


def valid_share(result: GrayResult, *, scale: float | None = None) -> ValidShare:
    """What limited the share of pixels ``result`` decoded: noise, contrast, weak bits.

    scale : full scale of the captures in DN (255 for 8-bit); default: from ``result.white``
        (255 when it is absent)

    Uses the decoder's own counts when it reports them (``result.diagnostics``); otherwise
    estimates them from ``contrast``, ``noise`` and ``mask`` with the decoder's default
    thresholds: a pixel is lit when white - black > 3 % of full scale; a lit pixel is lost
    to low contrast when white - black <= 3 sigma (the bit threshold can never be met);
    the other lit pixels outside the mask lost a weak bit (or read a code beyond the
    projector).
    """
    decoded = float(result.mask.mean())
    diag = getattr(result, "diagnostics", None)
    if diag:
        return _from_diagnostics(diag, result.mask.size, decoded)
    if scale is None:
        scale = full_scale(result.white, "white") if result.white is not None else 255.0
    lit = result.contrast > MIN_CONTRAST
    n_lit = int(lit.sum())
    low = lit & (result.contrast <= NOISE_SIGMAS * result.noise)
    n_low = int(low.sum())
    n_weak = n_lit - n_low - int((result.mask & lit).sum())
    return ValidShare(
        decoded=decoded,
        lit=n_lit / lit.size,
        noise_dn=float(result.noise * scale),
        low_contrast=n_low / n_lit if n_lit else 0.0,
        weak_bits=max(n_weak, 0) / n_lit if n_lit else 0.0,
        out_of_range=None,
        source="estimated",
    )


# --- codes from a decode ---------------------------------------------------------------------


def codes_family(session: Session):
    """The family of ``session``'s patterns that gives per-pixel projector codes (the
    highest "auto" priority among them: phase shifting, then Gray code), or None."""
    for fam in families_in(session.patterns):
        if fam.decoder is not None and hasattr(fam.decode_module(), "projector_codes"):
            return fam
    return None


def has_codes(session: Session) -> bool:
    """Whether the session's patterns give per-pixel projector codes (Gray code, phase shifting)."""
    return codes_family(session) is not None


def require_codes(session: Session) -> None:
    """Raise a clear error when ``session`` has no patterns to write codes from."""
    if not has_codes(session):
        found = sorted({p.family for p in session.patterns}) or ["none"]
        raise SlscanError(
            f"{session.root / SESSION_FILE}: {CODES_ONLY}; this session's patterns are "
            f"{', '.join(found)} (decode hybrid sets to range maps with a calibration)"
        )


def codes_from_gray(result: GrayResult, session: Session, view: str) -> ProjectorCodes:
    """The :class:`ProjectorCodes` of one view's Gray-code decode (no copy of the maps)."""
    descs = [p for p in session.patterns if p.family == "gray"]
    bits = getattr(result, "bits_used", None)
    if not isinstance(bits, tuple) or len(bits) != 2:
        bits = (len(gray_pairs(descs, "columns")), len(gray_pairs(descs, "rows")))
    return ProjectorCodes(
        view=view,
        column=result.column,
        row=result.row,
        mask=result.mask,
        projector_size=tuple(session.projector_size),
        bits=(int(bits[0]), int(bits[1])),
        valid_share=valid_share(result),
    )


def decode_codes(session: Session, view: ViewRecord | str, config=None) -> ProjectorCodes:
    """Decode one view's projector codes (no calibration needed), with the family that
    gives them (:func:`codes_family`).

    config : the decode stage's :class:`~slscan.decode.pipeline.DecodeConfig` (thresholds,
        bit dropping), or None for the defaults
    """
    require_codes(session)
    view = session.view(view) if isinstance(view, str) else view
    return codes_family(session).decode_module().projector_codes(session, view, config)


# --- files -----------------------------------------------------------------------------------


def _to_u16(values: np.ndarray) -> np.ndarray:
    return np.where(values >= 0, values, INVALID).astype(np.uint16)


def write_view_codes(codes: ProjectorCodes, folder: str | os.PathLike) -> dict[str, Any]:
    """Write one view's maps and ``codes.json`` into ``folder`` (atomically, file by file):
    16-bit PNG of whole projector pixels, or float32 TIFF for sub-pixel maps (phase
    shifting; :attr:`ProjectorCodes.encoding`).

    Returns the view's summary with its file names (relative to ``folder``).
    """
    w, h = codes.projector_size
    floats = codes.encoding == FLOAT_ENCODING
    if max(w, h) >= INVALID and not floats:
        raise SlscanError(f"{folder}: a {w}x{h} projector does not fit 16-bit code maps")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ext, write, encode = ("tiff", write_float_tiff, np.asarray) if floats else ("png", write_png, _to_u16)
    files = {"columns": f"columns.{ext}", "rows": None if codes.row is None else f"rows.{ext}", "mask": "mask.png"}
    write(folder / files["columns"], encode(codes.column))
    if codes.row is not None:
        write(folder / files["rows"], encode(codes.row))
    write_png(folder / "mask.png", codes.mask.astype(np.uint8) * 255)
    summary = {"format": f"{CODES_FORMAT}.view", "version": CODES_VERSION, **codes.summary(),
               **_sentinel(codes.encoding), "files": files}
    write_json(folder / VIEW_FILE, summary)
    return summary


def _sentinel(encoding: str) -> dict[str, Any]:
    """The JSON keys saying how the maps mark pixels not decoded (Gray code's as before)."""
    if encoding == FLOAT_ENCODING:
        return {"encoding": FLOAT_ENCODING, "invalid": "NaN"}
    return {"invalid": INVALID}


def write_codes_manifest(folder: str | os.PathLike, session: Session, entries: list[dict[str, Any]], *,
                         encoding: str = PNG_ENCODING) -> None:
    """Write ``projector_codes.json``: what was decoded, how the maps are stored
    (``encoding``, :attr:`ProjectorCodes.encoding`), the sentinel, the views' folders."""
    if encoding == FLOAT_ENCODING:
        maps = ("columns.tiff / rows.tiff: 32-bit float sub-pixel projector column / row (pixel centres at "
                "whole numbers), NaN where not decoded; mask.png: 255 where the column and the row decoded")
    else:
        maps = ("columns.png / rows.png: 16-bit projector column / row, 65535 where not decoded; "
                "mask.png: 255 where the column and the row decoded")
    write_json(Path(folder) / MANIFEST, {
        "format": CODES_FORMAT, "version": CODES_VERSION, "written_by": f"slscan {__version__}",
        "session": str(Path(session.root).resolve()),
        "projector": {"width": session.projector_size[0], "height": session.projector_size[1]},
        **_sentinel(encoding),
        "maps": maps,
        "views": entries,
    })


def _map(folder: Path, name: str | None, shape: tuple[int, int] | None, dtype) -> np.ndarray | None:
    if name is None:
        return None
    image = read_float_tiff(folder / name) if dtype == np.float32 else read_png(folder / name)
    if image.ndim != 2 or image.dtype != dtype or (shape is not None and image.shape != shape):
        want = f"{shape[1]}x{shape[0]} " if shape else ""
        kind = "float TIFF" if dtype == np.float32 else "grey PNG"
        raise SlscanError(
            f"{folder / name}: expected a {want}{np.dtype(dtype).itemsize * 8}-bit {kind}, "
            f"got {image.dtype} of shape {image.shape}"
        )
    return image


def read_codes(folder: str | os.PathLike, view: str | None = None) -> ProjectorCodes:
    """Read the projector codes ``slscan decode --codes`` wrote.

    folder : a view's folder (holding ``codes.json``), or the decode output folder
        (holding ``projector_codes.json``); from the latter ``view`` picks the view
        (default: the only one)

    Returns maps as the decoder gave them: Gray code's int32 columns and rows with -1
    where not decoded (as :func:`~slscan.decode.graycode.decode_gray`), phase shifting's
    float (float32 as stored) with NaN where not decoded; and the bool mask.
    """
    folder = Path(folder)
    if (folder / MANIFEST).is_file():
        with about_file(folder / MANIFEST, "projector-codes manifest"):
            folder = _view_folder(folder, view)
    elif view is not None:
        folder = folder / view
    meta_path = folder / VIEW_FILE
    if not meta_path.is_file():
        raise SlscanError(f"{folder}: no {VIEW_FILE} or {MANIFEST} (expected the output of slscan decode --codes)")
    with about_file(meta_path, "projector-codes file"):
        return _read_view_codes(folder, meta_path)


def _view_folder(folder: Path, view: str | None) -> Path:
    """The folder of ``view`` that the manifest in ``folder`` names."""
    manifest = read_json(folder / MANIFEST, "projector-codes manifest")
    names = [e.get("view") for e in manifest.get("views", [])]
    if not all(isinstance(name, str) for name in names):
        raise SlscanError(f"{folder / MANIFEST}: views named {names!r}; expected a name (text) for each")
    if view is None:
        if len(names) != 1:
            raise SlscanError(
                f"{folder / MANIFEST}: {len(names)} views ({', '.join(map(str, names))}); name one"
            )
        view = names[0]
    elif view not in names:
        raise SlscanError(f"{folder / MANIFEST}: no view {view!r}; expected one of {', '.join(map(str, names))}")
    entry = next(e for e in manifest["views"] if e.get("view") == view)
    sub = entry.get("folder", view)
    if not isinstance(sub, str) or not sub or Path(sub).is_absolute() or ".." in Path(sub).parts:
        raise SlscanError(f"{folder / MANIFEST}: view {view!r} has folder {sub!r}; expected a folder name "
                          "inside the decode output")
    return folder / sub


def _read_view_codes(folder: Path, meta_path: Path) -> ProjectorCodes:
    meta = read_json(meta_path, "projector-codes file")
    if not isinstance(meta, dict):
        raise SlscanError(f"{meta_path}: expected a JSON object (an slscan projector-codes file)")
    if meta.get("format") != f"{CODES_FORMAT}.view" or meta.get("version") != CODES_VERSION:
        raise SlscanError(
            f"{meta_path}: expected format {CODES_FORMAT}.view version {CODES_VERSION}, "
            f"got {meta.get('format')!r} version {meta.get('version')!r}"
        )
    encoding = meta.get("encoding", PNG_ENCODING)
    if encoding not in (PNG_ENCODING, FLOAT_ENCODING):
        raise SlscanError(f"{meta_path}: unknown map encoding {encoding!r}; expected {PNG_ENCODING} or "
                          f"{FLOAT_ENCODING}")
    try:
        files = meta["files"]
        invalid = int(meta["invalid"]) if encoding == PNG_ENCODING else None
        shape = (int(meta["camera"]["height"]), int(meta["camera"]["width"]))
        size = (int(meta["projector"]["width"]), int(meta["projector"]["height"]))
        bits = (int(meta["bits"]["columns"]), int(meta["bits"]["rows"]))
        limits = ValidShare(**meta["limits"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SlscanError(f"{meta_path}: malformed projector-codes file ({exc})") from None
    for key in ("columns", "mask"):
        if not isinstance(files.get(key), str):
            raise SlscanError(f"{meta_path}: files.{key} is {files.get(key)!r}; expected the name of its map")

    def codes(name: str | None) -> np.ndarray | None:
        if encoding == FLOAT_ENCODING:
            return _map(folder, name, shape, np.float32)
        values = _map(folder, name, shape, np.uint16)
        return None if values is None else np.where(values == invalid, -1, values.astype(np.int32))

    return ProjectorCodes(
        view=str(meta.get("view", folder.name)),
        column=codes(files["columns"]),
        row=codes(files.get("rows")),
        mask=_map(folder, files["mask"], shape, np.uint8) > 0,
        projector_size=size,
        bits=bits,
        valid_share=limits,
    )


# --- a whole session -------------------------------------------------------------------------


def _codes_task(task: tuple) -> tuple[ProjectorCodes, np.ndarray | None, np.ndarray | None, dict[str, Any], float]:
    """Decode one view and write its codes (runs in a worker process); the white capture
    and the saturation map come back only when they are to be logged."""
    session, view_name, folder, images, threshold = task
    t = time.perf_counter()
    fam = codes_family(session)
    if fam.name == "gray":  # the bit threshold is Gray code's own option
        result = decode_gray(session, session.view(view_name), threshold=threshold)
        codes = codes_from_gray(result, session, view_name)
    else:  # the family's decode (phase shifting: sub-pixel float maps)
        result = fam.decode_module().decode(session, session.view(view_name), None)
        codes = result.projector_codes
    entry = write_view_codes(codes, Path(folder) / view_name)
    seconds = time.perf_counter() - t
    return codes, result.white if images else None, result.saturated if images else None, entry, seconds


def decode_codes_session(
    session: Session | str | os.PathLike,
    out: str | os.PathLike,
    *,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
    executor: Executor = LOCAL,
    threshold: str = "adaptive",
) -> list[ProjectorCodes]:
    """Decode every view's Gray code (or phase shifting) into ``out/VIEW/columns.png``,
    ``rows.png`` (phase: ``columns.tiff``, ``rows.tiff``), ``mask.png`` and
    ``out/projector_codes.json``; no calibration needed, no range maps written.

    rec : an ``rr.RecordingStream`` for the white capture, the mask, the column and row maps
    executor : where the views are decoded (see :func:`slscan.decode.pipeline.decode_session`)
    threshold : the Gray-code bit thresholds, ``"adaptive"`` or ``"opencv"``
        (see :func:`slscan.decode.graycode.decode_gray_images`)
    """
    if not isinstance(session, Session):
        session = load_session(session)
    if not session.views:
        raise SlscanError(f"{session.root / SESSION_FILE}: the session has no views; expected at least one")
    require_codes(session)
    warn_if_lossy(session)
    executor = fit_workers(executor, session)
    executor.start(len(session.views), [__name__])
    results = []
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        entries = []
        tasks = [(session, view.name, tmp, rec is not None, threshold) for view in session.views]
        for index, (codes, white, saturated, entry, seconds) in enumerate(executor.map(_codes_task, tasks)):
            if rec is not None:
                _log_view(rec, codes, index, white=white, saturated=saturated)
            if progress:
                progress(codes.view)
            entries.append({"view": codes.view, "folder": codes.view, "valid_share": entry["valid_share"],
                            "noise_dn": entry["noise_dn"], "seconds": seconds})
            results.append(codes)
        write_codes_manifest(tmp, session, entries,
                             encoding=results[0].encoding if results else PNG_ENCODING)
    return results


def _log_view(rec, codes: ProjectorCodes, view_index: int, *, white: np.ndarray | None = None,
              saturated: np.ndarray | None = None) -> None:
    """Stream one view's codes (and its white capture) to Rerun, through the decode loggers."""
    from slscan.viewer import log_decode as rlog

    if rec is None:
        return
    if white is not None:
        from slscan.viewer.log import log_capture

        log_capture(rec, white, view_index=view_index, frame_index=0, label="white")
    rlog.log_decode_maps(rec, view_index=view_index, mask=codes.mask, codes=codes.column,
                         code_max=codes.projector_size[0], saturated=saturated)
    rlog.log_projector_codes(rec, view_index=view_index, column=codes.column, row=codes.row,
                             projector_size=codes.projector_size)
    rlog.log_metrics(rec, {"mask_share": codes.valid_share.decoded, "noise_dn": codes.valid_share.noise_dn,
                           "low_contrast_share": codes.valid_share.low_contrast,
                           "weak_bit_share": codes.valid_share.weak_bits}, view_index=view_index)
