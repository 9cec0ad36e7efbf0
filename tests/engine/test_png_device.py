"""PNG stacks unfiltered on a device (``engine.io.pngdevice``) equal the host decoder (libpng) bit for bit.

The slices are written here with every PNG filter type (None, Sub, Up, Average, Paeth) chosen per row at random,
8- and 16-bit, odd sizes, one or several IDAT chunks, so each predictor and the 16-bit byte order is exercised. The
kernels run on Warp's CPU device here (the path the worker takes on a CUDA device; CI has none); anything the
device path does not take (colour, interlaced, damaged, another size) must come out as the host decoder makes it,
or fail with its error.
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from engine.errors import InputError
from engine.io import codecs, load_volume
from engine.io.pngdevice import plain_png_layout, unfilter_on_device, wanted

RNG = np.random.default_rng(7)
ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def encode_png(img: np.ndarray, filters: np.ndarray, idat_parts: int = 1, interlace: int = 0) -> bytes:
    """A grayscale PNG of ``img`` (uint8/uint16) with row ``r`` filtered by type ``filters[r]`` (0-4)."""
    h, w = img.shape
    bpp = img.dtype.itemsize
    raw = img.astype(img.dtype.newbyteorder(">")).view(np.uint8).reshape(h, w * bpp).astype(np.int64)
    rows = []
    for r in range(h):
        x = raw[r]
        a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
        b = raw[r - 1] if r else np.zeros_like(x)
        c = np.concatenate([np.zeros(bpp, np.int64), b[:-bpp]])
        pred = [np.zeros_like(x), a, b, (a + b) // 2, _paeth(a, b, c)][int(filters[r])]
        rows.append(bytes([int(filters[r])]) + ((x - pred) % 256).astype(np.uint8).tobytes())
    stream = zlib.compress(b"".join(rows), 6)
    cut = np.linspace(0, len(stream), idat_parts + 1).astype(int)
    ihdr = struct.pack(">IIBBBBB", w, h, 8 * bpp, 0, 0, 0, interlace)
    idats = b"".join(_chunk(b"IDAT", stream[cut[i] : cut[i + 1]]) for i in range(idat_parts))
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + idats + _chunk(b"IEND", b"")


def encode_adam7(img: np.ndarray) -> bytes:
    """An interlaced (Adam7) grayscale PNG of ``img``, every row unfiltered."""
    h, w = img.shape
    big = img.astype(img.dtype.newbyteorder(">"))
    rows = []
    for x0, y0, dx, dy in ADAM7:
        sub = big[y0::dy, x0::dx]
        if sub.size:
            rows += [b"\x00" + r.tobytes() for r in sub]
    ihdr = struct.pack(">IIBBBBB", w, h, 8 * img.dtype.itemsize, 0, 0, 0, 1)
    body = _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b"".join(rows))) + _chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + body


def _slices(n: int, shape: tuple[int, int], dtype: type) -> np.ndarray:
    top = np.iinfo(dtype).max
    smooth = np.cumsum(RNG.integers(-3, 4, size=(n, *shape)), axis=2) % (top + 1)
    return np.where(RNG.random((n, *shape)) < 0.1, RNG.integers(0, top + 1, size=(n, *shape)), smooth).astype(dtype)


def _zip(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return path


def _load(path: Path, device: str | None, monkeypatch: pytest.MonkeyPatch, threads: int = 2) -> np.ndarray:
    monkeypatch.setattr(codecs, "UNFILTER_DEVICE", device)
    return load_volume(path, spacing_zyx_mm=(1.0, 1.0, 1.0), threads=threads).data


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_every_filter_type_equals_libpng(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, dtype: type
) -> None:
    vol = _slices(6, (23, 37), dtype)
    files = {}
    for z, img in enumerate(vol):
        filters = RNG.integers(0, 5, size=img.shape[0])
        files[f"s/slice_{z:03d}.png"] = encode_png(img, filters, idat_parts=1 + z % 3)
    path = _zip(tmp_path / "stack.zip", files)
    host = _load(path, None, monkeypatch)
    with caplog.at_level("WARNING", logger="engine.io.stack"):
        device = _load(path, "cpu", monkeypatch)
    assert not caplog.records, caplog.text  # the device path ran (a failure there falls back to the host, logged)
    np.testing.assert_array_equal(host, vol)
    np.testing.assert_array_equal(device, vol)
    assert device.dtype == np.dtype(dtype)


def test_slices_it_does_not_take_are_decoded_on_the_host(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Interlaced and colour slices go to the host decoder; the stack is the same as the host path's."""
    vol = _slices(5, (16, 20), np.uint16)
    files = {f"s/slice_{z:03d}.png": encode_png(img, RNG.integers(0, 5, size=16)) for z, img in enumerate(vol)}
    files["s/slice_002.png"] = encode_adam7(vol[2])  # interlaced: the device path leaves it
    assert plain_png_layout(files["s/slice_002.png"]) is None
    path = _zip(tmp_path / "stack.zip", files)
    np.testing.assert_array_equal(_load(path, "cpu", monkeypatch), vol)
    np.testing.assert_array_equal(_load(path, "cpu", monkeypatch), _load(path, None, monkeypatch))


