"""DICOM series (with or without preamble/file meta, any pydicom-decodable transfer syntax) -> :class:`Volume`.

Slices are ordered by ImagePositionPatient projected on the normal of ImageOrientationPatient. Uneven gaps and
gantry tilt are resampled onto a regular, orthogonal grid whose axes are the image row/column directions and the
slice normal (``Volume.direction``): tilted slices are shifted in-plane (shear correction), then interpolated
linearly along the normal at the median gap. Multi-frame images (Enhanced CT, Legacy Converted Enhanced CT) are
read frame by frame from their functional groups (``engine.io.dicom_frames``): a slice per frame, through the same
checks. Before any of that, the series must be whole (``engine.io.completeness``).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from engine.errors import InputError
from engine.io.archive import InputLimits, Member, Members
from engine.io.completeness import check_count, check_numbering, check_positions, drop_identical, same_position_groups
from engine.io.dicom_frames import FrameError, frame_count, frame_member, frames, is_multiframe
from engine.io.dicom_pixels import quiet, read_dataset, series_pixels
from engine.io.parallel import ordered_map
from engine.io.procs import DecodePool, start_pool
from engine.io.readers import Where
from engine.io.regrid import regularise as _regularise
from engine.io.stack import SPACING_HINT, StackWarning, natural_key
from engine.params import check_spacing_zyx_mm
from engine.types import Volume

_RAW_GROUPS = (b"\x08\x00", b"\x02\x00", b"\x00\x08")  # first tag group of a dataset without preamble
_NO_UID = "(no SeriesInstanceUID)"
PROCESS_MIN_FILES = 64  # processes=None: processes from this many files (their start takes 0.02-0.5 s) ...
PROCESS_MIN_WORKERS = 4  # ... and this many decode workers (on 2 busy cores threads did better)


def looks_like_dicom(head: bytes) -> bool:
    """Whether a file's first bytes could start a DICOM file (preamble + DICM, or a raw data set)."""
    return head[128:132] == b"DICM" or head[:4] == b"DICM" or head[:2] in _RAW_GROUPS


@dataclass
class _Slice:
    member: Member
    uid: str
    rows: int
    cols: int
    ipp: np.ndarray | None
    iop: np.ndarray | None
    pixel_spacing: tuple[float, float] | None
    instance: int | None
    frames: int
    samples: int
    thickness: float | None
    header: dict[str, Any]
    nonfinite: tuple[str, ...] = ()  # geometry tags present but holding NaN or an infinity
    frame: int | None = None  # a multi-frame image's frame (from 0): ``member`` names the frame, ``file`` is the file
    file: Member | None = None
    unusable: str = ""  # why the image cannot be loaded (raised only when its series is the one loaded)


def _floats(value: Any, n: int) -> np.ndarray | None:
    try:
        arr = np.array([float(v) for v in value], dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if arr.size == n and np.all(np.isfinite(arr)) else None


def _nonfinite(ds: Any) -> tuple[str, ...]:
    """Geometry tags present but holding NaN or an infinity: refused, since a fallback (instance order, a default
    spacing) would build a model without a word."""
    bad = []
    for tag in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "SliceThickness"):
        value = ds.get(tag)
        with contextlib.suppress(TypeError, ValueError):
            if value not in (None, "") and not np.all(np.isfinite(np.array(value, dtype=np.float64))):
                bad.append(tag)
    return tuple(bad)


