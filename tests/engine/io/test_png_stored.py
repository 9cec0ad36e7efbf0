"""The PNG fast path (``engine.io.codecs``): libdeflate inflates, libpng decodes a stored stream of the same rows.

Its samples must be libpng's on the original bytes, bit for bit, for every filter type (None, Sub, Up, Average,
Paeth, chosen per row at random), 8 and 16 bits, odd sizes, one or several IDAT chunks, ancillary chunks before and
after them; what it does not rewrap (interlaced, damaged, a stream of another size) is decoded from the original,
with libpng's own result or error. The real scans of ``../shared`` are checked slice by slice when present.
"""

from __future__ import annotations

import struct
import zipfile

import imagecodecs
import numpy as np
import pytest

from engine.io import codecs
from engine.io.codecs import decode_png_fast
from tests.conftest import shared_file
from tests.engine.pngfactory import chunk as _chunk
from tests.engine.pngfactory import encode_adam7, encode_png, gray_slices

RNG = np.random.default_rng(7)


def _with_chunks(png: bytes, before: list[bytes], after: list[bytes]) -> bytes:
    """``png`` with these (already framed) chunks after IHDR and after the IDATs."""
    ihdr_end = 8 + 25
    iend = png.rindex(b"IEND") - 4
    return png[:ihdr_end] + b"".join(before) + png[ihdr_end:iend] + b"".join(after) + png[iend:]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("parts", [1, 3])
def test_every_filter_type_equals_libpng(dtype: type, parts: int) -> None:
    for img in gray_slices(RNG, 4, (23, 37), dtype):
        png = encode_png(img, RNG.integers(0, 5, size=img.shape[0]), idat_parts=parts)
        png = _with_chunks(
            png,
            [_chunk(b"pHYs", bytes(9)), _chunk(b"sBIT", bytes([12 if dtype == np.uint16 else 6]))],
            [_chunk(b"tEXt", b"Comment\x00after the data")],
        )
        view = codecs._stored(imagecodecs, png)
        assert view is not None
        stored = bytes(view)
        assert stored.count(b"IDAT") == 1 and b"tEXt" in stored and b"sBIT" in stored
        fast = decode_png_fast(png)
        assert fast is not None and fast.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(fast, img)
        np.testing.assert_array_equal(fast, imagecodecs.png_decode(png))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_decodes_into_a_plane_of_the_volume(dtype: type) -> None:
    imgs = gray_slices(RNG, 3, (12, 9), dtype)
    volume = np.zeros((3, 12, 9), dtype)
    for k, img in enumerate(imgs):
        plane = volume[k]
        got = decode_png_fast(encode_png(img, RNG.integers(0, 5, size=12)), plane)
        assert got is plane  # decoded in place: no temporary slice
    np.testing.assert_array_equal(volume, imgs)
    # a plane of another shape, type or layout is left alone: a new array comes back
    png = encode_png(imgs[0], np.zeros(12, int))
    for other in (np.zeros((9, 12), dtype), np.zeros((12, 9), np.float32), np.zeros((12, 18), dtype)[:, ::2]):
        got = decode_png_fast(png, other)
        assert got is not other and not other.any()
        np.testing.assert_array_equal(got, imgs[0])


def test_what_it_does_not_rewrap_is_decoded_from_the_original() -> None:
    img = gray_slices(RNG, 1, (16, 20), np.uint16)[0]
    interlaced = encode_adam7(img)
    assert codecs._stored(imagecodecs, interlaced) is None
    np.testing.assert_array_equal(decode_png_fast(interlaced), img)
    png = encode_png(img, RNG.integers(0, 5, size=16))
    start = png.index(b"IDAT") + 4
    damaged = png[: start + 10] + bytes(8) + png[start + 18 :]
    assert codecs._stored(imagecodecs, damaged) is None
    with pytest.raises(Exception) as fast:
        decode_png_fast(damaged)
    with pytest.raises(Exception) as plain:
        imagecodecs.png_decode(damaged)
    assert type(fast.value) is type(plain.value) and str(fast.value) == str(plain.value)
    # rows of another size than the header's (a header that lies about the height): libpng's verdict, not ours
    ihdr = struct.pack(">IIBBBBB", 20, 15, 16, 0, 0, 0, 0)
    lying = png[:8] + _chunk(b"IHDR", ihdr) + png[8 + 25 :]
    assert codecs._stored(imagecodecs, lying) is None
    try:
        expected = imagecodecs.png_decode(lying)
    except Exception as exc:
        with pytest.raises(type(exc)):
            decode_png_fast(lying)
    else:
        np.testing.assert_array_equal(decode_png_fast(lying), expected)


@pytest.mark.parametrize("name", ["cranium_ct/cranium_ct_png16.zip", "head_phantom_dicom/head_phantom_png16.zip"])
def test_real_scans_equal_libpng(name: str) -> None:
    path = shared_file(*name.split("/"))
    with zipfile.ZipFile(path) as zf:
        for member in [n for n in zf.namelist() if n.endswith(".png")]:
            data = zf.read(member)
            assert codecs._stored(imagecodecs, data) is not None, member
            np.testing.assert_array_equal(decode_png_fast(data), imagecodecs.png_decode(data), err_msg=member)
