"""DICOM Segmentation (SEG) in: BINARY, FRACTIONAL and LABELMAP encodings, read with pydicom into one
``engine.io.labelmaps.LabelVolume``.

Segments come from the SegmentSequence (SegmentNumber is the label value, SegmentLabel the name,
RecommendedDisplayCIELabValue the colour, turned into sRGB). Each frame is placed by its Per-frame Plane Position
(ImagePositionPatient): into the referenced CT's grid when that CT is given (``reference``: the frames must lie on
its grid, with its row and column directions), else on the SEG's own grid (its slice positions along the normal of
ImageOrientationPatient; a SEG leaves out empty frames, so missing positions are empty slices). Segments are
independent masks: in ``labels`` a voxel in two segments goes to the later one (``source["overlap_voxels"]``), and
each segment that lost voxels keeps its whole mask in ``LabelVolume.masks`` (``LabelVolume.layers()``).

Pixels (``seg_pixels``): every transfer syntax pydicom decodes (native in any byte order, a deflated data set,
JPEG 2000, JPEG-LS, RLE of 8/16-bit frames), plus RLE Lossless of 1-bit frames and Deflated Image Frame
Compression (1.2.840.10008.1.2.8.1), which pydicom 3.0 lacks, decoded here; anything else is an ``InputError``
naming the transfer syntax.

A SEG with its CT in a folder, zip or tar (``read_seg_folder``) is placed on the series it references, loaded from
the same input by ``engine.io.load_volume``; a SEG file alone is placed on its own grid.

Errors: ``MissingReferenceError`` (the SEG's referenced series is not the CT given, or not in the input),
``LabelsOutsideScanError`` (no labelled voxel lands in the CT's grid), ``NotLabelsError`` (not a SEG),
``InputError`` (frames that cannot be placed or decoded).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.errors import InputError, LabelsOutsideScanError, MissingReferenceError, NotLabelsError
from engine.io.labelmaps import LabelVolume, Segment, make_label_volume, palette
from engine.types import Volume

__all__ = ["lab_to_srgb", "read_dicom_seg", "read_seg_folder", "referenced_series", "seg_pixels"]

SEG_CLASSES = ("1.2.840.10008.5.1.4.1.1.66.4", "1.2.840.10008.5.1.4.1.1.66.7")  # Segmentation, Label Map Seg.
_GRID_TOL = 0.05  # frame positions this far (in voxels) from the CT's grid are not on it


@dataclass
class _Frames:
    """The SEG's frames: pixels (F, rows, cols), positions (F, 3) LPS mm, segment number per frame (0: label map)."""

    pixels: np.ndarray
    positions: np.ndarray
    numbers: np.ndarray
    row: np.ndarray
    col: np.ndarray
    spacing_rc: tuple[float, float]
    slice_step: float | None


def lab_to_srgb(dicom_lab: Any) -> tuple[float, float, float]:
    """DICOM's scaled CIELab (0-65535 each; D65 white as in highdicom) as sRGB 0-1, clipped."""
    lab = [float(v) for v in dicom_lab]
    l_star, a_star, b_star = lab[0] / 65535 * 100, lab[1] / 65535 * 255 - 128, lab[2] / 65535 * 255 - 128
    fy = (l_star + 16) / 116
    f = np.array([a_star / 500 + fy, fy, fy - b_star / 200])
    xyz = np.where(f**3 > 0.008856, f**3, (f - 16 / 116) / 7.787) * np.array([0.95047, 1.0, 1.08883])
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    lin = m @ xyz
    rgb = np.where(lin > 0.0031308, 1.055 * np.abs(lin) ** (1 / 2.4) - 0.055, 12.92 * lin)
    r, g, b = (round(float(c), 4) for c in np.clip(rgb, 0, 1))
    return (r, g, b)


