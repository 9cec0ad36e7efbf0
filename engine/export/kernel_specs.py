"""The named kernels of the output layout (``engine.backend.Kernel``): the Warp kernels of ``layout.py`` and their
OpenCL C twins in ``layout.cl``, launched by ``engine.job.outputs.lay_out``."""

from __future__ import annotations

from engine.backend.base import Kernel


def _spec(name: str) -> Kernel:
    return Kernel(
        f"export.layout.{name}", f"engine.export.kernels.layout:{name}", f"engine.export.kernels:layout.cl:{name}"
    )


AFFINE_POINTS = _spec("affine_points")
ROTATE_VECTORS = _spec("rotate_vectors")
REVERSE_FACES = _spec("reverse_faces")
STL_FACETS = _spec("stl_facets")
GLTF_VERTICES = _spec("gltf_vertices")
