"""What a file's first bytes say it is, for the label readers (``engine.labels.uploads``, ``engine.labels.dicom_seg``)
and the API's check: a NIfTI-1/2 or NRRD label map (``sniff``), a DICOM file (``looks_like_dicom``) and whether it is
a SEG (``is_seg``: the SOP class its file meta, or a data set without one, names), and whether a NIfTI holds labels at
all (``check_nifti_head``). Imports nothing of the engine but its errors.
"""

from __future__ import annotations

import re
import zlib

from engine.errors import NotLabelsError

__all__ = ["SEG_SOP_CLASS", "SNIFF_BYTES", "check_nifti_head", "is_seg", "looks_like_dicom", "sniff"]

# Segmentation Storage (.66.4) and Label Map Segmentation Storage (.66.7), as a file's meta names its SOP class
SEG_SOP_CLASS = re.compile(rb"1\.2\.840\.10008\.5\.1\.4\.1\.1\.66\.[47](?![0-9.])")
SNIFF_BYTES = 4096  # NIfTI-1's header is 348 bytes, NIfTI-2's 540; a SEG's file meta names its SOP class early
_INTEGER_CODES = {2, 4, 8, 256, 512, 768, 1024, 1280}  # NIfTI datatype codes of integer data


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
