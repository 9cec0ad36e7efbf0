"""The named kernels of the per-label meshing (``engine.backend.Kernel``), each written twice: the Warp kernels of
``kernels/labels.py`` and their OpenCL C twins in ``kernels/labels.cl``, launched with the same arguments by the one
host code of ``engine.labels.extract``. Importing this module loads neither Warp nor PyOpenCL."""

from __future__ import annotations

from engine.backend.base import Kernel

_K = "engine.labels.kernels"


def _spec(name: str) -> Kernel:
    return Kernel(f"labels.{name}", f"{_K}.labels:{name}", f"{_K}:labels.cl:{name}")


MARK_EXTENT = _spec("mark_extent")  # generic over the map's integer type (``dtype=``)
FILL_ATLAS = _spec("fill_atlas")  # generic
PLACE_VERTICES = _spec("place_vertices")  # generic
OFFSET_FACES = _spec("offset_faces")
GATHER_SLOTS = _spec("gather_slots")
FACE_SUMS = _spec("face_sums")
LOCK_SLOTS = _spec("lock_slots")
