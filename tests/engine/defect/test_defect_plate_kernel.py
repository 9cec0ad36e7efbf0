"""The grid's allowance in the core test on the device (``region._plate_launch``, the ``PLATE`` kernel of
``kernels/plate.py`` and its OpenCL C twin ``plate.cl``) against a reference written here in numpy and scipy, in
double precision: a plate turned off the grid's axes (so the shell's normals are oblique and the columns sample
between voxels), a round hole through it, anisotropic voxels. Every backend gives the reference's cores, and the
cores of the growth (``cores``) are the strict ones and those."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

SPACING = np.array([3.0, 1.25, 1.25])  # exact in float32: no tie at two voxel widths is decided by rounding
LEVEL = 500.0
SHELLS = 2.0


def _scene(thick_mm: float) -> tuple[np.ndarray, ...]:
    """A plate about 9 mm thick, tilted 20 degrees about x, with a 24 mm hole; its mirror image the whole plate.
    What ``_rules`` hands the allowance: code, thick, to_bone, core (strict), mirrored, data (smooth fields, so the
    columns' trilinear samples cross the level between voxels)."""
    from engine.defect.region import BONE, MIRROR

    shape = (30, 48, 48)
    z, y, x = np.indices(shape).astype(np.float64)
    zm, ym, xm = z * SPACING[0], y * SPACING[1], x * SPACING[2]
    a = np.radians(20.0)
    across = (zm - 45.0) * np.cos(a) - (ym - 30.0) * np.sin(a)  # mm across the plate
    plate = 1000.0 * np.clip(5.0 - np.abs(across), 0.0, 1.0)  # 1000 inside, a 1 mm ramp at each face
    along = (zm - 45.0) * np.sin(a) + (ym - 30.0) * np.cos(a)
    hole = np.hypot(along, xm - 30.0) < 12.0
    mirrored = plate.astype(np.float32)
    data = np.where(hole, 0.0, plate).astype(np.float32)
    bone, mirror_bone = data >= LEVEL, mirrored >= LEVEL
    code = (np.where(bone, BONE, 0) | np.where(mirror_bone, MIRROR, 0) | np.where(data < 0.5 * LEVEL, 8, 0)).astype(
        np.uint8
    )
    thick = np.where(mirror_bone & ~bone, thick_mm, 0.0).astype(np.float32)
    to_bone = ndi.distance_transform_edt(~bone, sampling=SPACING).astype(np.float32)
    core = (((code & MIRROR) != 0) & ~bone & ((code & 8) != 0) & (to_bone > thick)).astype(np.uint8)
    return code, thick, to_bone, core, mirrored, data


def _reference(code, thick, to_bone, core, mirrored, data) -> set[tuple[int, int, int]]:
    """The rule as ``region.PLATE_SHELLS`` states it, in double precision, voxel by voxel."""
    from engine.defect.region import BONE, MIRROR

    shape = np.asarray(code.shape)
    big = float(SPACING.max())
    step = 0.5 * float(SPACING.min())
    out = set()
    for v in np.argwhere(((code & MIRROR) != 0) & ((code & BONE) == 0) & ((code & 8) != 0) & (core == 0)):
        t = float(thick[tuple(v)])
        if t <= 0.0:
            continue
        g = np.zeros(3)
        for k in range(27):
            off = np.array([k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1])
            w = np.array([(2 - off[1] ** 2) * (2 - off[2] ** 2), (2 - off[0] ** 2) * (2 - off[2] ** 2),
                          (2 - off[0] ** 2) * (2 - off[1] ** 2)])  # fmt: skip
            g += off * w * float(mirrored[tuple(np.clip(v + off, 0, shape - 1))]) / SPACING
        if not np.linalg.norm(g) > 0:
            continue
        u = g / np.linalg.norm(g)
        width = min(float(np.abs(u) @ SPACING), big)
        if not float(to_bone[tuple(v)]) > max(t - width, 2.0 * width):
            continue
        free, run = True, [True, True]
        k = 1
        while free and k * step <= SHELLS * t + step:
            for s, sign in enumerate((1.0, -1.0)):
                p = (v + sign * k * step * u / SPACING)[:, None]
                scan = ndi.map_coordinates(data, p, order=1, mode="constant", cval=-1.0e30)[0] >= LEVEL
                mirror = ndi.map_coordinates(mirrored, p, order=1, mode="constant", cval=-1.0e30)[0] >= LEVEL
                run[s] = run[s] and mirror
                free = free and not (scan or (not run[s] and mirror))
            k += 1
        if free:
            out.add(tuple(int(i) for i in v))
    return out


def test_the_kernel_gives_the_references_cores(device):
    """Read as 13 mm (a voxel over the 10 mm shell), the hole has no strict core; the allowance adds the voxels the
    reference finds, on every backend, and the growth starts from the strict cores and those."""
    from engine.backend.select import get_backend
    from engine.defect.region import _box, _plate_launch

    code, thick, to_bone, core, mirrored, data = _scene(13.0)
    assert not core.any()
    want = _reference(code, thick, to_bone, core, mirrored, data)
    assert len(want) >= 20  # the scene exercises the rule: a hole's middle, away from its rim
    be = get_backend(device)
    shape = code.shape

    def up(a, dtype):
        return be.from_host(np.ascontiguousarray(a, dtype=dtype).reshape(-1))

    box = _box(be, shape, np.zeros(3, np.int64), tuple(float(s) for s in SPACING))
    arrays = [up(data, np.float32), up(mirrored, np.float32), up(code, np.uint8), up(thick, np.float32),
              up(to_bone, np.float32), up(core, np.uint8)]  # fmt: skip
    marked, cores = _plate_launch(be, shape, box, *arrays, LEVEL)
    marked_h = be.to_host(marked).reshape(shape)
    got = {tuple(int(i) for i in v) for v in np.argwhere(marked_h == 3)}
    assert got == want
    np.testing.assert_array_equal(np.where(marked_h == 3, 0, marked_h), core)  # the strict cores kept as they were
    np.testing.assert_array_equal(be.to_host(cores).reshape(shape).astype(bool), (core == 1) | (marked_h == 3))


def test_the_kernel_agrees_with_the_reference_where_the_reading_is_right_or_too_thick(device):
    """Read as 10 mm (the shell's own thickness) the strict rule finds the hole's middle and the allowance adds the
    ring around it; read as 16 mm, no voxel of the 24 mm hole is far enough from the rim for either. The backend's
    cores (``_plate_cores``, host arrays in and out) are the reference's in both."""
    from engine.defect.region import _plate_cores

    for thick_mm, strict in ((10.0, True), (16.0, False)):
        code, thick, to_bone, core, mirrored, data = _scene(thick_mm)
        assert core.any() == strict
        want = _reference(code, thick, to_bone, core, mirrored, data)
        assert bool(want) == strict
        got = _plate_cores(code, thick, to_bone, core, mirrored, data, SPACING, LEVEL, device)
        assert {tuple(int(i) for i in v) for v in got} == want