def _dataset(source: Any, label: str) -> Any:
    """The SEG's data set from a path, its bytes or a parsed data set.

    Raises:
        NotLabelsError: not DICOM, or a DICOM object other than a Segmentation.
    """
    import io

    import pydicom

    from engine.labels.sniff import looks_like_dicom

    if isinstance(source, (str, Path)):
        source = Path(source).read_bytes()
    if isinstance(source, (bytes, bytearray)):
        not_dicom = NotLabelsError(f"{label}: neither a NIfTI, an NRRD nor a DICOM file")
        if not looks_like_dicom(bytes(source[:132])):
            raise not_dicom
        try:  # force: a data set without preamble and file meta, as the scan loader reads them
            ds = pydicom.dcmread(io.BytesIO(source), force=True)
            if "TransferSyntaxUID" not in ds.file_meta:
                implicit, little = ds.original_encoding
                ds.file_meta.TransferSyntaxUID = (
                    pydicom.uid.ImplicitVRLittleEndian
                    if implicit
                    else pydicom.uid.ExplicitVRLittleEndian
                    if little
                    else pydicom.uid.ExplicitVRBigEndian
                )
        except Exception:  # pydicom's own message suggests force=True: not for this user
            raise not_dicom from None
    else:
        ds = source
    if str(ds.get("SOPClassUID", "")) not in SEG_CLASSES and ds.get("Modality") != "SEG":
        raise NotLabelsError(f"{label}: a DICOM {ds.get('Modality', '?')} object, not a Segmentation (SEG)")
    return ds


def referenced_series(ds: Any) -> str | None:
    """The SeriesInstanceUID the SEG was drawn on (ReferencedSeriesSequence), if it says."""
    seq = ds.get("ReferencedSeriesSequence")
    return str(seq[0].SeriesInstanceUID) if seq else None


def _segments(ds: Any) -> tuple[Segment, ...]:
    out = []
    for i, item in enumerate(ds.SegmentSequence):
        if int(item.SegmentNumber) <= 0:  # a label map's background segment
            continue
        lab = item.get("RecommendedDisplayCIELabValue")
        colour = lab_to_srgb(lab) if lab is not None else palette(i)
        name = str(item.get("SegmentLabel") or f"segment_{item.SegmentNumber}")
        out.append(Segment(int(item.SegmentNumber), name, colour))
    return tuple(out)


def _frames(ds: Any, label: str, alone: bool = False) -> _Frames:
    """The SEG's frames and their geometry (``alone``: no CT given, a missing geometry names the series wanted)."""
    kind = str(ds.get("SegmentationType", "BINARY")).upper()
    pixels = seg_pixels(ds, label)
    if kind == "FRACTIONAL":
        pixels = (pixels.astype(np.float32) >= 0.5 * float(ds.get("MaximumFractionalValue", 255))).astype(np.uint8)
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per = ds.PerFrameFunctionalGroupsSequence
    if len(per) != len(pixels):
        raise InputError(f"{label}: {len(pixels)} frames but {len(per)} per-frame functional groups")

    def group(item: Any, name: str) -> Any:
        if name in item:
            return item[name].value[0]
        if shared is not None and name in shared:
            return shared[name].value[0]
        ref = referenced_series(ds)
        raise InputError(
            f"{label}: no {name} (per-frame or shared): the frames cannot be placed"
            + (f" without the referenced series {ref} (send the SEG with that series)" if ref and alone else "")
        )

    iop = np.asarray(group(per[0], "PlaneOrientationSequence").ImageOrientationPatient, dtype=np.float64)
    measures = group(per[0], "PixelMeasuresSequence")
    spacing = tuple(float(v) for v in measures.PixelSpacing)
    step = measures.get("SpacingBetweenSlices")
    positions = np.array(
        [[float(v) for v in group(f, "PlanePositionSequence").ImagePositionPatient] for f in per], dtype=np.float64
    )
    if kind == "LABELMAP":
        numbers = np.zeros(len(per), dtype=np.int64)
    else:
        numbers = np.array([int(group(f, "SegmentIdentificationSequence").ReferencedSegmentNumber) for f in per])
    return _Frames(pixels, positions, numbers, iop[:3], iop[3:], (spacing[0], spacing[1]), step and float(step))


# --- pixels ------------------------------------------------------------------------------------------------------

RLE_LOSSLESS = "1.2.840.10008.1.2.5"
DEFLATED_FRAMES = "1.2.840.10008.1.2.8.1"  # Deflated Image Frame Compression (PS3.5 8.2.16): raw Deflate per frame