def test_a_damaged_slice_fails_as_on_the_host(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    vol = _slices(4, (12, 14), np.uint8)
    files = {f"s/slice_{z:03d}.png": encode_png(img, RNG.integers(0, 5, size=12)) for z, img in enumerate(vol)}
    data = bytearray(files["s/slice_003.png"])
    data[45:60] = bytes(15)  # inside the zlib stream
    files["s/slice_003.png"] = bytes(data)
    path = _zip(tmp_path / "stack.zip", files)
    with pytest.raises(InputError, match=r"slice_003\.png") as host:
        _load(path, None, monkeypatch)
    with pytest.raises(InputError, match=r"slice_003\.png") as device:
        _load(path, "cpu", monkeypatch)
    assert str(device.value) == str(host.value)


def test_an_unknown_filter_type_is_left_to_the_host(monkeypatch: pytest.MonkeyPatch) -> None:
    """A row whose filter byte is above 4 is flagged by the kernel and left for the host decoder."""
    vol = _slices(3, (8, 9), np.uint16)
    pngs = [encode_png(img, RNG.integers(0, 5, size=8)) for img in vol]
    layout = plain_png_layout(pngs[1])
    assert layout is not None
    rows = bytearray(zlib.decompress(layout[3]))
    rows[(1 + 9 * 2) * 4] = 7  # row 4's filter type
    stream = zlib.compress(bytes(rows))
    ihdr = struct.pack(">IIBBBBB", 9, 8, 16, 0, 0, 0, 0)
    pngs[1] = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")
    out = np.zeros_like(vol)
    left = unfilter_on_device(lambda k: pngs[k], out, "cpu", threads=2)
    assert left == [1]
    np.testing.assert_array_equal(out[[0, 2]], vol[[0, 2]])


def test_chunks_of_slices_equal_one_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    vol = _slices(7, (10, 11), np.uint16)
    pngs = [encode_png(img, RNG.integers(0, 5, size=10)) for img in vol]
    per = 10 * (1 + 11 * 2)
    for chunk in (per, 3 * per, 100 * per):  # one slice per pass, three, all
        out = np.zeros_like(vol)
        assert unfilter_on_device(lambda k: pngs[k], out, "cpu", threads=3, chunk_bytes=chunk) == []
        np.testing.assert_array_equal(out, vol)


def test_wanted_on_cuda_within_a_budget() -> None:
    assert wanted("cuda:0", None) and wanted("cuda", 8 << 30)
    assert not wanted("cuda:0", 256 << 20) and not wanted("cpu", None) and not wanted("opencl:0", None)
