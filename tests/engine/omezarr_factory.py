"""OME-Zarr images written with zarr itself, following the OME-NGFF specification (v0.4 on Zarr v2, v0.5 on Zarr
v3), for the cases the committed fixtures (``tests/data/ome_zarr``, written by ome-zarr-py) do not cover: other
units, translations, channel and time axes, sharding, broken metadata, large volumes (``benchmarks/big_formats.py``).

    write_ome_zarr(path, volume, version="0.5", scale=(0.5, 0.25, 0.25), unit="micrometer")
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def write_ome_zarr(
    path: Path | str,
    volume: np.ndarray,
    *,
    version: str = "0.5",
    scale: Sequence[float] = (1.0, 1.0, 1.0),
    translation: Sequence[float] | None = None,
    unit: str | None = "micrometer",
    levels: int = 1,
    chunks: Sequence[int] | None = None,
    shards: Sequence[int] | None = None,
    extra_axes: str = "",
    attrs: dict[str, Any] | None = None,
) -> Path:
    """Write ``volume`` (z, y, x) as an OME-Zarr image at ``path``: ``levels`` levels ``"0"``, ``"1"``, ... (each
    halved on every axis by striding), the voxel size ``scale`` (z, y, x) in ``unit`` (None: no unit on the axes)
    and the optional ``translation``, ``extra_axes`` of size 1 before z ("t", "c" or "tc"); ``attrs`` replace the
    group's attributes (to write broken metadata). Returns ``path``."""
    import zarr

    zarr_format = 3 if version == "0.5" else 2
    group = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    lead = (1,) * len(extra_axes)
    datasets = []
    for k in range(levels):
        f = 2**k
        data = volume[::f, ::f, ::f].reshape(lead + volume[::f, ::f, ::f].shape)
        chunk = tuple(lead) + tuple(min(c, n) for c, n in zip(chunks or data.shape[-3:], data.shape[-3:], strict=True))
        kwargs: dict[str, Any] = {"chunks": chunk}
        if shards is not None:
            inner = chunk[len(lead) :]  # a shard holds whole chunks
            kwargs["shards"] = tuple(lead) + tuple(
                min(s, -(-n // c) * c) for s, n, c in zip(shards, data.shape[-3:], inner, strict=True)
            )
        if zarr_format == 3:
            kwargs["dimension_names"] = [*extra_axes, "z", "y", "x"]
        else:
            kwargs["chunk_key_encoding"] = {"name": "v2", "separator": "/"}
        arr = group.create_array(str(k), shape=data.shape, dtype=data.dtype, **kwargs)
        arr[...] = data
        transforms: list[dict[str, Any]] = [{"type": "scale", "scale": [*lead, *(s * f for s in scale)]}]
        if translation is not None:
            transforms.append({"type": "translation", "translation": [*(0.0 for _ in lead), *translation]})
        datasets.append({"path": str(k), "coordinateTransformations": transforms})
    kinds = {"t": "time", "c": "channel"}
    axes = [{"name": a, "type": kinds[a]} for a in extra_axes]
    axes += [{"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in "zyx"]
    multiscale = {"name": "image", "axes": axes, "datasets": datasets}
    if attrs is not None:
        group.attrs.put(attrs)
    elif version == "0.5":
        group.attrs.put({"ome": {"version": "0.5", "multiscales": [multiscale]}})
    else:
        group.attrs.put({"multiscales": [{"version": version, **multiscale}]})
    return Path(path)


def zip_folder(folder: Path, archive: Path, *, top: bool = True) -> Path:
    """Zip ``folder`` (stored, no compression: chunks are compressed already) with its name as the top folder
    (``top``) or its contents at the archive's top. Returns ``archive``."""
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:
        for root, _, files in os.walk(folder):
            for name in sorted(files):
                full = Path(root) / name
                rel = full.relative_to(folder.parent if top else folder).as_posix()
                zf.write(full, rel)
    return archive


def upload_folder(client: Any, folder: Path, bucket: str, key: str) -> str:
    """Put every file of ``folder`` under ``s3://bucket/key/`` with a boto3 ``client``; returns the URL."""
    for root, _, files in os.walk(folder):
        for name in files:
            full = Path(root) / name
            client.upload_file(str(full), bucket, f"{key}/{full.relative_to(folder).as_posix()}")
    return f"s3://{bucket}/{key}"
