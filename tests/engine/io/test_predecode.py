"""Slices decoded while the upload arrives (``engine.io.predecode``, ``engine.io.zipstream``): fed the archive in
any chunking, the sidecar gives the loader's volume exactly (same samples, order, report), for zips made by
Python's zipfile (stored, deflated, streamed with data descriptors, zip64) and by Info-ZIP's ``zip``; whatever
the loader would not read as that stack leaves no sidecar, and the job's mesh is the same either way."""

from __future__ import annotations

import io
import json
import shutil
import struct
import subprocess
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import IncompleteSeriesError, InputError
from engine.io import load_volume
from engine.io.png_rows import DeviceRows
from engine.io.predecode import PLANES, ROWS, UploadDecoder, load_predecoded, sidecar_paths
from engine.io.zipstream import CannotStream, ZipStream
from tests.engine.pngfactory import encode_png, gray_slices, png_of_stream

SPACING = (1.0, 0.5, 0.5)


class _Unseekable(io.RawIOBase):
    """A pipe-like sink: zipfile then writes data descriptors (sizes after the data)."""

    def __init__(self) -> None:
        self.data = bytearray()

    def writable(self) -> bool:
        return True

    def write(self, b: object) -> int:
        view = memoryview(b)  # type: ignore[arg-type]
        self.data += view
        return view.nbytes


def _pngs(n: int = 6, shape: tuple[int, int] = (12, 10), dtype: type = np.uint16, seed: int = 1) -> list[bytes]:
    slices = gray_slices(np.random.default_rng(seed), n, shape, dtype)
    filters = np.random.default_rng(seed).integers(0, 5, size=shape[0])
    return [encode_png(s, filters) for s in slices]


def _zip(
    members: list[tuple[str, bytes]], *, method: int = zipfile.ZIP_STORED, streamed: bool = False, zip64: bool = False
) -> bytes:
    sink: io.RawIOBase | io.BytesIO = _Unseekable() if streamed else io.BytesIO()
    with zipfile.ZipFile(sink, "w", compression=method) as zf:
        for name, data in members:
            if streamed:
                with zf.open(name, "w", force_zip64=zip64) as fh:
                    fh.write(data)
            else:
                zf.writestr(name, data)
    return bytes(sink.data) if isinstance(sink, _Unseekable) else sink.getvalue()


def _named(pngs: list[bytes]) -> list[tuple[str, bytes]]:
    return [(f"scan/slice_{i:03d}.png", p) for i, p in enumerate(pngs)]


def _decode(upload: Path, data: bytes, chunk: int, layout: str = PLANES) -> UploadDecoder:
    """Write ``data`` to ``upload`` and feed it to a decoder in ``chunk``-byte pieces, then finish."""
    dec = UploadDecoder(upload, threads=2, layout=layout)
    with upload.open("wb") as fh:
        for i in range(0, len(data), chunk):
            piece = memoryview(data)[i : i + chunk]
            fh.write(piece)
            dec.feed([piece])
    dec.finish()
    return dec


def _same_as_loader(upload: Path, spacing: tuple[float, float, float] = SPACING, rows: Any = None) -> None:
    got = load_predecoded(upload, spacing_zyx_mm=spacing, rows=rows)
    assert got is not None
    ref = load_volume(upload, spacing_zyx_mm=spacing)
    assert got.data.dtype == ref.data.dtype and np.array_equal(got.data, ref.data)
    assert got.spacing_zyx_mm == ref.spacing_zyx_mm
    assert got.source == {**ref.source, "decoded_during_upload": True}


def _nothing_left(upload: Path) -> bool:
    return not any(p.exists() for p in sidecar_paths(upload))


@pytest.mark.parametrize(
    ("method", "streamed", "zip64"),
    [
        (zipfile.ZIP_STORED, False, False),
        (zipfile.ZIP_DEFLATED, False, False),
        (zipfile.ZIP_STORED, True, False),
        (zipfile.ZIP_DEFLATED, True, False),
        (zipfile.ZIP_DEFLATED, True, True),
        (zipfile.ZIP_STORED, True, True),
    ],
    ids=["stored", "deflated", "stored-descriptor", "deflated-descriptor", "deflated-zip64", "stored-zip64"],
)
@pytest.mark.parametrize("chunk", [1, 7, 1 << 30], ids=["1B", "7B", "whole"])
def test_fed_in_any_chunks_it_is_the_loaders_volume(
    tmp_path: Path, method: int, streamed: bool, zip64: bool, chunk: int
) -> None:
    data = _zip(_named(_pngs(4 if chunk == 1 else 6)), method=method, streamed=streamed, zip64=zip64)
    dec = _decode(tmp_path / "upload", data, chunk)
    assert dec.reason is None
    _same_as_loader(tmp_path / "upload")


