"""Warp kernels of device meshes, by concern: ``topology`` (stars, vertex classes), ``compaction``, ``measures``
(edge census, volumes, pieces) and ``smoothing`` (Laplacian smoothing and vertex normals). No host logic lives here.
"""
