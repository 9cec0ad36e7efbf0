"""PNG slices unfiltered on a device (``engine.io.png_rows``): the host inflates, the device's kernels reconstruct.

The volume must be libpng's, bit for bit, on every backend (Warp's CPU path and OpenCL here; CUDA with the ``gpu``
marker), for every filter type chosen per row at random, 8 and 16 bits, odd sizes, several slabs; slices the
device does not take (interlaced, another format, a damaged stream, a filter type PNG does not define) are decoded
on the host, with the same error where they are broken; nothing is left in flight or held after a load.
"""

from __future__ import annotations

import io
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile

from engine.errors import InputError
from engine.io import load_volume
from engine.io.png_rows import DeviceRows, device_rows
from tests.conftest import shared_file
from tests.engine.pngfactory import encode_adam7, encode_png, gray_slices, png_of_stream

RNG = np.random.default_rng(11)
SPACING = (1.0, 1.0, 1.0)


def _zip(path: Path, slices: list[bytes], ext: str = "png") -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for k, data in enumerate(slices):
            zf.writestr(f"s_{k:03d}.{ext}", data)
    return path


def _pngs(imgs: np.ndarray) -> list[bytes]:
    return [encode_png(img, RNG.integers(0, 5, size=img.shape[0]), idat_parts=1 + k % 3) for k, img in enumerate(imgs)]


def _load(path: Path, rows: DeviceRows | None, threads: int = 3) -> np.ndarray:
    data: np.ndarray = load_volume(path, spacing_zyx_mm=SPACING, threads=threads, rows=rows).data
    return data


class _Counting(DeviceRows):
    """Counts the slices the device took and the slabs it was sent."""

    def __init__(self, backend: Any, slab_bytes: int) -> None:
        super().__init__(backend, slab_bytes=slab_bytes)
        self.taken = self.sends = 0

    def take(self, k: int, data: bytes) -> bool:
        took = super().take(k, data)
        self.taken += took  # the GIL makes the increment whole enough for a count checked after the load
        return took

    def _send(self, lo: int, hi: int) -> None:
        self.sends += 1
        super()._send(lo, hi)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_every_filter_type_equals_libpng(backend: Any, tmp_path: Path, dtype: type) -> None:
    imgs = gray_slices(RNG, 11, (29, 37), dtype)
    path = _zip(tmp_path / "s.zip", _pngs(imgs))
    plane = 29 * (1 + 37 * np.dtype(dtype).itemsize)
    rows = _Counting(backend, slab_bytes=3 * plane)  # slabs of 3 slices: 4 sends, the last one short
    got = _load(path, rows)
    assert got.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(got, imgs)
    np.testing.assert_array_equal(got, _load(path, None))
    assert rows.taken == 10 and rows.sends == 4  # every slice but the first (decoded to learn the shape)
    assert rows.rows is None and rows.out is None and not rows.pending  # nothing held, nothing in flight


