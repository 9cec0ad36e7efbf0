"""Label maps as uploads (a job's one file, stored without its name): found by content, checked before the job is
queued (``find_label_upload``), and read by the worker (``read_label_upload``).

A label upload is one of:

* a NIfTI-1/2 file (``n+1`` / ``n+2`` magic), gzipped or not; an integer map without intensity scaling (a float
  or scaled NIfTI is an image, not labels: ``NotLabelsError``, also before the job is queued);
* an NRRD or Slicer ``.seg.nrrd`` (``NRRD000`` magic; attached data);
* a zip holding exactly one of those (other members ignored), or a zip of a DICOM SEG with its referenced CT
  series (``engine.labels.dicom_seg.read_seg_folder``), or a DICOM SEG file alone (placed on its own grid);
* a folder of DICOM files holding a SEG and its referenced CT series (a PACS job's upload: a SEG received by
  C-STORE or fetched by DICOMweb, with its CT beside it).

Nothing here loads Warp: the API imports this module to check uploads.
"""

from __future__ import annotations

import contextlib
import re
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from engine.errors import InputError, NotLabelsError

__all__ = ["LabelUpload", "find_label_upload", "is_seg_file", "read_label_upload", "sniff"]

# Segmentation Storage (.66.4) and Label Map Segmentation Storage (.66.7), as a file's meta names its SOP class
SEG_SOP_CLASS = re.compile(rb"1\.2\.840\.10008\.5\.1\.4\.1\.1\.66\.[47](?![0-9.])")
_SNIFF_BYTES = 4096  # NIfTI-1's header is 348 bytes, NIfTI-2's 540; a SEG's file meta names its SOP class early
_INTEGER_CODES = {2, 4, 8, 256, 512, 768, 1024, 1280}  # NIfTI datatype codes of integer data
_SUFFIX = {"nifti": ".nii", "nifti-gz": ".nii.gz", "nrrd": ".nrrd"}


@dataclass(frozen=True)
class LabelUpload:
    """What the upload holds: ``kind`` ``"nifti"``, ``"nifti-gz"``, ``"nrrd"`` or ``"dicom-seg"``; ``member``: the
    label map's name in a zip (None: the upload itself, or a SEG zip's folder)."""

    kind: str
    member: str | None = None

    def describe(self) -> str:
        """A summary for the log (no names)."""
        return f"label map ({self.kind}{', in a zip' if self.member is not None else ''})"


def _gunzip_head(head: bytes) -> bytes:
    try:
        return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, _SNIFF_BYTES)
    except zlib.error:
        return b""


def _nifti_version(head: bytes) -> int | None:
    if len(head) >= 348 and head[344:348] == b"n+1\x00":
        return 1
    if len(head) >= 8 and head[4:8] == b"n+2\x00":
        return 2
    return None


def sniff(head: bytes) -> str | None:
    """The kind of label map these first bytes start (``LabelUpload.kind``), or None."""
    if head.startswith(b"NRRD000"):
        return "nrrd"
    if head[:2] == b"\x1f\x8b":
        return "nifti-gz" if _nifti_version(_gunzip_head(head)) else None
    return "nifti" if _nifti_version(head) else None


def is_seg(head: bytes) -> bool:
    """Whether a file's first bytes are a DICOM SEG's (its file meta names a segmentation SOP class)."""
    return head[128:132] == b"DICM" and SEG_SOP_CLASS.search(head) is not None


def check_nifti_head(head: bytes, label: str) -> None:
    """Refuse a NIfTI that is an image (float data, or integers with an intensity scaling), from its header.

    Raises:
        NotLabelsError: not integer labels.
    """
    import struct

    data = _gunzip_head(head) if head[:2] == b"\x1f\x8b" else head
    version = _nifti_version(data)
    if version is None:
        return
    for order in "<>":
        size = struct.unpack_from(order + "i", data, 0)[0]
        if size in (348, 540):
            break
    if version == 1:
        code = struct.unpack_from(order + "h", data, 70)[0]
        slope, inter = struct.unpack_from(order + "ff", data, 112)
    else:
        code = struct.unpack_from(order + "h", data, 12)[0]
        slope, inter = struct.unpack_from(order + "dd", data, 176)
    finite = [v == v and abs(v) != float("inf") for v in (slope, inter)]  # NaN: no scaling (as nibabel reads it)
    scaled = (finite[0] and slope not in (0.0, 1.0)) or (finite[1] and inter != 0.0)
    if code not in _INTEGER_CODES or scaled:
        what = "with an intensity scaling" if code in _INTEGER_CODES else f"of data type code {code} (not integer)"
        raise NotLabelsError(
            f"{label}: a NIfTI {what} is an image, not a label map; labels must be stored as integers (one value "
            "per structure)"
        )


def _zip_members(path: Path) -> Iterator[tuple[zipfile.ZipInfo, bytes]]:
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.is_dir():
                continue
            with zf.open(info) as fh:
                yield info, fh.read(_SNIFF_BYTES)


