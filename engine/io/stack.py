"""Slice stacks (zip of 2-D images) -> (z, y, x) arrays."""

from __future__ import annotations

import io
import re
import zipfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")


def natural_key(name: str) -> list[object]:
    """Sort key that puts ``img2`` before ``img10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def load_slice_zip(path: str | Path) -> npt.NDArray[np.generic]:
    """Read a zip of 2-D grayscale slices (natural name order) into a (z, y, x) array of their dtype.

    Raises:
        ValueError: the archive holds no images, or slices differ in shape or dtype.
    """
    import imageio.v3 as iio

    with zipfile.ZipFile(path) as zf:
        names = sorted(
            (n for n in zf.namelist() if n.lower().endswith(IMAGE_SUFFIXES) and not n.endswith("/")),
            key=natural_key,
        )
        if not names:
            raise ValueError(f"Expected image slices in {path}, found none")
        slices = [iio.imread(io.BytesIO(zf.read(n))) for n in names]
    first = slices[0]
    for n, s in zip(names, slices, strict=True):
        if s.shape != first.shape or s.dtype != first.dtype:
            raise ValueError(f"Expected every slice to be {first.shape} {first.dtype}, got {s.shape} {s.dtype} in {n}")
    return np.stack(slices)