def _scan(
    members: Members,
    on_progress: Callable[[float], None] | None = None,
    threads: int = 1,
    procs: DecodePool | None = None,
) -> tuple[list[_Slice], int]:
    """Headers of every DICOM image member, a slice per frame of a multi-frame image (read and parsed on ``threads``
    threads, or in ``procs``' processes); also the count of DICOM files without pixel data."""
    slices: list[_Slice] = []
    non_image = 0
    n = len(members.members)
    if procs is None:
        results = ordered_map(_header, members.members, threads)
    else:
        located = [(m.where, m.head) for m in members.members]
        results = ordered_map(_header_at, located, procs.workers, procs.pool, procs.chunk(n))  # type: ignore[arg-type]
    with quiet(), contextlib.closing(results) as found_all:
        for k, found in enumerate(found_all):
            if on_progress is not None:
                on_progress((k + 1) / n)
            if found == "non-image":
                non_image += 1
            elif isinstance(found, list):
                slices.extend(found if procs is None else [_attach(s, members.members[k]) for s in found])
    return slices, non_image


def _header_at(item: tuple[Where, bytes]) -> list[_Slice] | str | None:
    """In a decode process: :func:`_header` of a member read through its :class:`Where`; the slices come back
    with a member that only names them (the caller puts its own back: :func:`_attach`)."""
    where, head = item
    if not looks_like_dicom(head):
        return None
    found = _header(Member.at(where, head))
    if not isinstance(found, list):
        return found
    return [replace(s, member=Member(s.member.name, where.size, head), file=None) for s in found]


def _attach(found: _Slice, m: Member) -> _Slice:
    """A slice scanned in a decode process, with this process's member ``m`` back (under its frame's name)."""
    if found.frame is None:
        return replace(found, member=m)
    return replace(found, member=frame_member(m, found.frame), file=m)


@contextlib.contextmanager
def _decode_pool(members: Members, threads: int, processes: bool | None) -> Iterator[DecodePool | None]:
    """Processes for the series' parsing and decoding where they are wanted and possible, else None (threads)."""
    dicom = [m for m in members.members if looks_like_dicom(m.head)]
    wanted = len(dicom) >= PROCESS_MIN_FILES and threads >= PROCESS_MIN_WORKERS if processes is None else processes
    if not wanted or threads < 2 or len(dicom) < 2 or any(m.where is None for m in dicom):
        yield None
        return
    with start_pool(min(threads, len(dicom))) as procs:
        yield procs


def _header(m: Member) -> list[_Slice] | str | None:
    """One member's header as a :class:`_Slice`, or one per frame of a multi-frame image (``_frames``);
    "non-image" for DICOM without pixels; None for other files."""
    if not looks_like_dicom(m.head):
        return None
    ds = read_dataset(m, pixels=True)
    if ds is None:
        return None
    if "PixelData" not in ds or "Rows" not in ds or "Columns" not in ds:
        return "non-image"  # DICOMDIR, structured report, presentation state...
    ps = _floats(ds.get("PixelSpacing") or ds.get("ImagerPixelSpacing") or (), 2)
    iop = _floats(ds.get("ImageOrientationPatient") or (), 6)
    ipp = _floats(ds.get("ImagePositionPatient") or (), 3)
    inst = ds.get("InstanceNumber")
    thick = ds.get("SpacingBetweenSlices") or ds.get("SliceThickness")
    header = {
        "modality": str(ds.get("Modality", "")),
        "manufacturer": str(ds.get("Manufacturer", "")),
        "transfer_syntax": ds.file_meta.TransferSyntaxUID.name,
        "transfer_syntax_uid": str(ds.file_meta.TransferSyntaxUID),
        "gantry_tilt_deg": float(ds.get("GantryDetectorTilt") or 0.0),
        "slope": float(ds.get("RescaleSlope", 1) or 1),
        "intercept": float(ds.get("RescaleIntercept", 0) or 0),
        "series_number": str(ds.get("SeriesNumber", "") or ""),
        "sop_class_uid": str(ds.get("SOPClassUID", "") or ""),
        "sop_instance_uid": str(ds.get("SOPInstanceUID", "") or ""),
    }
    one = _Slice(
        member=m,
        uid=str(ds.get("SeriesInstanceUID", _NO_UID)),
        rows=int(ds.Rows),
        cols=int(ds.Columns),
        ipp=ipp,
        iop=iop,
        pixel_spacing=(float(ps[0]), float(ps[1])) if ps is not None and np.all(ps > 0) else None,
        instance=int(inst) if inst not in (None, "") else None,
        frames=frame_count(ds),
        samples=int(ds.get("SamplesPerPixel", 1) or 1),
        thickness=float(thick) if thick not in (None, "") and float(thick) > 0 else None,
        header=header,
        nonfinite=_nonfinite(ds),
    )
    return _frames(one, ds) if is_multiframe(ds) else [one]