def find_label_upload(path: str | Path, label: str = "the upload", *, force: bool = False) -> LabelUpload | None:
    """Whether an upload (a file, a zip, a folder) is a label map, by content (see the module docstring); None
    when it is not (a CT), unless ``force``.

    Raises:
        NotLabelsError: a float or scaled NIfTI; with ``force``, an upload that holds no label map.
        InputError: a zip with several label maps, or a zip that cannot be read.
    """
    p = Path(path)
    found: LabelUpload | None = None
    if p.is_dir():
        found = _in_folder(p, label)
    elif p.is_file() and zipfile.is_zipfile(p):
        found = _in_zip(p, label)
    elif p.is_file():
        with p.open("rb") as fh:
            head = fh.read(_SNIFF_BYTES)
        kind = sniff(head) or ("dicom-seg" if is_seg(head) else None)
        if kind is not None and kind.startswith("nifti"):
            check_nifti_head(head, label)
        found = LabelUpload(kind) if kind else None
    if found is None and force:
        raise NotLabelsError(
            f"{label} holds no label map bonemesh reads (an integer NIfTI, an NRRD or .seg.nrrd, or a zip of one, or "
            "of a DICOM SEG with its CT series)"
        )
    return found


def _in_zip(path: Path, label: str) -> LabelUpload | None:
    maps: list[tuple[str, str]] = []
    seg = other_dicom = 0
    try:
        for info, head in _zip_members(path):
            kind = sniff(head)
            if kind is not None:
                if kind.startswith("nifti"):
                    check_nifti_head(head, f"{label}: {info.filename}")
                maps.append((info.filename, kind))
            elif is_seg(head):
                seg += 1
            elif head[128:132] == b"DICM":
                other_dicom += 1
    except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
        raise InputError(f"{label}: the zip cannot be read ({exc})") from None
    if len(maps) > 1:
        shown = ", ".join(name for name, _ in maps[:4])
        raise InputError(f"{label} holds {len(maps)} label maps ({shown}); send one per job")
    if maps:
        return LabelUpload(maps[0][1], maps[0][0])
    return _seg_found(
        seg,
        other_dicom,
        f"{label} holds a DICOM SEG but no other DICOM file: zip the SEG with the CT series it was drawn on",
    )


def is_seg_file(path: Path) -> bool:
    """Whether the file at ``path`` is a DICOM SEG (by its first bytes)."""
    with path.open("rb") as fh:
        return is_seg(fh.read(_SNIFF_BYTES))


def _seg_found(seg: int, other_dicom: int, missing: str) -> LabelUpload | None:
    """A SEG upload when there is a SEG; ``MissingReferenceError(missing)`` when nothing else is DICOM."""
    if seg and not other_dicom:
        from engine.errors import MissingReferenceError

        raise MissingReferenceError(missing)
    return LabelUpload("dicom-seg") if seg else None


def _in_folder(path: Path, label: str) -> LabelUpload | None:
    """A folder of DICOM files (a PACS job's upload) holding a SEG: its first bytes name the SOP class."""
    seg = other_dicom = 0
    for f in sorted(q for q in path.rglob("*") if q.is_file()):
        with f.open("rb") as fh:
            head = fh.read(_SNIFF_BYTES)
        if is_seg(head):  # (is_seg_file, with the head kept for the next test)
            seg += 1
        elif head[128:132] == b"DICM":
            other_dicom += 1
    return _seg_found(
        seg,
        other_dicom,
        f"{label} holds a DICOM SEG without the CT series it was drawn on (its "
        "referenced series was not received or could not be fetched)",
    )


def _copy(src: IO[bytes], dest: Path, limit: int, label: str) -> None:
    n = 0
    with dest.open("wb") as out:
        while chunk := src.read(1 << 20):
            n += len(chunk)
            if n > limit:
                raise InputError(f"{label} expands to more than {limit:,} bytes; crop or downsample it first")
            out.write(chunk)


@contextlib.contextmanager
def _unpacked(path: Path, found: LabelUpload, label: str) -> Iterator[Path]:
    """A local path the readers take: the label map under a name with its suffix, or a SEG zip's folder."""
    from engine.io.archive import InputLimits, open_members

    limits = InputLimits()
    tmp = Path(tempfile.mkdtemp(prefix="bonemesh-labels-"))
    try:
        if found.kind == "dicom-seg" and not zipfile.is_zipfile(path):  # a folder with its CT, or one SEG file
            yield path  # (placed on its own grid)
            return
        if found.kind == "dicom-seg":
            folder = tmp / "seg"
            folder.mkdir()
            with open_members(path, limits) as members:  # names, counts and sizes checked as for any upload
                for i, m in enumerate(members.members):
                    (folder / f"{i:06d}.dcm").write_bytes(m.read())
            yield folder
            return
        target = tmp / f"labels{_SUFFIX[found.kind]}"
        if found.member is None:
            target.symlink_to(path.resolve())
        else:
            with open_members(path, limits, heads_only=True), zipfile.ZipFile(path) as zf, zf.open(found.member) as fh:
                _copy(fh, target, limits.max_total_bytes, label)
        yield target
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def read_label_upload(path: str | Path, found: LabelUpload, label: str = "the upload") -> Any:
    """The ``LabelVolume`` of an upload ``find_label_upload`` found to be a label map.

    Raises:
        LabelError (NotLabelsError, EmptyLabelError, MissingReferenceError, LabelsOutsideScanError), InputError.
    """
    from engine.io.labelmaps import read_labels
    from engine.labels.dicom_seg import read_dicom_seg, read_seg_folder

    with _unpacked(Path(path), found, label) as local:
        if found.kind != "dicom-seg":
            lv = read_labels(local)
        else:
            lv = read_seg_folder(local) if local.is_dir() else read_dicom_seg(local)
    lv.source["file"] = found.member or label
    return lv
