"""The named kernels of Marching Cubes 33 (``engine.backend.Kernel``), each written twice: the Warp kernels of
``kernels/mc33.py`` and the OpenCL C of ``kernels/mc33.cl``, launched with the same arguments by the one host pass
(``engine.isosurface.slabs``); and the slab geometry struct they share (``GRID``)."""

from __future__ import annotations

import numpy as np

from engine.backend.base import Kernel, Struct

BLOCK = 8  # cells per block edge: the kernels' BLOCK (both files), checked by test_opencl_mc33.py
BLOCK_CELLS = BLOCK * BLOCK * BLOCK

_W = "engine.isosurface.kernels.mc33"
_CL = "engine.isosurface.kernels:mc33.cl"
BLOCKS = Kernel("mc33.block", f"{_W}:block_kernel", f"{_CL}:block")
NAN = Kernel("mc33.nan", f"{_W}:nan_kernel", f"{_CL}:nan_check")
COUNT = Kernel("mc33.count", f"{_W}:count_kernel", f"{_CL}:count")
EMIT = Kernel("mc33.emit", f"{_W}:emit_kernel", f"{_CL}:emit")
PLANE = Kernel("mc33.plane", f"{_W}:plane_kernel", f"{_CL}:plane")

_I, _F = np.int32, np.float32
GRID = Struct(
    "mc33.Grid",
    f"{_W}:Grid",
    (
        ("nz", _I), ("ny", _I), ("nx", _I), ("zoff", _I), ("bz0", _I), ("nbz", _I), ("nby", _I), ("nbx", _I),
        ("cz_first", _I), ("level", _F), ("pad", _F), ("closed", _I), ("tau", _F), ("sz", _F), ("sy", _F),
        ("sx", _F),
    ),
)  # fmt: skip
