"""Label maps as inputs (an upload is stored without its name): found by content, the same way on every path (the
CLI, the API's check before the job is queued, the worker: ``find_label_upload``, called by
``engine.job.run_job`` and ``service.upload_check``), and read (``read_label_upload``).

A label input is one of:

* a NIfTI-1/2 file (``n+1`` / ``n+2`` magic), gzipped or not; an integer map without intensity scaling (a float
  or scaled NIfTI is an image, not labels: ``NotLabelsError``, also before the job is queued);
* an NRRD or Slicer ``.seg.nrrd`` (``NRRD000`` magic; attached data);
* a DICOM SEG file alone (placed on its own grid): a SEG is told by the SOP class its file meta names (Media
  Storage SOP Class UID), or for a data set without preamble and file meta by its SOP Class UID;
* a zip, a tar (plain or compressed) or a folder holding exactly one of those maps (other members ignored), or a
  DICOM SEG with its referenced CT series (``engine.labels.dicom_seg.read_seg_folder``; a PACS job's upload is
  such a folder). Archives and folders are listed by the scan loader's reader (``engine.io.archive.open_members``):
  the same members, limits and junk rules (``__MACOSX/``, dot files) as for a scan. One holding a SEG and no other
  DICOM file is refused naming the series the SEG references (``MissingReferenceError``).

Nothing here loads Warp: the API imports this module to check uploads.
"""

from __future__ import annotations

import contextlib
import re
import shutil
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from engine.errors import InputError, NotLabelsError

__all__ = ["SNIFF_BYTES", "LabelUpload", "find_label_upload", "is_seg", "is_seg_file", "read_label_upload", "sniff"]

# Segmentation Storage (.66.4) and Label Map Segmentation Storage (.66.7), as a file's meta names its SOP class
SEG_SOP_CLASS = re.compile(rb"1\.2\.840\.10008\.5\.1\.4\.1\.1\.66\.[47](?![0-9.])")
SNIFF_BYTES = 4096  # NIfTI-1's header is 348 bytes, NIfTI-2's 540; a SEG's file meta names its SOP class early
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
        return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, SNIFF_BYTES)
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


_RAW_GROUPS = (b"\x08\x00", b"\x02\x00", b"\x00\x08")  # a data set without preamble (as engine.io.dicom reads)
_MEDIA_SOP_CLASS = b"\x02\x00\x02\x00"  # (0002,0002) Media Storage SOP Class UID, file meta (explicit VR LE)
_SOP_CLASS = b"\x08\x00\x16\x00"  # (0008,0016) SOP Class UID, a raw little-endian data set


def looks_like_dicom(head: bytes) -> bool:
    """Whether a file's first bytes could start a DICOM file (preamble + DICM, or a raw data set), as the scan
    loader tells them (``engine.io.dicom.looks_like_dicom``)."""
    return head[128:132] == b"DICM" or head[:4] == b"DICM" or head[:2] in _RAW_GROUPS


def _uid_element(data: bytes, tag: bytes) -> bytes | None:
    """The UID value of the first element ``tag`` in ``data`` (explicit VR ``UI`` or implicit VR), if it is there."""
    i = data.find(tag)
    while 0 <= i:
        rest = data[i + 4 :]
        if rest[:2] == b"UI":
            value = rest[4 : 4 + int.from_bytes(rest[2:4], "little")]
        else:
            n = int.from_bytes(rest[:4], "little")
            value = rest[4 : 4 + n] if n <= 64 else b""
        value = value.rstrip(b"\x00 ")
        if value and re.fullmatch(rb"[0-9.]+", value):
            return value
        i = data.find(tag, i + 1)
    return None


def is_seg(head: bytes) -> bool:
    """Whether a file's first bytes are a DICOM SEG's: the SOP class its file meta names (Media Storage SOP Class
    UID), or for a data set without file meta its SOP Class UID, is Segmentation or Label Map Segmentation Storage.
    (A report that only references a SEG is not one.)"""
    if head[128:132] == b"DICM" or head[:4] == b"DICM":
        body = head[132:] if head[128:132] == b"DICM" else head[4:]
        uid = _uid_element(body, _MEDIA_SOP_CLASS) or _uid_element(body, _SOP_CLASS)  # file meta without it
    elif head[:2] in _RAW_GROUPS:
        uid = _uid_element(head, _SOP_CLASS)
    else:
        return False
    return uid is not None and SEG_SOP_CLASS.fullmatch(uid) is not None


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


