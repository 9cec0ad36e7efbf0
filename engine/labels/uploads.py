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
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from engine.errors import InputError, NotLabelsError
from engine.labels.sniff import SNIFF_BYTES, check_nifti_head, is_seg, looks_like_dicom, sniff

__all__ = [
    "SNIFF_BYTES",
    "LabelUpload",
    "find_label_upload",
    "is_seg",
    "is_seg_file",
    "read_label_upload",
    "read_labels",
    "sniff",
]

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


def read_labels(path: str | Path, *, reference: Any = None) -> Any:
    """Read a label map file by its suffix (NIfTI, NRRD / seg.nrrd: ``engine.io.labelmaps``) or, for other files, as a
    DICOM SEG placed into ``reference``'s grid (an ``engine.types.Volume``) when given (``engine.labels.dicom_seg``).

    Raises:
        NotLabelsError, EmptyLabelError, LabelsOutsideScanError, MissingReferenceError, InputError.
    """
    from engine.io.labelmaps import read_nifti_labels, read_nrrd_labels
    from engine.labels.dicom_seg import read_dicom_seg

    p = Path(path)
    name = p.name.lower()
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if name.endswith((".nii", ".nii.gz")):
        return read_nifti_labels(p)
    if name.endswith((".nrrd", ".nhdr")):
        return read_nrrd_labels(p)
    return read_dicom_seg(p, reference=reference)