def _frames(one: _Slice, ds: Any) -> list[_Slice]:
    """A multi-frame image as a slice per frame, with the geometry and rescale of its functional groups
    (``engine.io.dicom_frames``); one unusable slice, saying why, when its frames cannot be placed."""
    m = one.member
    try:
        found = frames(ds, m.name)
    except FrameError as exc:
        return [replace(one, unusable=str(exc))]
    return [
        replace(
            one,
            member=frame_member(m, f.index),
            file=m,
            frame=f.index,
            ipp=f.ipp,
            iop=f.iop,
            pixel_spacing=f.pixel_spacing,
            thickness=f.thickness,
            instance=None,  # one InstanceNumber for all the frames: their order comes from their positions
            nonfinite=f.nonfinite,
            header={**one.header, "slope": f.slope, "intercept": f.intercept, "gantry_tilt_deg": f.gantry_tilt_deg},
        )
        for f in found
    ]


def has_dicom_images(members: Members) -> bool:
    """Whether any member starts like a DICOM file (cheap check on the first bytes only)."""
    return any(looks_like_dicom(m.head) for m in members.members)


def load_dicom(
    members: Members,
    label: str,
    *,
    spacing_zyx_mm: tuple[float, float, float] | None,
    series_uid: str | None,
    limits: InputLimits,
    on_progress: Callable[[float], None] | None = None,
    threads: int = 1,
    processes: bool | None = None,
) -> Volume | None:
    """Load one DICOM series of ``members``; None when none of them is a DICOM image. Files are read, parsed and
    decoded on ``threads`` threads (``engine.io.parallel``), or in as many processes (``engine.io.procs``: pydicom's
    parsing holds the GIL); the result does not depend on either.

    Args:
        processes: decode in processes (True), on threads (False), or by default (None) in processes for inputs of
            at least ``PROCESS_MIN_FILES`` DICOM files and ``threads`` >= ``PROCESS_MIN_WORKERS``. Only with
            ``threads`` >= 2; threads where processes cannot be started (a daemonic process, a compressed tar's
            spooled members, no ``memfd_create``, a fork server that does not start).

    Raises:
        InputError: unknown ``series_uid``, inconsistent geometry, undecodable pixels, limits exceeded.
    """
    with _decode_pool(members, threads, processes) as procs:
        slices, non_image = _scan(members, on_progress, threads, procs)  # reading the files is most of the time
        if not slices:
            if series_uid is not None:
                raise InputError(f"series_uid={series_uid!r} was given, but {label} holds no DICOM images")
            return None
        series, choice = _pick_series(slices, series_uid, label)
        skipped = len(slices) - len(series) + non_image
        vol = _build(series, label, spacing_zyx_mm, limits, skipped=skipped, threads=threads, procs=procs)
    vol.source["series"] = choice
    return vol


def _describe(group: list[_Slice]) -> dict[str, Any]:
    """A series as the report names it: UID, number, modality and image count; never its free-text description
    (it may hold names or clinical details)."""
    h = group[0].header
    return {"uid": group[0].uid, "number": h["series_number"], "modality": h["modality"], "images": len(group)}


