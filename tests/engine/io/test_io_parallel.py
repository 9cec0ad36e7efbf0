"""The threaded ingest (``engine.io.parallel``) against the serial loop: same arrays, same metadata, same errors."""

from __future__ import annotations

import io
import threading
import time
import zipfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile
from pydicom.uid import JPEG2000Lossless, RLELossless

from engine.errors import InputError
from engine.io import load_volume
from engine.io.archive import open_members
from engine.io.parallel import MAX_THREADS, decode_threads, ordered_map
from engine.types import Volume
from tests.engine.dicom_factory import break_rle, series

SP = (1.5, 0.4, 0.3)
THREADS = 4  # more threads than the 2-core CI machine has CPUs: interleaving is forced


def _zip(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in reversed(list(files)):  # stored out of order on purpose
            zf.writestr(name, files[name])
    return path


def _encode(img: np.ndarray, ext: str) -> bytes:
    if ext == ".tif":
        buf = io.BytesIO()
        tifffile.imwrite(buf, img, photometric="minisblack" if img.ndim == 2 else "rgb", compression="zlib")
        return buf.getvalue()
    return iio.imwrite("<bytes>", img, extension=ext)


def _stack(n: int, dtype: type, shape: tuple[int, int] = (33, 47), colour: bool = False) -> np.ndarray:
    rng = np.random.default_rng(n)
    hi = 255 if dtype == np.uint8 else 60000
    return rng.integers(0, hi, size=(n, *shape, 3) if colour else (n, *shape)).astype(dtype)


def _assert_same(a: Volume, b: Volume) -> None:
    assert a.data.dtype == b.data.dtype and a.data.shape == b.data.shape
    np.testing.assert_array_equal(a.data, b.data)
    assert a.spacing_zyx_mm == b.spacing_zyx_mm
    assert a.origin_mm == b.origin_mm and a.direction == b.direction
    assert a.units == b.units and a.patient_frame == b.patient_frame
    assert a.source == b.source


@pytest.mark.parametrize(
    ("ext", "dtype"), [(".png", np.uint16), (".png", np.uint8), (".tif", np.uint16), (".jpg", np.uint8)]
)
def test_image_stack_threads_equal_serial(tmp_path: Path, ext: str, dtype: type) -> None:
    vol = _stack(23, dtype)  # 23 slices: img10..img22 must follow img9 whatever thread finishes first
    path = _zip(tmp_path / "s.zip", {f"img{k}{ext}": _encode(s, ext) for k, s in enumerate(vol)})
    serial = load_volume(path, spacing_zyx_mm=SP, threads=1)
    threaded = load_volume(path, spacing_zyx_mm=SP, threads=THREADS)
    _assert_same(serial, threaded)
    assert serial.data.dtype == dtype  # kept as stored: no float32 copy on the host
    if ext != ".jpg":  # lossless: the stored values themselves
        np.testing.assert_array_equal(threaded.data, vol)


@pytest.mark.parametrize("kind", ["tar", "folder"])
def test_other_containers_threads_equal_serial(tmp_path: Path, kind: str) -> None:
    import tarfile

    vol = _stack(12, np.uint16)
    files = {f"s/img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)}
    path = tmp_path / kind
    if kind == "tar":
        with tarfile.open(path, "w") as tf:
            for name, data in files.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
    else:
        for name, data in files.items():
            (path / name).parent.mkdir(parents=True, exist_ok=True)
            (path / name).write_bytes(data)
    _assert_same(load_volume(path, spacing_zyx_mm=SP, threads=1), load_volume(path, spacing_zyx_mm=SP, threads=3))
    np.testing.assert_array_equal(load_volume(path, spacing_zyx_mm=SP, threads=3).data, vol)


def test_colour_slices_warn_once_in_both_paths(tmp_path: Path) -> None:
    from engine.io import StackWarning

    vol = _stack(6, np.uint8, colour=True)
    path = _zip(tmp_path / "c.zip", {f"c{k}.png": _encode(s, ".png") for k, s in enumerate(vol)})
    with pytest.warns(StackWarning, match=r"6 image\(s\) \(c0.png...\)"):
        serial = load_volume(path, spacing_zyx_mm=SP, threads=1)
    with pytest.warns(StackWarning, match=r"6 image\(s\) \(c0.png...\)"):
        threaded = load_volume(path, spacing_zyx_mm=SP, threads=THREADS)
    _assert_same(serial, threaded)


def test_mixed_sizes_refused_naming_the_first_odd_slice(tmp_path: Path) -> None:
    vol = _stack(14, np.uint16)
    files = {f"img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)}
    files["img5.png"] = _encode(np.zeros((20, 20), np.uint16), ".png")
    files["img11.png"] = _encode(np.zeros((21, 21), np.uint16), ".png")  # a later one that also differs
    files["img8.png"] = _encode(vol[8].astype(np.uint8), ".png")  # and one of another dtype
    path = _zip(tmp_path / "m.zip", files)
    messages = []
    for threads in (1, THREADS):
        with pytest.raises(InputError, match=r"expected every slice to be 47x33 uint16 like img0.png") as err:
            load_volume(path, spacing_zyx_mm=SP, threads=threads)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "got 20x20 uint16 in img5.png" in messages[0]


def test_corrupt_slice_named_in_both_paths(tmp_path: Path) -> None:
    vol = _stack(10, np.uint16)
    files = {f"img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)}
    files["img3.png"] = files["img3.png"][:60]  # signature intact, data cut short
    files["img7.png"] = files["img7.png"][:60]
    path = _zip(tmp_path / "bad.zip", files)
    for threads in (1, THREADS):
        with pytest.raises(InputError, match=r"cannot decode img3\.png as PNG"):
            load_volume(path, spacing_zyx_mm=SP, threads=threads)


def test_progress_reaches_one_in_order(tmp_path: Path) -> None:
    vol = _stack(9, np.uint16)
    path = _zip(tmp_path / "p.zip", {f"img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)})
    seen: list[float] = []
    load_volume(path, spacing_zyx_mm=SP, threads=THREADS, on_progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == pytest.approx(1.0) and len(seen) == 8


# ---- DICOM -----------------------------------------------------------------------------------------------------


def _field(p: np.ndarray) -> np.ndarray:
    return 40.0 * np.sin(p[..., 0] / 3.0) + 5.0 * p[..., 1] - 7.0 * p[..., 2]


@pytest.mark.parametrize(
    ("syntax", "extra"),
    [
        (None, {}),
        (RLELossless, {}),
        (JPEG2000Lossless, {}),
        (None, {"slope": 2.0, "intercept": -2048.0}),  # integral rescale: int16 in place
        (None, {"slope": 0.5, "intercept": -1024.0}),  # fractional rescale: float32
    ],
    ids=["explicit-le", "rle", "j2k-lossless", "int-rescale", "float-rescale"],
)
def test_dicom_threads_equal_serial(tmp_path: Path, syntax: str | None, extra: dict[str, float]) -> None:
    kwargs: dict[str, object] = dict(extra)
    if syntax is not None:
        kwargs["transfer_syntax"] = syntax
    files = series(_field, positions_mm=[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0], shape=(40, 36), **kwargs)
    path = _zip(tmp_path / "d.zip", files)
    serial = load_volume(path, threads=1)
    threaded = load_volume(path, threads=THREADS)
    _assert_same(serial, threaded)
    assert serial.units == "HU" and serial.source["files"] == 9
    if syntax is not None:
        assert threaded.source["transfer_syntax"] == syntax.name


def test_dicom_uneven_tilted_series_threads_equal_serial(tmp_path: Path) -> None:
    files = series(_field, positions_mm=[0.0, 1.0, 2.5, 3.0, 4.0, 5.5], drift=(0.0, 0.3, 0.0))
    path = _zip(tmp_path / "t.zip", files)
    serial = load_volume(path, threads=1)
    assert serial.source["resampled"] is True
    _assert_same(serial, load_volume(path, threads=THREADS))


def test_dicom_undecodable_pixels_named_in_both_paths(tmp_path: Path) -> None:
    files = series(_field, positions_mm=[0.0, 1.0, 2.0, 3.0, 4.0, 5.0], transfer_syntax=RLELossless)
    break_rle(files, ("IM3", "IM5"))
    path = _zip(tmp_path / "r.zip", files)
    errors = []
    for threads in (1, THREADS):
        with pytest.raises(InputError, match=r"cannot decode the pixels of IM3") as err:
            load_volume(path, threads=threads)
        errors.append(str(err.value))
    assert errors[0] == errors[1]


# ---- the pool and the archive handles ----------------------------------------------------------------------------


def test_ordered_map_keeps_order_and_raises_the_first_failure() -> None:
    def slow_square(k: int) -> int:
        time.sleep(0.002 * ((7 * k) % 5))  # finish out of order
        if k in (13, 17):
            raise ValueError(f"item {k}")
        return k * k

    assert list(ordered_map(slow_square, range(13), 4)) == [k * k for k in range(13)]
    got = []
    with pytest.raises(ValueError, match="item 13"):
        for v in ordered_map(slow_square, range(30), 4):
            got.append(v)
    assert got == [k * k for k in range(13)]


def test_ordered_map_runs_ahead_only_a_window_and_stops_on_close() -> None:
    started: list[int] = []
    lock = threading.Lock()

    def record(k: int) -> int:
        with lock:
            started.append(k)
        return k

    gen = ordered_map(record, range(1000), 3)
    assert next(gen) == 0
    time.sleep(0.05)
    assert len(started) <= 2 * 3 + 1  # the window, not the whole input
    gen.close()  # cancels what has not started; joins the pool
    n = len(started)
    time.sleep(0.05)
    assert len(started) == n <= 2 * 3 + 1


def test_ordered_map_serial_runs_on_the_callers_thread() -> None:
    me = threading.get_ident()
    assert list(ordered_map(lambda _: threading.get_ident(), range(3), 1)) == [me] * 3


def test_decode_threads() -> None:
    import os

    assert decode_threads(3) == 3
    default = decode_threads()
    assert 1 <= default <= MAX_THREADS and default <= (os.cpu_count() or 1)
    for bad in (0, -1, 1.5, True, "4"):
        with pytest.raises(ValueError, match="positive number of decode threads"):
            decode_threads(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="positive number of decode threads"):
        load_volume("nowhere.zip", threads=0)


def test_zip_members_read_concurrently_from_one_listing(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    files = {f"m{k}.bin": rng.integers(0, 256, size=int(rng.integers(1, 300_000)), dtype=np.uint8).tobytes()
             for k in range(40)}  # fmt: skip
    path = _zip(tmp_path / "z.zip", files)
    with open_members(path) as members:
        by_name = {m.name: m for m in members.members}
        names = [n for _ in range(3) for n in files]  # every member read three times, by several threads
        for name, data in zip(names, ordered_map(lambda n: by_name[n].read(), names, 8), strict=True):
            assert data == files[name]
        handles = members._archive
        assert handles is not None and len(handles._opened) > 1  # the pool's threads had their own
    assert handles._opened == []  # closing the listing closed them all


# ---- the fast PNG decoder ---------------------------------------------------------------------------------------


def test_fast_png_path_gives_what_imageio_gives(tmp_path: Path) -> None:
    from PIL import Image

    from engine.io import codecs

    pytest.importorskip("imagecodecs")
    rng = np.random.default_rng(3)
    plain = {
        "u16": iio.imwrite("<bytes>", rng.integers(0, 65535, (9, 13)).astype(np.uint16), extension=".png"),
        "u8": iio.imwrite("<bytes>", rng.integers(0, 255, (9, 13)).astype(np.uint8), extension=".png"),
    }
    for name, data in plain.items():
        assert codecs.plain_gray_png(data), name
        fast = codecs.decode_png_fast(data)
        assert fast is not None
        general = iio.imread(data)
        assert fast.dtype == general.dtype and np.array_equal(fast, general), name
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (9, 13)).astype(np.uint8)).save(buf, format="PNG", transparency=3)
    others = {
        "transparent grey": buf.getvalue(),
        "rgb": iio.imwrite("<bytes>", rng.integers(0, 255, (9, 13, 3)).astype(np.uint8), extension=".png"),
        "jpeg": iio.imwrite("<bytes>", rng.integers(0, 255, (9, 13)).astype(np.uint8), extension=".jpg"),
    }
    for name, data in others.items():  # left to imageio, which knows what to do with them
        assert not codecs.plain_gray_png(data) and codecs.decode_png_fast(data) is None, name


def test_stack_equal_with_and_without_the_fast_png_decoder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from engine.io import codecs

    pytest.importorskip("imagecodecs")
    vol = _stack(7, np.uint16)
    path = _zip(tmp_path / "f.zip", {f"img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)})
    fast = load_volume(path, spacing_zyx_mm=SP, threads=THREADS)
    monkeypatch.setattr(codecs, "USE_IMAGECODECS", False)
    _assert_same(fast, load_volume(path, spacing_zyx_mm=SP, threads=1))


def test_plain_tar_is_read_in_place_and_a_truncated_one_is_refused(tmp_path: Path) -> None:
    import tarfile

    files = {f"m{k}.bin": bytes([k]) * (1000 + 517 * k) for k in range(6)}
    path = tmp_path / "t.tar"
    with tarfile.open(path, "w") as tf:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    with open_members(path) as members:
        assert all(m._spool is None for m in members.members)  # no temporary copies
        got = dict(zip([m.name for m in members.members], ordered_map(lambda m: m.read(), members.members, 3),
                       strict=True))  # fmt: skip
    assert got == files
    with open_members(tmp_path / "t.tar", heads_only=False) as members:
        last = members.members[-1]
        with open(path, "r+b") as fh:  # the file shrinks after the listing: the read says so
            fh.truncate(path.stat().st_size - 10240 - 600)
        with pytest.raises(InputError, match=r"m5\.bin.*archive is truncated"):
            last.read()


def test_no_decode_thread_outlives_a_failed_load(tmp_path: Path) -> None:
    vol = _stack(30, np.uint16)
    files = {f"img{k}.png": _encode(s, ".png") for k, s in enumerate(vol)}
    files["img4.png"] = _encode(np.zeros((5, 5), np.uint16), ".png")
    path = _zip(tmp_path / "m.zip", files)
    with pytest.raises(InputError, match=r"in img4\.png") as err:
        load_volume(path, spacing_zyx_mm=SP, threads=THREADS)
    assert err.value.__traceback__ is not None  # the traceback (and its frames) still held here
    assert not [t for t in threading.enumerate() if t.name.startswith("bonemesh-decode")]
