"""Fast decoders for the commonest slice format, used where they give exactly what the general path gives.

A 16- or 8-bit grayscale PNG (colour type 0, no transparency chunk: what CT exporters write) is decoded with
``imagecodecs.png_decode`` (libpng), which holds no GIL while it inflates and unfilters, so it scales with the
threads of ``engine.io.parallel``; Pillow's PNG reader runs its chunk loop in Python and scales less. Everything
else (palette, colour, alpha, 1/2/4-bit PNG, JPEG, BMP), and every PNG when imagecodecs is not installed, goes
through imageio/Pillow as before. Both give the stored values as uint8/uint16 (tests check they agree).
"""

from __future__ import annotations

import numpy as np

USE_IMAGECODECS = True  # benchmarks switch it off to time the general path


def _imagecodecs() -> object | None:
    try:
        import imagecodecs
    except ImportError:
        return None
    return imagecodecs if imagecodecs.PNG.available else None


def plain_gray_png(data: bytes) -> bool:
    """Whether PNG bytes hold an 8- or 16-bit grayscale image without a transparency chunk."""
    if len(data) < 33 or data[12:16] != b"IHDR" or data[25] != 0 or data[24] not in (8, 16):
        return False
    idat = data.find(b"IDAT")
    return idat > 0 and b"tRNS" not in data[:idat]


def decode_png_fast(data: bytes) -> np.ndarray | None:
    """The (y, x) array of a plain grayscale PNG through libpng; None when the general path must decode it."""
    if not USE_IMAGECODECS or not plain_gray_png(data):
        return None
    codecs = _imagecodecs()
    if codecs is None:
        return None
    arr = codecs.png_decode(data)  # type: ignore[attr-defined]
    return arr if arr.ndim == 2 and arr.dtype in (np.uint8, np.uint16) else None