def test_the_bundled_zip_and_one_made_by_info_zip(tmp_path: Path) -> None:
    upload = tmp_path / "upload"
    assert _decode(upload, HEADSQ_ZIP.read_bytes(), 64 << 10).reason is None  # the repository's own fixture
    _same_as_loader(upload, HEADSQ_SPACING_ZYX_MM)
    if shutil.which("zip") is None:
        pytest.skip("no zip command")
    folder = tmp_path / "slices"
    folder.mkdir()
    for i, png in enumerate(_pngs(8, dtype=np.uint8)):
        (folder / f"img{i}.png").write_bytes(png)  # natural order: img2 before img10
    (folder / "notes.txt").write_text("scanned on a Tuesday")  # not an image: the loader passes it by
    made = tmp_path / "made.zip"
    subprocess.run(["zip", "-q", "-r", str(made), "slices"], cwd=tmp_path, check=True)
    upload2 = tmp_path / "upload2"
    assert _decode(upload2, made.read_bytes(), 4096).reason is None
    _same_as_loader(upload2)
    piped = subprocess.run(  # Info-ZIP writing to a pipe: data descriptors, streamed
        ["zip", "-q", "-r", "-", "slices"], cwd=tmp_path, check=True, capture_output=True
    ).stdout
    upload3 = tmp_path / "upload3"
    assert _decode(upload3, piped, 1000).reason is None
    _same_as_loader(upload3)


def test_members_out_of_order_and_junk(tmp_path: Path) -> None:
    """The archive's order is not the stack's: the planes are read in the loader's (natural name) order; junk the
    loader skips is skipped."""
    pngs = _pngs(12)
    members = [(f"s/{i}.png", p) for i, p in enumerate(pngs)][::-1]
    members.insert(3, ("__MACOSX/s/._1.png", b"\x00\x05\x16\x07junk"))
    members.insert(5, ("s/", b""))
    data = _zip(members, method=zipfile.ZIP_DEFLATED)
    assert _decode(tmp_path / "upload", data, 999).reason is None
    _same_as_loader(tmp_path / "upload")


