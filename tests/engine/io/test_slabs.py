"""A scan read slab by slab (``engine.io.slabs``, issue 46): every kind of source gives the loader's planes, voxel
size and origin slab by slab; a scan that fits the bound's share is loaded whole (None); what cannot be read slab by
slab is refused in one line with a way out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from engine.errors import InputError
from engine.io import load_volume
from engine.io.slabs import SlabSource, open_slabs
from tests.engine.omezarr_factory import write_ome_zarr

SPACING = (0.5, 0.4, 0.3)


@pytest.fixture(scope="module")
def vol() -> np.ndarray:
    return np.random.default_rng(5).integers(0, 4000, size=(21, 18, 22)).astype(np.uint16)


def _written(kind: str, vol: np.ndarray, work: Path) -> Path:
    import tifffile

    if kind == "npy":
        np.save(work / "v.npy", vol)
        return work / "v.npy"
    if kind == "npy-big-endian":
        np.save(work / "v.npy", vol.astype(">u2"))
        return work / "v.npy"
    if kind == "tiff-folder":
        (work / "sl").mkdir()
        for k, plane in enumerate(vol):
            tifffile.imwrite(work / "sl" / f"s{k}.tif", plane)
        return work / "sl"
    if kind == "png-folder":
        import imageio.v3 as iio

        (work / "png").mkdir()
        for k, plane in enumerate(vol):
            iio.imwrite(work / "png" / f"s{k}.png", plane)
        return work / "png"
    if kind == "bigtiff":
        tifffile.imwrite(work / "v.tif", vol, bigtiff=True)
        return work / "v.tif"
    return write_ome_zarr(work / "v.ome.zarr", vol, scale=[s * 1000 for s in SPACING], chunks=(4, 9, 11))


@pytest.mark.parametrize("kind", ["npy", "npy-big-endian", "tiff-folder", "png-folder", "bigtiff", "ome-zarr"])
def test_slabs_are_the_loaded_planes(vol: np.ndarray, tmp_path: Path, kind: str) -> None:
    path = _written(kind, vol, tmp_path)
    spacing = None if kind == "ome-zarr" else SPACING
    loaded = load_volume(path, spacing_zyx_mm=spacing)
    assert open_slabs(path, loaded.data.nbytes, spacing_zyx_mm=spacing) is None  # fits: loaded whole
    sliced = open_slabs(path, loaded.data.nbytes - 1, spacing_zyx_mm=spacing, threads=2)
    assert sliced is not None
    src = sliced.data
    assert isinstance(src, SlabSource)
    assert (src.shape, src.dtype, src.nbytes) == (loaded.data.shape, loaded.data.dtype, loaded.data.nbytes)
    assert sliced.spacing_zyx_mm == pytest.approx(loaded.spacing_zyx_mm)
    assert sliced.origin_mm == loaded.origin_mm and sliced.units == loaded.units
    for z0, z1 in ((0, 21), (0, 1), (3, 4), (3, 9), (7, 8), (8, 17), (20, 21), (19, 25)):  # across zarr's chunk rows
        np.testing.assert_array_equal(src.read(z0, z1), loaded.data[z0:z1], err_msg=f"{z0}:{z1}")
    for step in (1, 2, 3, 5):
        np.testing.assert_array_equal(src.strided(step), loaded.data[::step, ::step, ::step])
    assert (src.min(), src.max()) == (loaded.data.min(), loaded.data.max())
    src.close()


def test_what_is_not_read_slab_by_slab_is_refused_when_it_does_not_fit(tmp_path: Path) -> None:
    from tests.engine.dicom_factory import series

    files = series(lambda p: p[..., 0] * 0 + 100, positions_mm=[0.0, 1.0, 2.0, 3.0])
    (tmp_path / "dcm").mkdir()
    for name, data in files.items():
        (tmp_path / "dcm" / name).write_bytes(data)
    assert open_slabs(tmp_path / "dcm", 1 << 30) is None
    with pytest.raises(InputError, match=r"DICOM series .* not read slab by slab: give a larger --max-host-bytes"):
        open_slabs(tmp_path / "dcm", 100)
    np.save(tmp_path / "i32.npy", np.zeros((4, 8, 8), np.int32))
    with pytest.raises(InputError, match=r"its samples are int32.*--max-host-bytes of at least"):
        open_slabs(tmp_path / "i32.npy", 100, spacing_zyx_mm=SPACING)
    with pytest.raises(InputError) as err:
        write_ome_zarr(tmp_path / "i32.ome.zarr", np.zeros((4, 8, 8), np.int32), chunks=(2, 8, 8))
        open_slabs(tmp_path / "i32.ome.zarr", 100)
    assert "\n" not in str(err.value) and "--max-host-bytes" in str(err.value)


@pytest.mark.parametrize("kind", ["npy", "png-folder", "ome-zarr"])
def test_a_box_of_the_scan_is_the_loaded_box(vol: np.ndarray, tmp_path: Path, kind: str) -> None:
    """A region of interest out of core (``SlabSource[box]``, a box of a box too) reads the loaded scan's voxels."""
    path = _written(kind, vol, tmp_path)
    spacing = None if kind == "ome-zarr" else SPACING
    loaded = load_volume(path, spacing_zyx_mm=spacing).data
    src = open_slabs(path, loaded.nbytes - 1, spacing_zyx_mm=spacing).data
    box = src[2:19, 3:16, 5:20]
    assert box.shape == (17, 13, 15)
    for z0, z1 in ((0, 17), (0, 1), (1, 2), (2, 11), (16, 17)):  # a plane, rows of chunks, across them
        np.testing.assert_array_equal(box.read(z0, z1), loaded[2 + z0 : 2 + z1, 3:16, 5:20], err_msg=f"{z0}:{z1}")
    inner = box[1:9, 2:12, 0:7]
    np.testing.assert_array_equal(inner.read(0, 8), loaded[3:11, 5:15, 5:12])
    np.testing.assert_array_equal(inner.read(4, 5), loaded[7:8, 5:15, 5:12])
    src.close()


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_a_box_of_an_ome_zarr_decodes_only_the_chunks_inside_it(vol: np.ndarray, tmp_path: Path, version: str) -> None:
    """Out of core, a region of interest of an OME-Zarr reads the chunks it holds and no other: with every other
    chunk made unreadable the box still reads (the whole scan does not), chunk by chunk in zarr's own layout."""
    path = write_ome_zarr(tmp_path / "v.ome.zarr", vol, version=version, scale=[s * 1000 for s in SPACING],
                          chunks=(4, 9, 11))  # fmt: skip
    level = path / "0"
    spoiled = 0
    for f in level.rglob("*"):
        if not f.is_file() or f.name in ("zarr.json", ".zarray", ".zattrs", ".zgroup"):
            continue
        rel = f.relative_to(level).as_posix()
        index = [int(p) for p in (rel.split("/")[1:] if rel.startswith("c/") else rel.replace("/", ".").split("."))]
        if index[1] != 0 or index[2] != 0:  # outside rows 0-8 and columns 0-10
            f.write_bytes(b"not a chunk")
            spoiled += 1
    assert spoiled >= 6 * 3
    src = open_slabs(path, vol.nbytes - 1).data
    box = src[1:20, 2:9, 0:11]
    np.testing.assert_array_equal(box.read(0, 19), vol[1:20, 2:9, 0:11])
    np.testing.assert_array_equal(box.read(5, 6), vol[6:7, 2:9, 0:11])
    with pytest.raises(InputError, match="cannot be read"):
        src.read(0, 4)
    src.close()