def test_slices_it_does_not_take_are_decoded_on_the_host(backend: Any, tmp_path: Path) -> None:
    imgs = gray_slices(RNG, 9, (16, 21), np.uint16)
    pngs = _pngs(imgs)
    pngs[2] = encode_adam7(imgs[2])  # interlaced
    pngs[4] = png_of_stream(imgs[4], zlib.compress(bytes(100)))  # rows of the wrong size
    files = {f"s_{k:03d}.png": p for k, p in enumerate(pngs)}
    files["s_007.png"] = _tiff(imgs[7])  # a TIFF among the PNGs (the loader goes by content)
    with zipfile.ZipFile(tmp_path / "s.zip", "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    rows = _Counting(backend, slab_bytes=1 << 20)
    with pytest.raises(InputError) as err:
        _load(tmp_path / "s.zip", rows)  # slice 4's stream is short: libpng's error, named
    assert "s_004.png" in str(err.value)
    assert rows.rows is None and not rows.pending
    pngs[4] = encode_png(imgs[4], np.zeros(16, int))
    files["s_004.png"] = pngs[4]
    with zipfile.ZipFile(tmp_path / "s.zip", "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    rows.taken = 0
    got = _load(tmp_path / "s.zip", rows)  # the same DeviceRows, reused for the next load
    np.testing.assert_array_equal(got, imgs)
    assert rows.taken == 6  # 1, 3, 4, 5, 6, 8: not 2 (interlaced) nor 7 (TIFF)


def test_a_filter_type_png_does_not_define_is_libpngs_error(backend: Any, tmp_path: Path) -> None:
    imgs = gray_slices(RNG, 4, (8, 10), np.uint8)
    pngs = _pngs(imgs)
    raw = b"".join(bytes([0 if r != 5 else 7]) + imgs[2][r].tobytes() for r in range(8))
    pngs[2] = png_of_stream(imgs[2], zlib.compress(raw))  # row 5: filter type 7
    path = _zip(tmp_path / "s.zip", pngs)
    rows = _Counting(backend, slab_bytes=1 << 20)
    with pytest.raises(InputError) as on_device:
        _load(path, rows)
    assert rows.taken == 3  # it inflated fine: the device found the filter type
    with pytest.raises(InputError) as on_host:
        _load(path, None)
    assert str(on_device.value) == str(on_host.value) and "s_002.png" in str(on_device.value)


def test_volumes_of_other_types_and_the_cpu_are_left_to_the_host(tmp_path: Path) -> None:
    assert device_rows("cpu") is None  # libpng on every thread is the faster way on the host
    from engine.backend.select import get_backend

    rows = DeviceRows(get_backend("cpu"))
    assert not rows.start(np.zeros((2, 3, 4), np.int16)) and not rows.start(np.zeros((2, 3, 4), np.float32))
    imgs = gray_slices(RNG, 3, (6, 7), np.uint8)
    path = _zip(tmp_path / "s.zip", [_tiff(img) for img in imgs], ext="tif")
    counting = _Counting(get_backend("cpu"), slab_bytes=1 << 20)
    np.testing.assert_array_equal(_load(path, counting), imgs)  # no PNG: nothing staged, nothing sent
    assert counting.taken == 0 and counting.sends == 0


def _tiff(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    tifffile.imwrite(buf, img)
    return buf.getvalue()


@pytest.mark.gpu
def test_cuda_with_the_page_locked_buffers(tmp_path: Path) -> None:
    from engine.staging import VolumeBuffer, pinned_rows

    imgs = gray_slices(RNG, 40, (200, 301), np.uint16)
    path = _zip(tmp_path / "s.zip", _pngs(imgs))
    rows = device_rows("cuda")
    assert rows is not None and rows.allocate is pinned_rows("cuda")
    rows.slab_bytes = 7 * 200 * 603  # several slabs, the copies overlapping the decode
    volume = load_volume(path, spacing_zyx_mm=SPACING, threads=4, rows=rows, allocate=VolumeBuffer(pinned=True))
    np.testing.assert_array_equal(volume.data, imgs)


def test_warm_up_loads_the_kernel(backend: Any) -> None:
    DeviceRows(backend).warm_up()  # one 1 x 1 slice through the kernel: it builds and runs on this backend


@pytest.mark.parametrize(
    "where",
    ["engine/data/headsq_png16.zip", "cranium_ct/cranium_ct_png16.zip", "head_phantom_dicom/head_phantom_png16.zip"],
)
def test_real_scans_equal_libpng(backend: Any, where: str) -> None:
    """Real CT exports (mostly Paeth rows): the bundled headsq always, the ../shared scans where present."""
    path = Path(__file__).parents[3] / where if where.startswith("engine/") else shared_file(*where.split("/"))
    rows = _Counting(backend, slab_bytes=24 << 20)
    got = _load(path, rows, threads=2)
    np.testing.assert_array_equal(got, _load(path, None, threads=2))
    assert rows.taken == got.shape[0] - 1 and rows.sends >= 1


def test_the_cli_unfilters_on_its_gpu_only() -> None:
    from engine.cli.args import _png_rows

    assert _png_rows(None) is None and _png_rows("cpu") is None
    assert _png_rows("cuda:99") is None  # not present: the reconstruction says so, not the loader
