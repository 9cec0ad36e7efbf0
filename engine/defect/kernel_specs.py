"""The named kernels of the defect template (``engine.backend.Kernel``), each written twice: the Warp kernels of
``kernels/edt.py``, ``kernels/mirror.py``, ``kernels/plate.py``, ``kernels/plane.py`` and ``kernels/skull.py``, and
the OpenCL C of ``kernels/edt.cl``, ``kernels/mirror.cl``, ``kernels/plate.cl``, ``kernels/plane.cl`` and
``kernels/skull.cl``, launched with the same arguments by the one host code (``engine.defect.ops``,
``engine.defect.region``, ``engine.defect.plane``); and the argument structs they share."""

from __future__ import annotations

import numpy as np

from engine.backend.base import Kernel, Struct

_EDT, _EDT_CL = "engine.defect.kernels.edt", "engine.defect.kernels:edt.cl"
_MIR, _MIR_CL = "engine.defect.kernels.mirror", "engine.defect.kernels:mirror.cl"
_PLN, _PLN_CL = "engine.defect.kernels.plane", "engine.defect.kernels:plane.cl"
_SKL, _SKL_CL = "engine.defect.kernels.skull", "engine.defect.kernels:skull.cl"
_PLT, _PLT_CL = "engine.defect.kernels.plate", "engine.defect.kernels:plate.cl"

FEATURES = Kernel("defect.features", f"{_EDT}:features_kernel", f"{_EDT_CL}:features")
EDT_PASS = Kernel("defect.edt_pass", f"{_EDT}:edt_pass_kernel", f"{_EDT_CL}:edt_pass")
EDT_SQRT = Kernel("defect.edt_sqrt", f"{_EDT}:sqrt_kernel", f"{_EDT_CL}:edt_sqrt")
MIRROR = Kernel("defect.mirror", f"{_MIR}:mirror_kernel", f"{_MIR_CL}:mirror")
CORE = Kernel("defect.core", f"{_MIR}:core_kernel", f"{_MIR_CL}:core")
GROW = Kernel("defect.grow", f"{_MIR}:grow_kernel", f"{_MIR_CL}:grow")
SELECT = Kernel("defect.select", f"{_MIR}:select_kernel", f"{_MIR_CL}:select_value")
BITS = Kernel("defect.bits", f"{_MIR}:bits_kernel", f"{_MIR_CL}:any_bits")
RIDGE = Kernel("defect.ridge", f"{_MIR}:ridge_kernel", f"{_MIR_CL}:ridge")
PLATE = Kernel("defect.plate", f"{_PLT}:plate_kernel", f"{_PLT_CL}:plate")
CFT_SEED = Kernel("defect.cft_seed", f"{_PLN}:seed_kernel", f"{_PLN_CL}:seed")
CFT_PASS = Kernel("defect.cft_pass", f"{_PLN}:cft_pass_kernel", f"{_PLN_CL}:cft_pass")
NEAREST_PART = Kernel("defect.nearest_part", f"{_PLN}:nearest_part_kernel", f"{_PLN_CL}:nearest_part")
NEAREST_JOIN = Kernel("defect.nearest_join", f"{_PLN}:nearest_join_kernel", f"{_PLN_CL}:nearest_join")
FLAGS = Kernel("defect.flags", f"{_PLN}:flags_kernel", f"{_PLN_CL}:flags")
SOBEL = Kernel("defect.sobel", f"{_PLN}:sobel_kernel", f"{_PLN_CL}:sobel")
PIECE_INIT = Kernel("defect.piece_init", f"{_SKL}:init_kernel", f"{_SKL_CL}:init")
PIECE_HOOK = Kernel("defect.piece_hook", f"{_SKL}:hook_kernel", f"{_SKL_CL}:hook")
PIECE_ROOTS = Kernel("defect.piece_roots", f"{_SKL}:roots_kernel", f"{_SKL_CL}:roots")
PIECE_GATHER = Kernel("defect.piece_gather", f"{_SKL}:gather_kernel", f"{_SKL_CL}:gather")
PIECE_MASK = Kernel("defect.piece_mask", f"{_SKL}:piece_kernel", f"{_SKL_CL}:piece")

_I, _F = np.int32, np.float32
MIRROR_MAP = Struct(
    "defect.Mirror",
    f"{_MIR}:Mirror",
    tuple((name, _F) for name in ("a00", "a01", "a02", "a10", "a11", "a12", "a20", "a21", "a22", "b0", "b1", "b2")),
)  # q = a @ p + b on grid (x, y, z) mm
BOX = Struct(
    "defect.Box",
    f"{_MIR}:Box",
    (("nz", _I), ("ny", _I), ("nx", _I), ("lz", _I), ("ly", _I), ("lx", _I), ("sz", _F), ("sy", _F), ("sx", _F)),
)  # a crop: shape, first voxel in the whole grid (z, y, x), spacing (z, y, x mm)