@pytest.mark.parametrize(
    "case", ["corrupt", "tiff", "dicom", "colour", "shapes", "truncated", "encrypted-like", "prefix"]
)
def test_what_it_cannot_vouch_for_leaves_no_sidecar(tmp_path: Path, case: str) -> None:
    pngs = _pngs(5)
    members = _named(pngs)
    if case == "corrupt":  # a damaged stream in one slice: libpng refuses it
        bad = bytearray(pngs[2])
        bad[60:80] = bytes(20)
        members[2] = (members[2][0], bytes(bad))
    elif case == "tiff":  # the loader reads it; the sidecar holds PNG slices only
        members[1] = ("scan/slice_001.tif", b"II*\x00" + bytes(100))
    elif case == "dicom":  # the loader reads the archive as DICOM then
        members.append(("scan/ct.dcm", bytes(128) + b"DICM" + bytes(64)))
    elif case == "colour":
        members[4] = (members[4][0], pngs[4][:25] + b"\x02" + pngs[4][26:])
    elif case == "shapes":
        members[3] = (members[3][0], _pngs(1, shape=(8, 8))[0])
    data = _zip(members, method=zipfile.ZIP_DEFLATED if case == "dicom" else zipfile.ZIP_STORED)
    if case == "truncated":  # the central directory never comes
        data = data[: len(data) // 2]
    elif case == "encrypted-like":
        at = data.index(b"PK\x03\x04", 10)
        data = data[: at + 6] + b"\x01" + data[at + 7 :]
    elif case == "prefix":  # a self-extracting stub before the first member
        data = b"#!/bin/sh\nexit 0\n" + data
    upload = tmp_path / "upload"
    dec = _decode(upload, data, 777)
    assert dec.reason is not None and _nothing_left(upload)
    assert load_predecoded(upload, spacing_zyx_mm=SPACING) is None


def test_a_sidecar_that_is_not_this_uploads_is_not_read(tmp_path: Path) -> None:
    upload = tmp_path / "upload"
    assert _decode(upload, _zip(_named(_pngs(5))), 1 << 20).reason is None
    manifest = sidecar_paths(upload)[1]
    good = manifest.read_text()
    manifest.write_text(good.replace('"boot_id": "', '"boot_id": "before a crash '))  # planes never fsynced
    assert load_predecoded(upload, spacing_zyx_mm=SPACING) is None
    manifest.write_text(good)
    assert load_predecoded(upload, spacing_zyx_mm=SPACING) is not None
    other = _zip(_named(_pngs(5, seed=9)))  # another scan of the same size, the old sidecar left beside it
    upload.write_bytes(other)
    assert load_predecoded(upload, spacing_zyx_mm=SPACING) is None  # its CRCs are not the manifest's


def test_the_loaders_refusals_stay_its_own(tmp_path: Path) -> None:
    """A hole in the numbering is refused as the loader refuses it; no voxel size: the loader's error too."""
    members = [(f"s/slice_{i}.png", p) for i, p in zip((0, 1, 2, 3, 5, 6), _pngs(6), strict=True)]
    upload = tmp_path / "upload"
    assert _decode(upload, _zip(members), 1 << 20).reason is None
    with pytest.raises(IncompleteSeriesError):
        load_predecoded(upload, spacing_zyx_mm=SPACING)
    with pytest.raises(IncompleteSeriesError):
        load_volume(upload, spacing_zyx_mm=SPACING)


def test_abort_keeps_nothing_and_a_slow_pool_holds_the_feed(tmp_path: Path) -> None:
    upload = tmp_path / "upload"
    data = _zip(_named(_pngs(8)))
    dec = UploadDecoder(upload, threads=1, backlog_bytes=1)  # at most one member waiting at a time
    dec.feed([data[: len(data) // 2]])
    assert sidecar_paths(upload)[0].exists()
    dec.abort()
    assert _nothing_left(upload)
    dec.feed([data[len(data) // 2 :]])  # after abort: ignored, nothing written
    assert _nothing_left(upload)


def test_the_stream_reader_refuses_what_it_cannot_follow() -> None:
    with pytest.raises(CannotStream):
        ZipStream().feed(b"not a zip at all")
    data = _zip(_named(_pngs(2)), method=zipfile.ZIP_DEFLATED)
    stream = ZipStream(max_member_bytes=100)
    with pytest.raises(CannotStream):
        stream.feed(data)


def test_a_host_memory_bound_reads_the_sidecar_slab_by_slab(tmp_path: Path) -> None:
    upload = tmp_path / "upload"
    assert _decode(upload, _zip(_named(_pngs(6))[::-1]), 1 << 20).reason is None
    vol = load_predecoded(upload, spacing_zyx_mm=SPACING, whole_bytes=100)
    ref = load_volume(upload, spacing_zyx_mm=SPACING)
    assert vol is not None and not isinstance(vol.data, np.ndarray)
    try:
        assert np.array_equal(vol.data.read(0, 6), ref.data) and np.array_equal(vol.data.read(2, 4), ref.data[2:4])
    finally:
        vol.data.close()


@pytest.mark.parametrize("layout", [PLANES, ROWS])
def test_the_job_is_the_same_with_and_without_the_sidecar(tmp_path: Path, layout: str) -> None:
    """``run_job`` on the bundled scan: every file but the report byte for byte the same, from a sidecar of samples
    or of rows; the report says where the slices came from."""
    from engine.job import InputSpec, JobSpec, resolve_runtime, run_job
    from engine.params import ReconParams

    upload = tmp_path / "upload"
    assert _decode(upload, HEADSQ_ZIP.read_bytes(), 1 << 20, layout).reason is None
    spec = JobSpec(
        recon=ReconParams.from_dict({"iso": {"iso": 1150.0}}), input=InputSpec(spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    )
    runtime = resolve_runtime("cpu")
    fast = run_job(upload, tmp_path / "fast", spec, runtime, predecoded=True)
    plain = run_job(upload, tmp_path / "plain", spec, runtime)
    assert fast.report["input"]["source"]["decoded_during_upload"] is True
    assert "decoded_during_upload" not in plain.report["input"]["source"]
    assert list(fast.paths) == list(plain.paths)
    for name, path in fast.paths.items():
        if name != "report.json":
            assert path.read_bytes() == plain.paths[name].read_bytes(), name


def test_it_reads_into_the_buffer_the_loader_is_given(tmp_path: Path) -> None:
    """A GPU worker's page-locked buffer (``allocate``): the planes land in the array it hands out."""
    upload = tmp_path / "upload"
    assert _decode(upload, _zip(_named(_pngs(7))[::-1]), 1 << 20).reason is None
    backing = np.zeros(1 << 16, np.uint8)

    def allocate(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:  # a view of a larger buffer, as staging's
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        return backing[:nbytes].view(dtype).reshape(shape)

    vol = load_predecoded(upload, spacing_zyx_mm=SPACING, allocate=allocate, threads=3)
    assert vol is not None and np.shares_memory(vol.data, backing)
    assert np.array_equal(vol.data, load_volume(upload, spacing_zyx_mm=SPACING).data)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("chunk", [7, 1 << 30], ids=["7B", "whole"])
def test_a_sidecar_of_rows_is_the_loaders_volume_on_the_host_and_on_a_device(
    tmp_path: Path, backend: Any, dtype: type, chunk: int
) -> None:
    """Only inflated by the decoder (every filter type, chosen per row), unfiltered by libpng on the host or by a
    device's kernel (Warp's CPU path, OpenCL), in slabs, and slab by slab under a host memory bound: the
    loader's samples, bit for bit."""
    upload = tmp_path / "upload"
    data = _zip(_named(_pngs(7, (13, 11), dtype))[::-1], method=zipfile.ZIP_DEFLATED)
    assert _decode(upload, data, chunk, ROWS).reason is None
    manifest = json.loads(sidecar_paths(upload)[1].read_text())
    assert manifest["layout"] == ROWS
    assert sidecar_paths(upload)[0].stat().st_size == 7 * 13 * (1 + 11 * np.dtype(dtype).itemsize)
    _same_as_loader(upload)  # libpng on the host
    rows = DeviceRows(backend, slab_bytes=3 * 13 * (1 + 11 * np.dtype(dtype).itemsize))  # slabs of 3 slices
    _same_as_loader(upload, rows=rows)
    assert rows.rows is None and rows.out is None and not rows.pending  # nothing held, nothing in flight
    vol = load_predecoded(upload, spacing_zyx_mm=SPACING, whole_bytes=100, rows=rows)
    assert vol is not None and not isinstance(vol.data, np.ndarray)
    try:
        ref = load_volume(upload, spacing_zyx_mm=SPACING).data
        assert np.array_equal(vol.data.read(0, 7), ref) and np.array_equal(vol.data.read(2, 5), ref[2:5])
    finally:
        vol.data.close()


def test_rows_it_could_not_unfilter_leave_no_sidecar_and_are_the_loaders_error(tmp_path: Path) -> None:
    """A row naming filter type 5 inflates fine: the decoder checks every row's type, keeps no sidecar, and the
    loader reports the slice; a sidecar changed on disk afterwards is not read (host or device)."""
    from engine.backend import get_backend

    imgs = gray_slices(np.random.default_rng(3), 4, (6, 5), np.uint8)
    pngs = [encode_png(img, np.zeros(6, int)) for img in imgs]
    raw = bytearray(zlib.decompress(_idat(pngs[2])))
    raw[2 * 6] = 5  # row 2's filter type
    pngs[2] = png_of_stream(imgs[2], zlib.compress(bytes(raw)))
    upload = tmp_path / "upload"
    dec = _decode(upload, _zip(_named(pngs)), 1 << 20, ROWS)
    assert dec.reason is not None and "inflate" in dec.reason and _nothing_left(upload)
    with pytest.raises(InputError):
        load_volume(upload, spacing_zyx_mm=SPACING)

    good = tmp_path / "good"
    assert (
        _decode(good, _zip(_named([encode_png(img, np.zeros(6, int)) for img in imgs])), 1 << 20, ROWS).reason is None
    )
    planes = sidecar_paths(good)[0]
    hurt = bytearray(planes.read_bytes())
    hurt[6 * 2 + 6] = 7  # plane 0, row 1's filter type
    planes.write_bytes(bytes(hurt))
    assert load_predecoded(good, spacing_zyx_mm=SPACING) is None
    assert load_predecoded(good, spacing_zyx_mm=SPACING, rows=DeviceRows(get_backend("cpu"))) is None


def test_rows_without_a_device_or_libpng_here_are_left_to_the_loader(tmp_path: Path, monkeypatch: Any) -> None:
    """A worker with neither a GPU nor imagecodecs cannot unfilter rows: the loader reads the upload (Pillow), also
    under a host memory bound, where the slabs would otherwise fail half way through a job."""
    import engine.io.codecs as codecs

    upload = tmp_path / "upload"
    assert _decode(upload, _zip(_named(_pngs(4))), 1 << 20, ROWS).reason is None
    monkeypatch.setattr(codecs, "_imagecodecs", lambda: None)
    assert load_predecoded(upload, spacing_zyx_mm=SPACING) is None
    assert load_predecoded(upload, spacing_zyx_mm=SPACING, whole_bytes=100) is None


def _idat(png: bytes) -> bytes:
    at = png.index(b"IDAT")
    (length,) = struct.unpack(">I", png[at - 4 : at])
    return png[at + 4 : at + 4 + length]
