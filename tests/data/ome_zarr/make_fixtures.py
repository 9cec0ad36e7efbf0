"""Writes the OME-Zarr fixtures of ``tests/engine/io/test_io_zarr.py`` with ome-zarr-py's ``write_image`` (the OME
community's writer), so that the reader is tested on files another project wrote. ome-zarr-py pulls in s3fs and
aiobotocore, whose botocore pin clashes with the project's boto3, so it is not a test dependency: run this in a
virtual environment of its own, from the repository root:

    python -m venv /tmp/ozvenv && /tmp/ozvenv/bin/pip install "ome-zarr==0.18.0"
    PYTHONPATH=. /tmp/ozvenv/bin/python tests/data/ome_zarr/make_fixtures.py

It writes ``phantom_v04.ome.zarr`` (OME-NGFF 0.4 on Zarr v2) and ``phantom_v05.ome.zarr`` (0.5 on Zarr v3): the
bone phantom ``engine.data.phantom.bone_phantom(SHAPE)`` at two levels (full resolution, and halved on every axis),
the voxel size ``SCALE`` in micrometer, chunks of ``CHUNKS``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import zarr
from ome_zarr.format import FormatV04, FormatV05
from ome_zarr.writer import write_image

from engine.data.phantom import bone_phantom

SHAPE = (16, 32, 40)
SCALE = {"z": 120.0, "y": 100.0, "x": 80.0}  # micrometer
CHUNKS = (4, 16, 16)
HERE = Path(__file__).resolve().parent


def main() -> None:
    image = bone_phantom(SHAPE, workers=1)
    for name, fmt in (("phantom_v04.ome.zarr", FormatV04()), ("phantom_v05.ome.zarr", FormatV05())):
        path = HERE / name
        shutil.rmtree(path, ignore_errors=True)
        group = zarr.open_group(str(path), mode="w", zarr_format=fmt.zarr_format)
        write_image(
            image,
            group,
            scale_factors=[{"z": 2, "y": 2, "x": 2}],
            method="nearest",
            fmt=fmt,
            axes="zyx",
            scale=SCALE,
            axes_units={"z": "micrometer", "y": "micrometer", "x": "micrometer"},
            storage_options={"chunks": CHUNKS},
        )
        print(name, sorted(p.name for p in path.iterdir()))  # noqa: T201


if __name__ == "__main__":
    main()
