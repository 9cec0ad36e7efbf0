"""engine.io.load_volume on image stacks, volume files and archives (incl. the safety limits)."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile

from engine.errors import InputError
from engine.io import InputLimits, StackWarning, load_volume
from engine.io.stack import load_slice_zip, natural_key
from tests.conftest import shared_file

SP = (2.0, 0.5, 0.25)


def _vol(n: int = 5, dtype: type = np.uint16, shape: tuple[int, int] = (12, 10)) -> np.ndarray:
    rng = np.random.default_rng(n)
    hi = 250 if dtype == np.uint8 else 4000
    return rng.integers(0, hi, size=(n, *shape)).astype(dtype)


def _encode(img: np.ndarray, ext: str) -> bytes:
    if ext in (".tif", ".tiff"):
        buf = io.BytesIO()
        tifffile.imwrite(buf, img, photometric="minisblack" if img.ndim == 2 else "rgb")
        return buf.getvalue()
    return iio.imwrite("<bytes>", img, extension=ext)


def _slices(vol: np.ndarray, ext: str, stem: str = "img") -> dict[str, bytes]:
    return {f"{stem}{k}{ext}": _encode(s, ext) for k, s in enumerate(vol)}


def _write(path: Path, files: dict[str, bytes], kind: str) -> Path:
    if kind == "zip":
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            for n, b in reversed(list(files.items())):  # stored out of order on purpose
                zf.writestr(n, b)
    elif kind in ("tar", "tar.gz"):
        with tarfile.open(path, "w:gz" if kind == "tar.gz" else "w") as tf:
            for n, b in files.items():
                info = tarfile.TarInfo(n)
                info.size = len(b)
                tf.addfile(info, io.BytesIO(b))
    else:
        path.mkdir()
        for n, b in files.items():
            (path / n).parent.mkdir(parents=True, exist_ok=True)
            (path / n).write_bytes(b)
    return path


@pytest.mark.parametrize("ext", [".png", ".tif", ".bmp"])
@pytest.mark.parametrize("kind", ["zip", "tar", "tar.gz", "folder"])
def test_lossless_stacks_in_every_container(tmp_path: Path, ext: str, kind: str) -> None:
    vol = _vol(12, np.uint8 if ext == ".bmp" else np.uint16)  # 12 slices: img10, img11 must follow img9
    path = _write(tmp_path / f"s.{kind}", _slices(vol, ext), kind)
    out = load_volume(path, spacing_zyx_mm=SP)
    assert out.data.dtype == vol.dtype and np.array_equal(out.data, vol)
    assert out.spacing_zyx_mm == SP and out.units == "raw"
    assert out.source["files"] == 12 and out.source["container"] == kind


def test_jpeg_stack(tmp_path: Path) -> None:
    vol = np.repeat(np.linspace(0, 250, 16, dtype=np.uint8)[None, None], 4 * 16, 0).reshape(4, 16, 16)
    out = load_volume(_write(tmp_path / "j.zip", _slices(vol, ".jpg"), "zip"), spacing_zyx_mm=SP)
    assert out.data.shape == (4, 16, 16) and out.data.dtype == np.uint8
    assert np.abs(out.data.astype(int) - vol).max() < 8  # lossy


def test_natural_order_beats_text_order(tmp_path: Path) -> None:
    vol = np.arange(11, dtype=np.uint16)[:, None, None] * np.ones((1, 4, 4), np.uint16)
    files = {f"scan/img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)}
    out = load_volume(_write(tmp_path / "n.zip", files, "zip"), spacing_zyx_mm=SP)
    assert list(out.data[:, 0, 0]) == list(range(11))
    assert sorted(["img10", "img2", "img1"], key=natural_key) == ["img1", "img2", "img10"]
    assert np.array_equal(load_slice_zip(tmp_path / "n.zip"), vol)  # the old entry point still works


def test_mixed_shape_or_dtype_names_the_odd_file(tmp_path: Path) -> None:
    files = _slices(_vol(3), ".png")
    files["img3.png"] = _encode(np.zeros((5, 5), np.uint16), ".png")
    with pytest.raises(InputError, match=r"img3\.png"):
        load_volume(_write(tmp_path / "m.zip", files, "zip"), spacing_zyx_mm=SP)
    files["img3.png"] = _encode(np.zeros((12, 10), np.uint8), ".png")
    with pytest.raises(InputError, match=r"uint8 in img3\.png"):
        load_volume(_write(tmp_path / "d.zip", files, "zip"), spacing_zyx_mm=SP)


def test_rgb_becomes_luminance_with_one_warning(tmp_path: Path) -> None:
    rgb = np.zeros((3, 6, 6, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 100, 200, 50
    with pytest.warns(StackWarning, match="3 image.*luminance") as rec:
        out = load_volume(_write(tmp_path / "c.zip", _slices(rgb, ".png"), "zip"), spacing_zyx_mm=SP)
    assert len([w for w in rec if issubclass(w.category, StackWarning)]) == 1
    assert out.data.shape == (3, 6, 6) and out.data.dtype == np.uint8
    assert int(out.data[0, 0, 0]) == round(0.299 * 100 + 0.587 * 200 + 0.114 * 50)


def test_missing_spacing_says_how_to_give_it(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"z, y, x order \(CLI --voxel-size z=\.\.,y=\.\.,x=\.\.; job params"):
        load_volume(_write(tmp_path / "s.zip", _slices(_vol(3), ".png"), "zip"))
    for absurd in ((1, 0, 1), (1e300, 1, 1), (1, 1e-300, 1), (1, 1, float("nan"))):
        with pytest.raises(InputError, match=r"Expected a voxel size between 0.0001 and 100 mm"):
            load_volume(tmp_path / "s.zip", spacing_zyx_mm=absurd)


def test_tiff_resolution_tags_give_spacing(tmp_path: Path) -> None:
    vol = _vol(4)
    path = tmp_path / "ij.tif"  # ImageJ: pixels per micron + z spacing
    ij = {"spacing": 4.1, "unit": "micron"}
    tifffile.imwrite(path, vol, photometric="minisblack", imagej=True, resolution=(1 / 4.1, 1 / 4.1), metadata=ij)
    out = load_volume(path)
    assert np.array_equal(out.data, vol) and out.source["spacing_from"] == "tiff"
    assert out.spacing_zyx_mm == pytest.approx((0.0041, 0.0041, 0.0041))
    cm = tmp_path / "cm"  # separate slices with pixels per cm: x/y known, z must come from the call
    files = {}
    for k, s in enumerate(vol):
        buf = io.BytesIO()
        tifffile.imwrite(buf, s, resolution=(40.0, 20.0), resolutionunit="CENTIMETER")
        files[f"s{k}.tif"] = buf.getvalue()
    with pytest.raises(InputError, match=r"pixel size \(y 0\.5 mm, x 0\.25 mm\).*--voxel-size z=\.\.,y=0\.5,x=0\.25"):
        load_volume(_write(cm, files, "folder"))
    dpi = tmp_path / "dpi.tif"  # 72 dpi is a display default, never a voxel size
    tifffile.imwrite(dpi, vol, photometric="minisblack", resolution=(72.0, 72.0), resolutionunit="INCH")
    with pytest.raises(InputError, match=r"72 dpi.*not a voxel size"):
        load_volume(dpi)
    huge = tmp_path / "huge.tif"  # ImageJ tags of 2 m voxels: refused like a caller's absurd spacing
    tifffile.imwrite(huge, vol, imagej=True, resolution=(1 / 2e6, 1 / 2e6), metadata={"spacing": 2e6, "unit": "micron"})
    with pytest.raises(InputError, match=r"TIFF tags give an implausible voxel size.*between 0.0001 and 100 mm"):
        load_volume(huge)


def test_planar_rgb_tiff(tmp_path: Path) -> None:
    rgb = np.zeros((3, 6, 5), np.uint8)  # separate colour planes
    rgb[0], rgb[1], rgb[2] = 100, 200, 50
    tifffile.imwrite(tmp_path / "p.tif", rgb, photometric="rgb", planarconfig="separate")
    files = {f"p{k}.tif": (tmp_path / "p.tif").read_bytes() for k in range(3)}
    with pytest.warns(StackWarning, match="luminance"):
        out = load_volume(_write(tmp_path / "p.zip", files, "zip"), spacing_zyx_mm=SP)
    assert out.data.shape == (3, 6, 5) and int(out.data[0, 0, 0]) == 153  # 0.299*100 + 0.587*200 + 0.114*50


def test_multipage_tiff_and_npy(tmp_path: Path) -> None:
    vol = _vol(6)
    tifffile.imwrite(tmp_path / "v.tif", vol, photometric="minisblack")
    assert np.array_equal(load_volume(tmp_path / "v.tif", spacing_zyx_mm=SP).data, vol)
    np.save(tmp_path / "v.npy", vol.astype(np.int32) - 1000)
    out = load_volume(tmp_path / "v.npy", spacing_zyx_mm=SP)
    assert out.data.dtype == np.int16 and np.array_equal(out.data, vol.astype(np.int16) - 1000)
    np.save(tmp_path / "f.npy", vol.astype(np.float64) / 3)
    assert load_volume(tmp_path / "f.npy", spacing_zyx_mm=SP).data.dtype == np.float32
    with zipfile.ZipFile(tmp_path / "npy.zip", "w") as zf:
        zf.write(tmp_path / "v.npy", "volume.npy")
    assert load_volume(tmp_path / "npy.zip", spacing_zyx_mm=SP).data.shape == vol.shape
    with pytest.raises(InputError, match="multi-page TIFF on its own"):
        files = {"a.tif": (tmp_path / "v.tif").read_bytes(), "b.tif": _encode(vol[0], ".tif")}
        load_volume(_write(tmp_path / "mp.zip", files, "zip"), spacing_zyx_mm=SP)


# ---- safety -----------------------------------------------------------------------------------------------------


def test_zip_bomb_is_refused(tmp_path: Path) -> None:
    files = _slices(_vol(2), ".png")
    files["padding.raw"] = bytes(4 << 20)  # 4 MiB of zeros deflate ~1000x
    path = _write(tmp_path / "bomb.zip", files, "zip")
    with pytest.raises(InputError, match="zip bomb"):
        load_volume(path, spacing_zyx_mm=SP)
    with pytest.raises(InputError, match="zip bomb"):
        load_volume(_write(tmp_path / "bomb.tar.gz", files, "tar.gz"), spacing_zyx_mm=SP)
    small = InputLimits(max_total_bytes=1 << 20)
    with pytest.raises(InputError, match="too large"):
        load_volume(_write(tmp_path / "big.tar", files, "tar"), spacing_zyx_mm=SP, limits=small)


def test_lying_zip_header_is_caught(tmp_path: Path) -> None:
    """A member whose central directory understates its size: the stream check still stops it."""
    path = _write(tmp_path / "lie.zip", {"a.png": _encode(_vol(1)[0], ".png"), "z.raw": bytes(3 << 20)}, "zip")
    raw = path.read_bytes()
    assert raw.count((3 << 20).to_bytes(4, "little")) == 2  # local header + central directory
    path.write_bytes(raw.replace((3 << 20).to_bytes(4, "little"), (1000).to_bytes(4, "little")))
    with pytest.raises(InputError, match="not a readable zip archive"):
        load_volume(path, spacing_zyx_mm=SP)


def test_path_traversal_names_are_refused_and_never_written(tmp_path: Path) -> None:
    work = tmp_path / "w"
    work.mkdir()
    for name in ("../evil.png", "/abs/evil.png", "a/../../evil.png"):
        path = _write(work / "t.zip", {"ok.png": _encode(_vol(1)[0], ".png"), name: b"x"}, "zip")
        with pytest.raises(InputError, match="points outside the archive"):
            load_volume(path, spacing_zyx_mm=SP)
        path.unlink()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["w"]


def test_tar_symlinks_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "l.tar"
    with tarfile.open(path, "w") as tf:
        for n, b in _slices(_vol(3), ".png").items():
            info = tarfile.TarInfo(n)
            info.size = len(b)
            tf.addfile(info, io.BytesIO(b))
        link = tarfile.TarInfo("img9.png")
        link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tf.addfile(link)
    assert load_volume(path, spacing_zyx_mm=SP).data.shape[0] == 3


def test_member_count_and_voxel_limits(tmp_path: Path) -> None:
    path = _write(tmp_path / "many.zip", _slices(_vol(10), ".png"), "zip")
    with pytest.raises(InputError, match="more than the limit of 5"):
        load_volume(path, spacing_zyx_mm=SP, limits=InputLimits(max_members=5))
    with pytest.raises(InputError, match="more than the limit of 100"):
        load_volume(path, spacing_zyx_mm=SP, limits=InputLimits(max_voxels=100))
    np.save(tmp_path / "v.npy", np.zeros((4, 8, 8), np.uint8))
    with pytest.raises(InputError, match="256 voxels"):
        load_volume(tmp_path / "v.npy", spacing_zyx_mm=SP, limits=InputLimits(max_voxels=100))


def test_bad_inputs_fail_clearly(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        load_volume(tmp_path / "nope.zip")
    good = _write(tmp_path / "g.zip", _slices(_vol(3), ".png"), "zip").read_bytes()
    (tmp_path / "trunc.zip").write_bytes(good[: len(good) // 2])
    with pytest.raises(InputError, match="not a readable zip"):
        load_volume(tmp_path / "trunc.zip", spacing_zyx_mm=SP)
    (tmp_path / "junk.bin").write_bytes(b"hello, not a scan\n" * 10)
    with pytest.raises(InputError, match="found none"):
        load_volume(tmp_path / "junk.bin", spacing_zyx_mm=SP)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage")
    with pytest.raises(InputError, match=r"cannot decode bad\.png"):
        load_volume(tmp_path / "bad.png", spacing_zyx_mm=SP)


# ---- real PNG stacks in ../shared/data ---------------------------------------------------------------------------

REAL = ["cranium_ct", "pelvis_ct", "headsq_ct", "shrew_trabecular_microct", "head_phantom_dicom"]


@pytest.mark.parametrize("folder", REAL)
def test_real_png_stacks(folder: str) -> None:
    meta = json.loads(shared_file(folder, "meta.json").read_text())
    zip_path = shared_file(folder, meta["files"]["slices_png16"])
    spacing = tuple(meta["spacing_mm_xyz"][::-1])
    with pytest.raises(InputError, match="spacing_zyx_mm"):
        load_volume(zip_path)
    vol = load_volume(zip_path, spacing_zyx_mm=spacing)
    assert vol.data.shape == tuple(meta["shape_zyx"]) and vol.data.dtype == np.uint16
    assert (int(vol.data.min()), int(vol.data.max())) == tuple(meta["stored_range"])
    for level, count in meta["stored_count_above"].items():
        assert int((vol.data > float(level)).sum()) == count


def test_bundled_headsq_matches_its_readme() -> None:
    """The headsq copy in engine/data, checked against the facts of ../shared/data/headsq_ct/README.md, so that the
    check runs without the shared checkout."""
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP

    with pytest.raises(InputError, match="spacing_zyx_mm"):
        load_volume(HEADSQ_ZIP)
    vol = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    assert vol.data.shape == (93, 64, 64) and vol.data.dtype == np.uint16
    assert (int(vol.data.min()), int(vol.data.max())) == (0, 3926)
    assert int((vol.data > 500).sum()) == 144_947 and int((vol.data > 1150).sum()) == 34_240