def _pick_series(slices: list[_Slice], series_uid: str | None, label: str) -> tuple[list[_Slice], dict[str, Any]]:
    """The series to load: the one named, else the largest CT series (the largest of any modality when none is
    CT); also what the report says of the choice (``used``, ``ignored``, ``rule``)."""
    groups: dict[str, list[_Slice]] = defaultdict(list)
    for s in slices:
        groups[s.uid].append(s)
    listing = "; ".join(f"{uid} ({len(g)} images)" for uid, g in sorted(groups.items(), key=lambda kv: -len(kv[1])))
    if series_uid is not None:
        if series_uid not in groups:
            raise InputError(f"{label} has no series {series_uid!r}; available: {listing}")
        best_uid, rule = series_uid, "named by series_uid"
    else:
        ct = [uid for uid, g in groups.items() if g[0].header["modality"].upper() == "CT"]
        candidates = ct or list(groups)
        best_uid = max(candidates, key=lambda uid: len(groups[uid]))
        rule = "the largest CT series" if ct else "the largest series (none is CT)"
    ignored = [_describe(g) for uid, g in sorted(groups.items(), key=lambda kv: -len(kv[1])) if uid != best_uid]
    choice = {"rule": rule, "used": _describe(groups[best_uid]), "ignored": ignored}
    if series_uid is None and len(groups) > 1:
        warnings.warn(
            f"{label} holds {len(groups)} DICOM series; loading {rule} ({len(groups[best_uid])} images, the others "
            f"are ignored). Choose with series_uid=: {listing}",
            StackWarning,
            stacklevel=4,
        )
    return groups[best_uid], choice


def _build(
    series: list[_Slice],
    label: str,
    call: tuple[float, float, float] | None,
    limits: InputLimits,
    skipped: int,
    threads: int = 1,
    procs: DecodePool | None = None,
) -> Volume:
    first = series[0]
    for s in series:
        if s.nonfinite:
            raise InputError(
                f"{label}: {s.member.name} holds NaN or an infinity in {', '.join(s.nonfinite)}, so where its pixels "
                "lie is unknown; refusing the series (re-export it from the scanner or PACS)"
            )
        if s.unusable:
            raise InputError(f"{label}: {s.unusable}")
        if s.samples != 1:
            raise InputError(f"{s.member.name} is a colour DICOM ({s.samples} samples/pixel); expected grayscale CT/MR")
        if (s.rows, s.cols) != (first.rows, first.cols):
            raise InputError(
                f"expected every image of the series to be {first.cols}x{first.rows} like {first.member.name}, "
                f"got {s.cols}x{s.rows} in {s.member.name}"
            )
    series, duplicates = _drop_duplicates(series, label, threads, procs)
    geo = _geometry(series, label, call)
    order = geo["order"]
    series = [series[i] for i in order]
    limits.check_voxels((len(series), first.rows, first.cols), label)
    data, units, fill = series_pixels(series, threads, procs)
    source: dict[str, Any] = {
        "format": "dicom",
        "files": len({(s.file or s.member).name for s in series}),
        "images": len(series),
        "other_files_skipped": skipped,
        "modality": first.header["modality"],
        "manufacturer": first.header["manufacturer"],
        "transfer_syntax": first.header["transfer_syntax"],
        "series_uid": first.uid,
    }
    completeness = geo["completeness"]
    completeness.duplicates_dropped = duplicates
    source["completeness"] = completeness.report()
    d, a, b = geo["d"], geo["a"], geo["b"]
    gaps = np.diff(d)
    source["original_gaps_mm"] = [round(float(g), 4) for g in gaps]
    sy, sx = geo["yx"]
    if geo["regular"]:
        sz = geo["z"]
        origin = geo["p0"]
        source["resampled"] = False
    else:
        data, sz, (oy, ox) = _regularise(data, d, a / sx, b / sy, geo["z"], fill, limits, label)
        origin = geo["p0"] + ox * sx * geo["row"] + oy * sy * geo["col"]
        source["resampled"] = True
        source["gantry_tilt_deg"] = round(geo["tilt_deg"], 3)
        if geo["tilt_deg"] > 0:
            source["completeness"]["layout"] += " with gantry tilt"
        source["completeness"]["resampled"] = True
    spacing = (float(sz), float(sy), float(sx))
    try:
        check_spacing_zyx_mm(spacing)
    except ValueError as exc:
        raise InputError(f"{label}: the DICOM headers give an implausible voxel size: {exc}") from None
    if call is not None and geo["from_file"] and not np.allclose(call, spacing, rtol=0.01):
        raise InputError(
            f"{label}: the DICOM series defines its voxel size (z, y, x = {spacing[0]:g}, {spacing[1]:g}, "
            f"{spacing[2]:g} mm), but spacing_zyx_mm={tuple(call)} was given; leave the spacing out for DICOM input"
        )
    direction = tuple(tuple(float(v) for v in row) for row in np.column_stack([geo["row"], geo["col"], geo["n"]]))
    return Volume(
        data=data,
        spacing_zyx_mm=spacing,
        origin_mm=tuple(float(v) for v in origin),  # type: ignore[arg-type]
        direction=direction,
        units=units,
        source=source,
        patient_frame=bool(geo.get("oriented", False)),
        instances=tuple(_instance_of(s) for s in series),
    )


