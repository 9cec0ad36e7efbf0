"""Multi-page TIFF and BigTIFF volumes read page by page into one array (``engine.io.tiff``), and TIFF folders
decoded slice by slice into their planes: the same values as before, the array made once by ``allocate``, the file
opened where its bytes lie (a folder, an uncompressed tar, a stored zip member) and never read into memory whole."""

from __future__ import annotations

import tarfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile

from engine.errors import InputError
from engine.io import InputLimits, load_volume
from engine.io.archive import Member

SP = (0.5, 0.25, 0.25)


def _vol(shape: tuple[int, int, int] = (9, 20, 24), dtype: Any = np.uint16) -> np.ndarray:
    return np.random.default_rng(3).integers(0, 3000, size=shape).astype(dtype)


def _allocator() -> tuple[list[tuple[tuple[int, ...], np.dtype[Any]]], Any]:
    made: list[tuple[tuple[int, ...], np.dtype[Any]]] = []

    def allocate(shape: tuple[int, ...], dtype: np.dtype[Any]) -> np.ndarray:
        made.append((shape, np.dtype(dtype)))
        return np.empty(shape, dtype)

    return made, allocate


@pytest.fixture
def no_whole_reads(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Records (and so forbids, where the test asserts it empty) any member read into memory whole."""
    seen: list[str] = []
    real = Member.read

    def read(self: Member) -> bytes:
        seen.append(self.name)
        return real(self)

    monkeypatch.setattr(Member, "read", read)
    return seen


@pytest.mark.parametrize(
    ("kwargs", "dtype"),
    [
        ({"bigtiff": True}, np.uint16),
        ({}, np.uint8),
        ({"bigtiff": True, "compression": "zlib"}, np.int16),
        ({"compression": "lzw", "tile": (16, 16)}, np.float32),
        ({"imagej": True}, np.uint16),
        ({"bigtiff": True, "metadata": None}, np.uint16),  # no shape metadata: 9 plain pages, one series
    ],
)
@pytest.mark.parametrize("threads", [1, 3])
def test_multipage_and_bigtiff_read_page_by_page_into_the_allocated_array(
    tmp_path: Path, kwargs: dict[str, Any], dtype: Any, threads: int, no_whole_reads: list[str]
) -> None:
    data = _vol(dtype=dtype)
    tifffile.imwrite(tmp_path / "vol.tif", data, **kwargs)
    made, allocate = _allocator()
    seen: list[float] = []
    vol = load_volume(
        tmp_path / "vol.tif", spacing_zyx_mm=SP, allocate=allocate, threads=threads, on_progress=seen.append
    )
    np.testing.assert_array_equal(vol.data, data)
    assert vol.data.dtype == dtype and made == [(data.shape, np.dtype(dtype))]
    assert vol.source["format"] == "tiff" and seen[-1] == 1.0
    assert no_whole_reads == []  # opened in place: never read into bytes first


def test_bigtiff_in_an_uncompressed_tar_and_a_stored_zip_is_read_in_place(
    tmp_path: Path, no_whole_reads: list[str]
) -> None:
    data = _vol()
    tifffile.imwrite(tmp_path / "vol.tif", data, bigtiff=True)
    with tarfile.open(tmp_path / "vol.tar", "w") as tf:
        tf.add(tmp_path / "vol.tif", "scan/vol.tif")
    with zipfile.ZipFile(tmp_path / "stored.zip", "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("x" * 7 + "/vol.tif", (tmp_path / "vol.tif").read_bytes())
    for archive in ("vol.tar", "stored.zip"):
        np.testing.assert_array_equal(load_volume(tmp_path / archive, spacing_zyx_mm=SP).data, data)
    assert no_whole_reads == []
    with zipfile.ZipFile(tmp_path / "deflated.zip", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.write(tmp_path / "vol.tif", "vol.tif")
    np.testing.assert_array_equal(load_volume(tmp_path / "deflated.zip", spacing_zyx_mm=SP).data, data)
    assert no_whole_reads == ["vol.tif"]  # a deflated member cannot be read in place


def test_imagej_spacing_tags_are_kept(tmp_path: Path) -> None:
    data = _vol()
    tifffile.imwrite(tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.025, 1 / 0.02),
                     metadata={"spacing": 0.05, "unit": "mm"})  # fmt: skip
    vol = load_volume(tmp_path / "ij.tif")
    np.testing.assert_allclose(vol.spacing_zyx_mm, (0.05, 0.02, 0.025))
    assert vol.source["spacing_from"] == "tiff"


def test_colour_and_hyperstacks_still_decode_whole(tmp_path: Path) -> None:
    rgb = np.random.default_rng(1).integers(0, 255, size=(3, 8, 10, 3)).astype(np.uint8)
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb")
    with pytest.warns(UserWarning, match="luminance"):
        vol = load_volume(tmp_path / "rgb.tif", spacing_zyx_mm=SP)
    assert vol.data.shape == (3, 8, 10) and vol.data.dtype == np.uint8
    wide = _vol().astype(np.int32)  # not an engine type: narrowed after a whole read, as before
    tifffile.imwrite(tmp_path / "i32.tif", wide)
    vol = load_volume(tmp_path / "i32.tif", spacing_zyx_mm=SP)
    assert vol.data.dtype == np.uint16
    np.testing.assert_array_equal(vol.data, wide)


def test_voxel_limit_is_checked_before_allocating(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "vol.tif", _vol(), bigtiff=True)
    made, allocate = _allocator()
    with pytest.raises(InputError, match="4,320 voxels"):
        load_volume(tmp_path / "vol.tif", spacing_zyx_mm=SP, limits=InputLimits(max_voxels=1000), allocate=allocate)
    assert made == []


def test_truncated_bigtiff_is_one_clear_error(tmp_path: Path) -> None:
    tifffile.imwrite(tmp_path / "vol.tif", _vol(), bigtiff=True, compression="zlib")
    raw = (tmp_path / "vol.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(raw[: len(raw) * 2 // 3])
    with pytest.raises(InputError, match=r"cut\.tif") as info:
        load_volume(tmp_path / "cut.tif", spacing_zyx_mm=SP)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("threads", [1, 2])
def test_tiff_folder_slices_decode_into_their_planes(tmp_path: Path, threads: int) -> None:
    """A folder of one TIFF per slice (natural order, thousands in real scans): each slice decoded into its plane
    of the one allocated array (no slice-sized temporaries to copy), compressed or not."""
    data = _vol((12, 20, 24))
    folder = tmp_path / "slices"
    folder.mkdir()
    for k, plane in enumerate(data):
        tifffile.imwrite(folder / f"slice_{k}.tif", plane, compression="zlib" if k % 2 else None)
    made, allocate = _allocator()
    vol = load_volume(folder, spacing_zyx_mm=SP, allocate=allocate, threads=threads)
    np.testing.assert_array_equal(vol.data, data)
    assert made == [(data.shape, np.dtype(np.uint16))] and vol.source["files"] == 12


def test_tiff_slice_decoded_into_its_plane() -> None:
    from engine.io.stack import _decode_tiff

    data = _vol((1, 20, 24))[0]
    import io

    buf = io.BytesIO()
    tifffile.imwrite(buf, data, compression="zlib")
    plane = np.zeros_like(data)
    arr, _ = _decode_tiff(buf.getvalue(), plane)
    assert arr is plane
    np.testing.assert_array_equal(plane, data)
    other = np.zeros((20, 24), np.uint8)  # another type: a new array, the plane untouched
    arr, _ = _decode_tiff(buf.getvalue(), other)
    assert arr is not other and not other.any()
