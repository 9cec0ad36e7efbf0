"""Warp kernels of device meshes, by concern: ``topology`` (stars, vertex classes), ``compaction``, ``measures``
(edge census, volumes, pieces) and ``smoothing`` (Laplacian smoothing and vertex normals), each with its OpenCL C twin
(``topology.cl``, ...: the same kernels, arithmetic and order; named in ``engine.surface.kernel_specs``). No host
logic lives here.
"""