def _instance_of(s: _Slice) -> tuple[str, str, int | None]:
    """(SOP Class UID, SOP Instance UID, frame number or None) of the image a slice came from."""
    frame = getattr(s, "frame", None)
    return s.header["sop_class_uid"], s.header["sop_instance_uid"], None if frame is None else int(frame) + 1


def _drop_duplicates(
    series: list[_Slice], label: str, threads: int, procs: DecodePool | None
) -> tuple[list[_Slice], int]:
    """The series without repeated images: the same SOP instance received twice, or two images at one position
    whose pixels are identical; the count dropped.

    Raises:
        IncompleteSeriesError: two images at one position with different pixels.
    """
    seen: set[tuple[str, Any]] = set()
    unique = []
    for s in series:
        key = (s.header["sop_instance_uid"], getattr(s, "frame", None))
        if not key[0] or key not in seen:
            unique.append(s)
            seen.add(key)
    if not all(s.ipp is not None and s.iop is not None for s in unique) or len(unique) < 2:
        return unique, len(series) - len(unique)
    iop0 = unique[0].iop
    normal = np.cross(iop0[:3], iop0[3:])  # type: ignore[index]
    normal /= max(float(np.linalg.norm(normal)), 1e-12)
    order = list(np.argsort(np.array([s.ipp @ normal for s in unique]), kind="stable"))  # type: ignore[operator]
    ordered = [unique[i] for i in order]
    d = np.array([s.ipp @ normal for s in ordered])  # type: ignore[operator]
    groups = same_position_groups(d)
    if groups:
        members = sorted({k for g in groups for k in g})
        data, _, _ = series_pixels([ordered[k] for k in members], threads, None)  # the pool holds one array
        where = {k: j for j, k in enumerate(members)}
        names = [s.member.name for s in ordered]
        keep = drop_identical(data, [[where[k] for k in g] for g in groups], [names[k] for k in members], label)
        kept = {members[j] for j in keep}
        ordered = [s for k, s in enumerate(ordered) if k not in set(members) or k in kept]
    return ordered, len(series) - len(ordered)


def _thickness(series: list[_Slice]) -> float | None:
    """The series' slice thickness (median over the images that carry it), or None."""
    values = [s.thickness for s in series if s.thickness]
    return float(np.median(values)) if values else None