def find_label_upload(path: str | Path, label: str = "the upload", *, force: bool = False) -> LabelUpload | None:
    """Whether an input (a file, a zip or tar archive, a folder) is a label map, by content (see the module
    docstring); None when it is not (a scan), unless ``force``. The one detection of every path: the CLI, the API's
    upload check and the worker (``engine.job.run_job``); archives and folders are listed by the scan loader's own
    reader (``engine.io.archive.open_members``: the same members, junk such as ``__MACOSX/`` left out).

    Raises:
        NotLabelsError: a float or scaled NIfTI; with ``force``, an input that holds no label map.
        MissingReferenceError: an archive or folder holding a DICOM SEG and no other DICOM file (not the CT series
            it was drawn on; the message names that series). A SEG file alone is read on its own grid.
        InputError: several label maps, or an archive that cannot be read.
    """
    from engine.io.archive import open_members

    p = Path(path)
    found: LabelUpload | None = None
    if p.exists():
        with open_members(p, heads_only=True, head_bytes=SNIFF_BYTES) as members:
            found = _in_members(members, p, label)
    if found is None and force:
        raise NotLabelsError(
            f"{label} holds no label map bonemesh reads (an integer NIfTI, an NRRD or .seg.nrrd, a DICOM SEG, or a "
            "zip or folder of one, or of a DICOM SEG with its CT series)"
        )
    return found


def _in_members(members: Any, path: Path, label: str) -> LabelUpload | None:
    """The label map among an input's members (``engine.io.archive.Members``)."""
    maps: list[tuple[str, str]] = []
    segs: list[str] = []
    other_dicom = 0
    single = members.kind == "file"
    for m in members.members:
        kind = sniff(m.head)
        if kind is not None:
            if kind.startswith("nifti"):
                check_nifti_head(m.head, label if single else f"{label}: {m.name}")
            maps.append((m.name, kind))
        elif is_seg(m.head):
            segs.append(m.name)
        elif looks_like_dicom(m.head):
            other_dicom += 1
    if single:
        return LabelUpload(maps[0][1]) if maps else LabelUpload("dicom-seg") if segs else None
    if len(maps) > 1:
        shown = ", ".join(name for name, _ in maps[:4])
        raise InputError(f"{label} holds {len(maps)} label maps ({shown}); send one per job")
    if maps:
        return LabelUpload(maps[0][1], maps[0][0])
    if not segs:
        return None
    if len(segs) > 1:
        raise InputError(f"{label} holds {len(segs)} DICOM SEG files ({', '.join(segs[:4])}); send one per job")
    if not other_dicom:
        from engine.errors import MissingReferenceError

        raise MissingReferenceError(f"{label} holds a DICOM SEG {_without_ct(path, segs[0])}")
    return LabelUpload("dicom-seg")


def _without_ct(path: Path, member: str) -> str:
    """'without the CT series it was drawn on (...)', naming that series where the SEG says it."""
    from engine.io.archive import open_members

    uid = None
    with contextlib.suppress(Exception), open_members(path) as members:
        m = next(m for m in members.members if m.name == member)
        uid = seg_referenced_series(m.read())
    named = f"series {uid}" if uid else "a series the SEG does not name"
    return (
        f"without the CT series it was drawn on ({named} is missing: it was not sent, received or fetched); send "
        "the SEG with that series, or the SEG file alone to place it on its own grid"
    )


def seg_referenced_series(data: bytes) -> str | None:
    """The SeriesInstanceUID a SEG's bytes say it was drawn on (ReferencedSeriesSequence), if any."""
    import io

    import pydicom

    from engine.labels.dicom_seg import referenced_series

    return referenced_series(pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True, force=True))


def is_seg_file(path: Path) -> bool:
    """Whether the file at ``path`` is a DICOM SEG (by its first bytes)."""
    with path.open("rb") as fh:
        return is_seg(fh.read(SNIFF_BYTES))


@contextlib.contextmanager
def _unpacked(path: Path, found: LabelUpload) -> Iterator[Path]:
    """The label map as a local file under a name with its suffix (the readers go by it): the input itself, or its
    member copied out of the archive or folder (read through ``open_members``: names, counts and sizes checked as
    for any input)."""
    from engine.io.archive import open_members

    tmp = Path(tempfile.mkdtemp(prefix="bonemesh-labels-"))
    try:
        target = tmp / f"labels{_SUFFIX[found.kind]}"
        if found.member is None:
            target.symlink_to(path.resolve())
        else:
            with open_members(path) as members:
                member = next((m for m in members.members if m.name == found.member), None)
                if member is None:
                    raise InputError(f"{path.name}: its member {found.member!r} is gone")
                target.write_bytes(member.read())
        yield target
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def read_label_upload(path: str | Path, found: LabelUpload, label: str = "the upload") -> Any:
    """The ``LabelVolume`` of an input ``find_label_upload`` found to be a label map: a NIfTI / NRRD (alone or a
    member), a SEG file alone (on its own grid), or a SEG with its CT series in an archive or folder (on the CT).

    Raises:
        LabelError (NotLabelsError, EmptyLabelError, MissingReferenceError, LabelsOutsideScanError), InputError.
    """
    from engine.io.archive import open_members
    from engine.io.labelmaps import read_labels
    from engine.labels.dicom_seg import read_dicom_seg, read_seg_folder

    p = Path(path)
    if found.kind == "dicom-seg":
        with open_members(p, heads_only=True) as members:
            single = members.kind == "file"
        lv = read_dicom_seg(p, label=label) if single else read_seg_folder(p, label)
    else:
        with _unpacked(p, found) as local:
            lv = read_labels(local)
    lv.source["file"] = found.member or label
    return lv