def _ts(ds: Any) -> tuple[str, str]:
    """The transfer syntax's UID and its name, for messages."""
    uid = ds.file_meta.get("TransferSyntaxUID") if hasattr(ds, "file_meta") else None
    if uid is None:
        return "", "an unnamed transfer syntax"
    name = getattr(uid, "name", "") or str(uid)
    return str(uid), (f"{name} ({uid})" if name != str(uid) else str(uid))


def seg_pixels(ds: Any, label: str) -> np.ndarray:
    """Every frame of a SEG as (frames, rows, columns) stored values (0/1 for BINARY).

    Native (uncompressed, any byte order, deflated data set), JPEG 2000, JPEG-LS and RLE of 8/16-bit frames are
    decoded by pydicom; RLE Lossless of 1-bit frames and Deflated Image Frame Compression (any bit depth) here, as
    pydicom 3.0 does neither: each frame is one encoded item, and its 1-bit values are packed LSB first from a byte
    boundary (PS3.5 8.2; a writer that packed the frames as one bit stream across frame boundaries is read too).

    Raises:
        InputError: the pixel data cannot be decoded; the message names the transfer syntax.
    """
    uid, ts = _ts(ds)
    rows, cols, n = int(ds.Rows), int(ds.Columns), _frame_count(ds)
    bits = int(ds.get("BitsAllocated", 1))
    if "PixelData" not in ds:
        raise InputError(f"{label}: a SEG without pixel data")
    try:
        if uid == DEFLATED_FRAMES or (uid == RLE_LOSSLESS and bits == 1):
            try:
                raw = [_decode_item(item, uid) for item in _items(ds, n)]
            except InputError as exc:
                raise InputError(f"{label}: its pixel data in transfer syntax {ts} cannot be decoded: {exc}") from None
            pixels = _unpack(raw, n, rows, cols, bits, f"{label} ({ts})")
        else:
            pixels = np.asarray(ds.pixel_array)
    except InputError:
        raise
    except Exception as exc:  # pydicom raises NotImplementedError, RuntimeError, ValueError... for what it lacks
        first = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else type(exc).__name__
        raise InputError(
            f"{label}: its pixel data in transfer syntax {ts} cannot be decoded ({first}); send the SEG in an "
            "uncompressed transfer syntax (Explicit VR Little Endian), RLE Lossless, JPEG 2000 or Deflated Image "
            "Frame Compression"
        ) from None
    if pixels.size != n * rows * cols:
        raise InputError(f"{label}: {pixels.size} pixel values for {n} frames of {rows} x {cols} ({ts})")
    return pixels.reshape(n, rows, cols)


def _frame_count(ds: Any) -> int:
    try:
        return max(int(ds.get("NumberOfFrames", 1) or 1), 1)
    except (TypeError, ValueError):
        return 1


def _items(ds: Any, n: int) -> list[bytes]:
    """The encoded frames of encapsulated pixel data (one item each; several fragments of a frame joined)."""
    from pydicom.encaps import generate_frames

    if not getattr(ds["PixelData"], "is_undefined_length", True):
        raise InputError("the transfer syntax is encapsulated but the pixel data are not (a damaged file)")
    return list(generate_frames(ds.PixelData, number_of_frames=n))


def _decode_item(item: bytes, uid: str) -> bytes:
    """One encoded frame's bytes: raw Deflate (a zlib or gzip wrapper tolerated), or RLE Lossless of one segment."""
    if uid == DEFLATED_FRAMES:
        for wbits in (-15, 47):
            try:
                return zlib.decompressobj(wbits).decompress(item)
            except zlib.error:
                continue
        raise InputError("a frame is not Deflate data")
    return _rle_segments(item)


def _rle_segments(item: bytes) -> bytes:
    """An RLE Lossless frame (PS3.5 Annex G) of 1-bit samples: its one segment, PackBits-decoded."""
    if len(item) < 64:
        raise InputError(f"an RLE frame of {len(item)} bytes, shorter than its 64-byte header")
    header = np.frombuffer(item[:64], dtype="<u4")
    count = int(header[0])
    if count != 1:
        raise InputError(f"an RLE frame of 1-bit samples with {count} segments (expected 1)")
    start = int(header[1])
    if not 64 <= start < len(item):
        raise InputError(f"an RLE segment offset {start} outside its frame of {len(item)} bytes")
    return _packbits(item[start:])