def _geometry(series: list[_Slice], label: str, call: tuple[float, float, float] | None) -> dict[str, Any]:
    """Slice order, positions along the normal (d) and in-plane offsets (a along rows, b along columns) in mm."""
    n_sl = len(series)
    check_count(n_sl, label)
    geo: dict[str, Any] = {"from_file": True, "tilt_deg": 0.0}
    spacings = {s.pixel_spacing for s in series}
    if None in spacings or len(spacings) != 1:
        if None in spacings and call is None:
            raise InputError(f"{label}: the DICOM images carry no PixelSpacing; {SPACING_HINT}")
        if None not in spacings:
            raise InputError(f"{label}: the images of the series have different PixelSpacing values {sorted(spacings)}")
        geo["from_file"] = False
    geo["yx"] = next(iter(spacings)) if geo["from_file"] else (call[1], call[2])  # type: ignore[index]
    if all(s.ipp is not None and s.iop is not None for s in series):
        iop0 = series[0].iop
        assert iop0 is not None
        for s in series:
            if not np.allclose(s.iop, iop0, atol=1e-3):  # type: ignore[arg-type]
                raise InputError(
                    f"{label}: the image orientation changes within the series ({series[0].member.name} vs "
                    f"{s.member.name}); such a series cannot be put on one grid (localizer mixed in, or a "
                    "variable-tilt acquisition): export the axial series on its own"
                )
        geo["oriented"] = True  # origin and axes in the patient frame (LPS), from the headers
        row, col = iop0[:3] / np.linalg.norm(iop0[:3]), iop0[3:] / np.linalg.norm(iop0[3:])
        if abs(float(row @ col)) > 1e-3:
            raise InputError(f"{label}: ImageOrientationPatient rows and columns are not perpendicular ({iop0})")
        normal = np.cross(row, col)
        pos = np.array([s.ipp for s in series])
        order = list(np.argsort(pos @ normal, kind="stable"))
        pos = pos[order]
        d = pos @ normal
        rel = pos - pos[0]
        a, b = rel @ row, rel @ col
    else:
        if any(s.instance is None for s in series):
            raise InputError(
                f"{label}: the images have neither ImagePositionPatient/ImageOrientationPatient nor InstanceNumber, "
                "so their order is unknown"
            )
        order = sorted(range(n_sl), key=lambda i: (series[i].instance, natural_key(series[i].member.name)))
        thick = series[0].thickness if call is None else call[0]
        if thick is None:
            raise InputError(f"{label}: the DICOM images carry no slice positions or thickness; {SPACING_HINT}")
        row, col, normal = np.eye(3)
        d = np.arange(n_sl) * float(thick)
        a = b = np.zeros(n_sl)
        pos = np.zeros((1, 3))
        geo["from_file"] = geo["from_file"] and call is None
    gaps = np.diff(d)
    names = [series[i].member.name for i in order]
    if n_sl > 1 and gaps.min() < 1e-3:
        k = int(np.argmin(gaps))
        raise InputError(
            f"{label}: two images lie at the same slice position ({names[k]} and {names[k + 1]}): the series mixes "
            "repeated acquisitions; keep one of them"
        )
    if geo.get("oriented"):
        geo["completeness"] = check_positions(d, names, label, _thickness(series))
    else:  # no positions: the instance numbers stand for them
        instances = [f"instance {series[i].instance}" for i in order]
        geo["completeness"] = check_numbering(instances, label)
        geo["completeness"].layout = "ordered by instance number (no positions)"
    sy, sx = geo["yx"]
    med = float(np.median(gaps))
    even = float(gaps.max() - gaps.min()) <= max(0.01 * med, 0.01)
    straight = float(np.ptp(a)) <= 0.05 * sx and float(np.ptp(b)) <= 0.05 * sy
    geo["z"] = float(d[-1] - d[0]) / (n_sl - 1) if (even and n_sl > 1) else med
    if not straight:
        shear = math.hypot(float(np.ptp(a)), float(np.ptp(b))) / max(float(d[-1] - d[0]), 1e-9)
        geo["tilt_deg"] = math.degrees(math.atan(shear))
    geo.update(order=order, d=d, a=a, b=b, row=row, col=col, n=normal, p0=pos[0], regular=even and straight)
    return geo