def _packbits(data: bytes) -> bytes:
    """PackBits (TIFF 6.0 / DICOM RLE): a header byte n >= 0 copies n + 1 bytes, n in -127..-1 repeats the next
    byte 1 - n times, -128 is a no-op."""
    out = bytearray()
    i, end = 0, len(data)
    while i < end:
        n = data[i]
        i += 1
        if n < 128:
            out += data[i : i + n + 1]
            i += n + 1
        elif n > 128:
            if i < end:
                out += data[i : i + 1] * (257 - n)
            i += 1
    return bytes(out)


def _unpack(raw: list[bytes], n: int, rows: int, cols: int, bits: int, label: str) -> np.ndarray:
    """Decoded frame bytes as (n, rows * cols) values: 1-bit values unpacked LSB first, else little-endian words."""
    npix = rows * cols
    if bits != 1:
        if bits not in (8, 16, 32):
            raise InputError(f"{label}: {bits} bits allocated per pixel")
        dtype = np.dtype(f"<u{bits // 8}")
        need = npix * dtype.itemsize
        if len(raw) != n or any(len(r) < need for r in raw):
            raise InputError(f"{label}: {len(raw)} decoded frames shorter than {need} bytes each ({n} expected)")
        return np.stack([np.frombuffer(r, dtype=dtype, count=npix) for r in raw])
    per = -(-npix // 8)
    if len(raw) == n and all(len(r) >= per for r in raw):  # each frame from a byte boundary (PS3.5 8.2)
        out = np.empty((n, npix), dtype=np.uint8)
        for f, r in enumerate(raw):
            out[f] = np.unpackbits(np.frombuffer(r, dtype=np.uint8, count=per), bitorder="little")[:npix]
        return out
    stream = b"".join(raw)  # one bit stream across frame boundaries, as native 1-bit pixel data is
    total = -(-n * npix // 8)
    if len(stream) < total:
        raise InputError(
            f"{label}: the decoded frames hold {len(stream)} bytes, fewer than the {total} that {n} frames of "
            f"{rows} x {cols} 1-bit pixels need"
        )
    flat = np.unpackbits(np.frombuffer(stream, dtype=np.uint8, count=total), bitorder="little")
    return flat[: n * npix].reshape(n, npix)


@dataclass
class _Placement:
    """Where each frame goes: the grid's shape, each frame's slice and corner (k, j0, i0), and whether its rows and
    columns run backwards along the grid's."""

    shape: tuple[int, int, int]
    at: np.ndarray  # (F, 3) k, j0, i0
    flip_rows: bool = False  # the frame's row direction runs along -x
    flip_cols: bool = False  # the frame's column direction runs along -y


@dataclass
class _Painted:
    labels: np.ndarray
    painted: int
    overlaps: int
    losers: set[int]  # segments that lost voxels to a later one


def _paint(labels: np.ndarray, k: int, j0: int, i0: int, frame: np.ndarray, number: int) -> tuple[int, int, set[int]]:
    """Frame pixels into slice k at (j0, i0), clipped to the grid; returns (voxels painted, overlaps, the segments
    whose voxels the frame took)."""
    nz, ny, nx = labels.shape
    if not 0 <= k < nz:
        return 0, 0, set()
    r0, c0 = max(0, -j0), max(0, -i0)
    r1, c1 = min(frame.shape[0], ny - j0), min(frame.shape[1], nx - i0)
    if r0 >= r1 or c0 >= c1:
        return 0, 0, set()
    part = frame[r0:r1, c0:c1]
    dst = labels[k, j0 + r0 : j0 + r1, i0 + c0 : i0 + c1]
    values = part.astype(labels.dtype) if number == 0 else np.where(part != 0, number, 0).astype(labels.dtype)
    on = values != 0
    taken = on & (dst != 0) & (dst != values)
    losers = {int(v) for v in np.unique(dst[taken])} if taken.any() else set()
    dst[on] = values[on]
    return int(np.count_nonzero(on)), int(np.count_nonzero(taken)), losers


def _paint_all(fr: _Frames, pl: _Placement, dtype: Any, only: int | None = None) -> _Painted:
    """The frames (only segment ``only``'s when given) painted on the placement's grid."""
    labels = np.zeros(pl.shape, dtype=dtype)
    out = _Painted(labels, 0, 0, set())
    for f in range(len(fr.pixels)):
        if only is not None and int(fr.numbers[f]) != only:
            continue
        frame = fr.pixels[f][:: -1 if pl.flip_cols else 1, :: -1 if pl.flip_rows else 1]
        k, j0, i0 = (int(v) for v in pl.at[f])
        n, o, lost = _paint(labels, k, j0, i0, frame, int(fr.numbers[f]))
        out.painted, out.overlaps, out.losers = out.painted + n, out.overlaps + o, out.losers | lost
    return out


def _into_reference(fr: _Frames, ref: Volume, label: str) -> _Placement:
    """Where the frames go in the CT's grid."""
    direction = np.asarray(ref.direction, dtype=np.float64)
    if abs(fr.row @ direction[:, 0]) < 0.999 or abs(fr.col @ direction[:, 1]) < 0.999:
        raise LabelsOutsideScanError(
            f"{label}: the SEG's rows and columns do not run along the CT's; it is not on the CT's grid"
        )
    sp_xyz = np.asarray(ref.spacing_zyx_mm[::-1], dtype=np.float64)
    idx = ((fr.positions - np.asarray(ref.origin_mm)) @ np.linalg.inv(direction).T) / sp_xyz  # (F, 3) i, j, k
    if np.abs(idx - np.round(idx)).max() > _GRID_TOL:
        raise LabelsOutsideScanError(f"{label}: the SEG's frames do not lie on the CT's grid (off by a fraction)")
    idx = np.round(idx).astype(np.int64)
    flip_rows, flip_cols = bool(fr.row @ direction[:, 0] < 0), bool(fr.col @ direction[:, 1] < 0)
    rows, cols = fr.pixels.shape[1:]
    at = np.column_stack(
        [idx[:, 2], idx[:, 1] - (rows - 1 if flip_cols else 0), idx[:, 0] - (cols - 1 if flip_rows else 0)]
    )
    nz, ny, nx = ref.data.shape
    return _Placement((int(nz), int(ny), int(nx)), at, flip_rows, flip_cols)


def _own_grid(fr: _Frames, label: str) -> tuple[_Placement, tuple[float, ...], np.ndarray, np.ndarray]:
    """Where the frames go on the SEG's own grid, and that grid: (placement, spacing zyx, origin, direction)."""
    normal = np.cross(fr.row, fr.col)
    d = fr.positions @ normal
    levels = np.unique(np.round(d, 4))
    gaps = np.diff(levels)
    step = fr.slice_step or (float(gaps.min()) if len(gaps) else 1.0)
    k = np.round((d - levels[0]) / step).astype(np.int64)
    if len(gaps) and np.abs((levels - levels[0]) / step - np.round((levels - levels[0]) / step)).max() > _GRID_TOL:
        raise InputError(f"{label}: the SEG's frame positions are not on a regular grid of {step:g} mm")
    first = int(np.argmin(d))
    origin = fr.positions[first]
    rows, cols = fr.pixels.shape[1:]
    at = np.column_stack([k, np.zeros_like(k), np.zeros_like(k)])
    direction = np.column_stack([fr.row, fr.col, normal])
    placement = _Placement((int(k.max()) + 1, int(rows), int(cols)), at)
    return placement, (float(step), fr.spacing_rc[0], fr.spacing_rc[1]), origin, direction


def read_dicom_seg(
    path: str | Path | bytes | Any, *, reference: Volume | None = None, label: str | None = None
) -> LabelVolume:
    """A DICOM SEG (a path, its bytes or a pydicom data set) as a ``LabelVolume``: on ``reference``'s grid (its
    referenced CT) when given, else its own. ``label`` names it in messages (default: the file's name).

    Raises:
        MissingReferenceError: ``reference`` is another series than the one the SEG references.
        LabelsOutsideScanError: the SEG's frames are not on the CT's grid, or none of its voxels lands in it.
        NotLabelsError: the file is not a DICOM SEG.
        InputError: its frames cannot be placed or decoded (the message names the transfer syntax).
    """
    name = label or (Path(path).name if isinstance(path, (str, Path)) else "the SEG")
    ds = _dataset(path, name)
    segments = _segments(ds)
    fr = _frames(ds, name, alone=reference is None)
    dtype = np.uint8 if max(s.value for s in segments) < 256 else np.uint16
    wanted = referenced_series(ds)
    source: dict[str, Any] = {"format": "dicom-seg", "file": name, "encoding": str(ds.get("SegmentationType"))}
    source["referenced_series_uid"] = wanted
    if reference is not None:
        have = reference.source.get("series_uid")
        if wanted and have and wanted != have:
            raise MissingReferenceError(
                f"{name}: the SEG was drawn on series {wanted}, but the CT given is series {have}"
            )
        placement = _into_reference(fr, reference, name)
        source["placed_by"] = "Per-frame Plane Position into the referenced CT's grid"
        spacing, origin, direction = reference.spacing_zyx_mm, reference.origin_mm, reference.direction
    else:
        placement, sp, o, dmat = _own_grid(fr, name)
        source["placed_by"] = "Per-frame Plane Position on the SEG's own grid"
        spacing = (sp[0], sp[1], sp[2])
        origin = (float(o[0]), float(o[1]), float(o[2]))
        direction = tuple((float(r[0]), float(r[1]), float(r[2])) for r in dmat)
    done = _paint_all(fr, placement, dtype)
    if reference is not None and done.painted == 0:
        raise LabelsOutsideScanError(f"{name}: no labelled voxel of the SEG lies inside the referenced CT")
    labels = done.labels
    # segments are independent masks: each that lost voxels to a later one keeps its whole mask
    masks: dict[int, np.ndarray] = {}
    for value in sorted(done.losers):
        masks[value] = _paint_all(fr, placement, np.uint8, only=value).labels != 0
    if done.overlaps:
        source["overlap_voxels"] = done.overlaps
    return make_label_volume(labels, spacing, origin, direction, segments, source, masks=masks)


def read_seg_folder(folder: str | Path, label: str | None = None) -> LabelVolume:
    """The SEG of a folder, zip or tar archive placed on its referenced CT series from the same input
    (``engine.io.load_volume``, which leaves the SEG, a series of its own, aside).

    ``source["reference"]`` says what the CT's completeness checks found (``engine.io.completeness``).

    Raises:
        MissingReferenceError: the input lacks the series the SEG references (or the SEG names none).
        IncompleteSeriesError: the referenced series is there but incomplete.
        InputError: not exactly one SEG, or the CT cannot be loaded (the message says why).
    """
    from engine.errors import IncompleteSeriesError
    from engine.io import load_volume
    from engine.io.archive import open_members
    from engine.labels.sniff import SNIFF_BYTES, is_seg

    root = Path(folder)
    where = label or root.name
    with open_members(root, head_bytes=SNIFF_BYTES) as members:
        segs = [m for m in members.members if is_seg(m.head)]  # by the file meta
        if len(segs) != 1:
            raise InputError(f"{where}: expected one DICOM SEG, found {len(segs)}")
        seg_name, data = segs[0].name, segs[0].read()
    name = f"{where}: {seg_name}" if members.kind != "file" else where
    ds = _dataset(data, name)
    wanted = referenced_series(ds)
    if not wanted:
        raise MissingReferenceError(
            f"{name}: the SEG names no referenced series (ReferencedSeriesSequence) to place it on"
        )
    try:
        ct = load_volume(root, series_uid=wanted)
    except IncompleteSeriesError as exc:
        raise IncompleteSeriesError(f"{name}: the CT series it was drawn on ({wanted}): {exc}") from None
    except InputError as exc:
        text = str(exc)
        if f"has no series {wanted!r}" in text or "holds no DICOM images" in text:
            raise MissingReferenceError(
                f"{name}: its referenced series {wanted} (the CT it was drawn on) is not in {where}; send the SEG "
                "with that series"
            ) from None
        raise InputError(f"{name}: its CT series {wanted} cannot be loaded: {text}") from None
    lv = read_dicom_seg(ds, reference=ct, label=name)
    # what the CT's checks found: a model for the PACS is made only on a CT checked whole (``worker.pacs``)
    lv.source["reference"] = {"images": int(ct.data.shape[0]), "completeness": ct.source.get("completeness")}
    return lv
