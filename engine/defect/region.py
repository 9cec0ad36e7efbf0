"""The defect region: bone that the mirror image has and the scan lacks, where it is missing, not moved.

On a crop around the skull and its mirror image (Warp kernels, ``engine.defect.kernels``; the host labels the
pieces and measures them):

1. **Mirror**: the scan sampled (trilinear) at every voxel's mirror image across the plane; the mirrored skull is
   the mirrored samples at or above the level next to the skull's mirror image. ``tissue``: the median of the
   samples 1.5 voxels to 2 mm beyond the bone (scalp, brain, air); a sample is *absent bone* when it is nearer to
   that than to the level (``mid``, halfway), so thin bone below the level is not missing bone.
2. **Shell rule**: the local thickness ``t`` of the healthy shell: the diameter of the largest ball inside the
   skull centred within ``THICKNESS_REACH_MM`` of the voxel's mirror image. A voxel of the mirrored skull outside
   the bone is a *core* voxel when no bone of the scan lies within ``t`` of it and its sample is absent bone: a
   mirror that is off by less than the shell's thickness (asymmetry, an imperfect plane) leaves a sliver with bone
   beside it, never a core; only a hole through the whole shell does. The defect is every voxel of the mirrored
   skull outside the bone within ``t`` + one voxel of a core (the core grown back to the rim): 26-connected pieces
   that hold a core.
3. **Mirrored locally**: each candidate piece is mirrored again across the plane fitted to the scan around it
   (``engine.defect.plane.ring_plane``: the samples within ``RING_MM`` of it, it left out, matched with their
   mirror images, sub-voxel) and the rules rerun there: the template fits the rim it fills, and a piece that a
   turned neck or jaw made (gone when mirrored across its own bone's plane) is asymmetry, not a hole. A local plane
   that would move the piece's mirror image by more than ``MAX_LOCAL_MOVE_MM`` has matched something else (the
   hole itself) and is not used.
4. **Missing, not moved**: the same rule the other way round finds *anti-cores*, bone of the scan with no mirrored
   bone within its thickness. Bone missing on one side has its anti-core at its mirror image, across the plane;
   bone that moved has one right beside it as well. A piece with more anti-core than ``MAX_ANTI_SHARE`` of its core
   beside it (within ``2 t`` + one voxel, its own mirror image's surroundings left out) is moved bone.
5. **Through the shell, and its rim** (``engine.defect.rim``): a defect is a hole through the whole shell: its
   columns along the mirrored shell's normal span the mirrored shell (``spans_shell``) over an opening at least
   ``MIN_SPAN_WIDTH_MM`` wide and ``MIN_SPAN_SHARE`` of its outline, however its rim is bevelled (a sliver of
   asymmetry or a partial-thickness dent has the scan's bone across the rest of the shell). A defect fills a hole in
   the bone, so its rim meets the bone; a piece whose rim meets it over less than ``MIN_CONTACT`` is not a hole's
   fill. A kept piece is filled out to the rim with the mirror's bone (``_to_rim``), and a rim gap still over a voxel
   is bridged across to the bone (``_close_rim``). A piece whose rim is open on the side of the plane, or that lies
   across the plane, is a defect across the midline (``MidlineDefectError``). So is a would-be template whose hole
   goes on past the plane (``engine.defect.rim.past_plane``, followed along the shell from the template's edge
   facing it) by more than ``MIDLINE_PAST_MM``: past the plane the mirror image lacks the bone too, and the
   template stops as far short of it; by less, the template is kept with a warning (``midline_warning``).
6. **Confidence**: the mirror image's overlap with the bone around the piece (``local_fit``) times the share of its
   filled rim that meets the bone must reach ``MIN_CONFIDENCE``; below it the template would not fit the hole (the
   sides differ there, or the pose and slices defeat the mirror) and the piece is refused with both measures.
7. **Size**: a piece smaller than ``min_defect_volume`` is left out, unless its opening, seen along its thinnest
   axis, is at least ``MIN_DEFECT_WIDTH_MM`` wide (``_wide_opening``: the plug's thickness as the grid reads it
   over-reads a thin shell on coarse slices); none left is ``NoDefectError``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.backend.base import Backend
from engine.defect.grid import CONNECTIVITY, BoolArray, FloatArray, Grid, bounding_box, label_voxels, reflect, touching
from engine.defect.params import DefectParams
from engine.defect.plane import SymmetryPlane, reflection, ring_plane
from engine.defect.rim import (
    Across,
    Rim,
    Span,
    open_toward_plane,
    opening_width_mm,
    past_plane,
    rim_of,
    spans_shell,
)
from engine.errors import MidlineDefectError, NoDefectError

THICKNESS_REACH_MM = 5.0  # the shell's middle is looked for this far around a voxel (shells up to 10 mm)
RING_MM = 15.0  # a piece's own plane is fitted on the scan's samples within this distance of it (it left out)
MAX_LOCAL_MOVE_MM = 4.0  # the local plane may move a piece's mirror image this far (or two voxels) from the global
MAX_LOCAL_PIECES = 24  # the largest candidates (by volume) that are mirrored locally
MAX_ANTI_SHARE = 0.5
MIN_CONTACT = 0.5
# confidence: how well the mirror image matches the scan's bone around a piece (``local_fit``, intersection over
# union) times the share of its rim that meets the bone once filled (``Rim.contact``). Measured on the sweep (issue
# 42): the head phantom's templates with Dice 0.17-0.55 had 0.25-0.34 (a turned head of 5 mm slices: the mirror off
# by a slice, its bone short of the rim), those with Dice 0.74 and more 0.38-0.56, headsq's and the cranium's 0.40+
MIN_CONFIDENCE = 0.36
# a rim gap of more than this many voxels is closed across gaps up to RIM_CLOSE_SHELLS shells wide
CLOSE_GAP_VOXELS = 1.0
RIM_CLOSE_SHELLS = 0.5
# ... and a template whose rim is still more than this many voxels (mean over its outline) off the bone once filled
# out to the rim, bridged and filled across slices is refused: it would not close the hole (issue 42's goal; the
# sweep's one such template, the turned head phantom's 40 mm cut at 67.5 degrees, high: 1.36 voxels, its top
# slice's rim 1.4-8.6 mm in-plane from the bone, where the mirror's oblique thin vault falls under the level; wider
# bridges made it 1.39-1.54)
MAX_RIM_GAP_VOXELS = 1.0
# a piece that comes within a shell's thickness of the plane is looked at for a hole going on across it, this far
# past its edge toward the plane (at least 3 shells)
MIDLINE_REACH_MM = 15.0
MIN_OPEN_TOWARD_PLANE = 0.4  # measured: one-sided defects 0.0-0.41 (near the midline), across it 0.45-0.78
# how far the hole goes on past the plane (``engine.defect.rim.past_plane``: from the template's edge facing the
# plane along the shell to the hole's rim, over a front MIN_SPAN_WIDTH_MM wide): past the plane the mirror image
# lacks the bone too, and the template stops about as far short of it, so the strip it leaves open at the midline
# is about twice as wide. A hole reaching past the plane by more than MIDLINE_PAST_MM (or a voxel along the way,
# the measure's own step, where that is more) is a midline defect; one reaching past it by less keeps its template
# with a warning in defect.json (issue 42). Measured on the sweep (docs/defect.md): the one-sided templates within
# MIDLINE_NEAR_MM of the plane -28.9 to +2.3 mm, the cuts across it that got templates until then 1.6 (the
# cranium's, its removed bone 3 mm past) and 3.0-15 mm
MIDLINE_PAST_MM = 2.5
# ... measured from a template's edge within this distance of the plane (a hole across it by as much has its
# template's edge there); a straight path along the shell from farther off leaves the skull's curve and meets no
# bone (the gantry-tilt head's one-sided cuts low at the side, 61 mm off, read 15 mm past it)
MIDLINE_NEAR_MM = 2.0 * MIDLINE_REACH_MM
# a defect is a hole through the shell: the scan lacks the mirrored shell across its whole thickness (its columns
# along the shell's normal span it, ``engine.defect.rim.spans_shell``) over an opening at least this wide, and over
# at least this share of its outline (a bevelled rim spans it only over its narrowest opening)
MIN_SPAN_WIDTH_MM = 8.0
MIN_SPAN_SHARE = 0.15
# ... and on the piece's median column the scan lacks at least three quarters of the mirrored shell (a column's
# own rule, ``SPAN_MISSING``): a hole's columns lack it all over its opening (the sweep's cuts: 0.88-1.0, bevelled
# and ball-shaped rims included), a piece of a real head's own asymmetry that spans the shell along one edge only
# lacks none of it on most columns (0.0), the gantry-tilt head's skull base joined to a low cut 0.6-0.65 (issue 42:
# until then half was enough, and those pieces were kept beside the hole's)
MIN_SPAN_MISSING = 0.75
# a piece joined to another through a thin neck (narrower than a ball of this many shells' radius) is cut apart
# there, and each part is held to the median column's bar on its own: a part that is not a hole through the shell
# (the skull's own asymmetry joined to a cut) is left out, the hole's part kept (issue 42)
NECK_SHELLS = 0.25
MIN_CORE_VOXELS = 4
# the core's allowance for the grid's staircase (issue 42): the shell's thickness ``t`` is read as twice a voxel
# centre's distance to the nearest voxel outside the shell (the largest within reach) and the core's distance to
# the bone is voxel centre to voxel centre, so on a coarse grid ``t`` reads up to a voxel's width (along the shell's
# normal) over the shell's own, and a hole about twice the shell wide has no core (headsq's 20 mm cuts at 3.2 mm:
# the shell reads 8.8-14.3 mm, their openings 7.5-11.5 mm). A voxel of the mirrored shell that the scan lacks is a
# core with that width less (never nearer the bone than two widths: a shell one voxel thick reads two, and a sliver
# a voxel thick is no hole) where the shell there is a plate with nothing behind it: along the mirrored shell's
# normal, within PLATE_SHELLS of its thickness either way, neither the scan's bone nor, past the shell's own run,
# the mirror's (the vault between the brain and the scalp). The layered bone of the face and the skull base (air
# cells, sinuses, septa), where the two sides differ by holes that size, keeps the strict rule (headsq's mastoid and
# nasal pieces: with one shell they became templates of the intact scan). Used only for pieces that the strict
# cores do not make (``_plate_pieces``): a hole the strict rule finds keeps its template.
PLATE_SHELLS = 2.0
MIN_DEFECT_WIDTH_MM = 15.0  # the smallest defect reported: a plug this wide through the shell
MIN_DEFECT_SKULL_SHARE = 0.001  # ... and at least this share of the skull's volume
# voxel classes of the kernels' ``code``
BONE, SKULL, MIRROR = 1, 2, 4


def min_defect_volume(shell_mm: float, skull_mm3: float) -> float:
    """The default smallest defect (mm^3): a plug ``MIN_DEFECT_WIDTH_MM`` wide through a shell ``shell_mm`` thick,
    and at least ``MIN_DEFECT_SKULL_SHARE`` of the skull."""
    plug = math.pi * (MIN_DEFECT_WIDTH_MM / 2) ** 2 * shell_mm
    return max(plug, MIN_DEFECT_SKULL_SHARE * skull_mm3)


@dataclass
class Piece:
    """One candidate piece of the defect and the verdict on it (``local_*``: the plane of the bone around it)."""

    label: int
    voxels: int
    volume_mm3: float
    core_mm3: float
    anti_mm3: float = 0.0
    plate: bool = False  # its cores came with the grid's allowance (``PLATE_SHELLS``): a hole the strict cores miss
    side_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # min, median, max distance to the plane (+: left)
    centroid_lps_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    local_normal: tuple[float, float, float] | None = None
    local_offset_mm: float | None = None
    local_residual_mm: float | None = None
    local_turn_deg: float | None = None
    local_move_mm: float | None = None
    local_used: bool = False
    rim: Rim | None = None
    span: Span | None = None
    across: Across | None = None  # how far the hole goes on past the plane (``past_plane``), where measured
    fit: float | None = None
    shell_mm: float | None = None  # the healthy shell's local thickness over the piece (median)
    bridged_mm3: float = 0.0  # added across rim gaps (``_close_rim``)
    cut_mm3: float = 0.0  # parts joined through a thin neck that are not a hole through the shell (``_cut_necks``)
    kept: bool = False
    reason: str = ""
    index: npt.NDArray[np.int64] | None = field(default=None, repr=False)  # voxels (z, y, x) in the region's crop

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "volume_mm3": round(self.volume_mm3, 2),
            "core_mm3": round(self.core_mm3, 2),
            "core_with_grid_allowance": self.plate,
            "moved_bone_mm3": round(self.anti_mm3, 2),
            "side": "left" if self.side_mm[1] > 0 else "right",
            "plane_distance_mm": {"min": round(self.side_mm[0], 2), "median": round(self.side_mm[1], 2),
                                  "max": round(self.side_mm[2], 2)},
            "centroid_lps_mm": [round(v, 2) for v in self.centroid_lps_mm],
            "kept": self.kept,
            "reason": self.reason,
        }  # fmt: skip
        if self.local_turn_deg is not None:
            out["local_plane"] = {
                "used": self.local_used,
                "turn_deg": round(self.local_turn_deg, 3),
                "moves_mirror_mm": None if self.local_move_mm is None else round(self.local_move_mm, 3),
                "residual_mm": None if self.local_residual_mm is None else round(self.local_residual_mm, 4),
            }
        if self.fit is not None:
            out["mirror_fit_iou"] = round(self.fit, 4)
        if self.rim is not None:
            out["rim"] = self.rim.to_dict()
        if self.span is not None:
            out["spans_shell"] = self.span.to_dict()
        if self.across is not None:
            out["midline"] = self.across.to_dict()
        if self.bridged_mm3:
            out["rim_gap_bridged_mm3"] = round(self.bridged_mm3, 2)
        if self.cut_mm3:
            out["cut_at_necks_mm3"] = round(self.cut_mm3, 2)
        return out


@dataclass
class Region:
    """The defect's voxels on a crop of the scan (``lo``: the crop's first voxel in the whole grid) and what the
    rules saw. ``mask``: the template's voxels; ``mirrored``: the mirrored scan (across each kept piece's own
    plane around it); ``data``: the scan (float32)."""

    lo: npt.NDArray[np.int64]
    mask: BoolArray
    data: npt.NDArray[np.float32]
    mirrored: npt.NDArray[np.float32]
    bone: BoolArray
    level: float
    tissue: float
    mid: float
    shell_mm: float
    skull_mm3: float
    min_volume_mm3: float
    pieces: list[Piece] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def kept(self) -> list[Piece]:
        return [p for p in self.pieces if p.kept]


@dataclass
class _Rules:
    """The voxel rules' output on one crop (host arrays)."""

    lo: npt.NDArray[np.int64]
    grown: BoolArray
    core: npt.NDArray[np.uint8]  # 1: core, 2: anti-core, 3: core with the grid's allowance (``PLATE_SHELLS``)
    mirrored: npt.NDArray[np.float32]
    thick: npt.NDArray[np.float32] | None  # the healthy shell's thickness where asked for (``_rules``' ``thick``)
    plate_grown: BoolArray | None = None  # with ``plate="both"``: the region grown from the cores with the allowance

    def with_plate(self) -> _Rules:
        """The rules' output grown from the cores with the grid's allowance (``plate="both"``'s second answer)."""
        assert self.plate_grown is not None
        return _Rules(self.lo, self.plate_grown, self.core, self.mirrored, self.thick)


def _mirror_box(grid: Grid, lo: Any, hi: Any, normal: Any, offset: float, margin: Any) -> tuple[Any, Any]:
    """The box [lo, hi) joined with its mirror image's, widened by ``margin`` voxels, within the grid."""
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    mirrored = reflect(grid.xyz(corners), np.asarray(normal), offset)
    m_idx = mirrored[:, ::-1] / np.asarray(grid.spacing_zyx)
    a = np.minimum(np.asarray(lo), np.floor(m_idx.min(axis=0)).astype(np.int64)) - margin
    b = np.maximum(np.asarray(hi), np.ceil(m_idx.max(axis=0)).astype(np.int64) + 1) + margin
    return np.maximum(a, 0), np.minimum(b, grid.shape)


@dataclass
class _Source:
    """The crop the mirror images are sampled from, on the device: the scan, the skull and the skull's inner
    distances (``half``), its first voxel ``lo`` in the whole grid."""

    data: Any
    skull: Any
    half: Any
    lo: npt.NDArray[np.int64]
    outside: float
    box: Any = None  # the kernels' ``Box`` of the crop


def _rules(
    data: npt.NDArray[np.float32],
    skull: BoolArray,
    bone: BoolArray,
    lo: npt.NDArray[np.int64],
    source: _Source,
    mirror: tuple[FloatArray, FloatArray],
    grid: Grid,
    level: float,
    mid: float,
    be: Backend,
    on_device: tuple[Any, Any, Any] | None = None,
    want_thick: bool = False,
    plate: str = "none",
) -> _Rules:
    """Mirror, shell rule and growth on one box of the scan (the kernels, on the backend ``be``), mirror images
    sampled from ``source``; results on the host. ``on_device``: the box's scan, skull and distance to the bone when
    already there (flat device arrays); ``want_thick``: the shell's thickness comes back too. ``plate``: the cores
    with the grid's allowance (``_plate_launch``, marked 3 in ``core``): "none", "only" (the region grown from the
    strict cores and them) or "both" (the strict region, and that one as ``plate_grown``)."""
    from engine.defect.kernel_specs import CORE, GROW, MIRROR_MAP
    from engine.defect.kernel_specs import MIRROR as MIRROR_KERNEL
    from engine.defect.ops import bits, distance, select, upload_mask

    sp = grid.spacing_zyx
    sp_arr = np.asarray(sp)
    rad = np.ceil(THICKNESS_REACH_MM / sp_arr).astype(np.int64)
    shape = tuple(int(s) for s in data.shape)
    n = int(np.prod(shape))
    if on_device is None:
        d_data: Any = be.from_host(np.ascontiguousarray(data, dtype=np.float32).reshape(-1))
        d_skull: Any = upload_mask(be, skull)
        to_bone = distance(be, upload_mask(be, bone), shape, sp)
    else:
        d_data, d_skull, to_bone = on_device
    mirrored = be.empty(n, np.float32)
    code = be.empty(n, np.uint8)
    thick = be.empty(n, np.float32)
    box = _box(be, shape, lo, sp)
    a, b = (np.asarray(v, dtype=np.float64) for v in mirror)
    m = be.struct(MIRROR_MAP, **{f"a{i}{j}": float(a[i, j]) for i in range(3) for j in range(3)},
                  **{f"b{i}": float(b[i]) for i in range(3)})  # fmt: skip
    be.launch(
        MIRROR_KERNEL,
        shape,
        [d_data, d_skull, box, source.data, source.skull, source.half, source.box, m, float(level), float(mid),
         source.outside, *(int(r) for r in rad), THICKNESS_REACH_MM, mirrored, code, thick],
    )  # fmt: skip
    to_mirror = distance(be, bits(be, code, MIRROR), shape, sp)
    core = be.empty(n, np.uint8)
    be.launch(CORE, n, [code, thick, to_bone, to_mirror, core])

    def host(arr: Any) -> Any:
        return be.to_host(arr).reshape(shape)

    def grow(cores: Any) -> Any:
        to_core = distance(be, select(be, cores, 1), shape, sp)
        out = be.empty(n, np.uint8)
        be.launch(GROW, shape, [d_data, mirrored, code, thick, to_core, box, float(level), float(sp_arr.max()), out])
        return out

    if plate == "none":
        grown = grow(core)
        # sync point: only what the host reads comes back
        return _Rules(lo, host(grown).astype(bool), host(core), host(mirrored), host(thick) if want_thick else None)
    marked, with_plate = _plate_launch(be, shape, box, d_data, mirrored, code, thick, to_bone, core, level)
    core_h = host(marked)  # sync point: the cores, 3 where the grid's allowance adds one
    added = bool((core_h == 3).any())
    strict = host(grow(core)).astype(bool) if plate == "both" or not added else None
    # no core added: the region grown from them is the strict one (one growth)
    grown_plate = host(grow(with_plate)).astype(bool) if added else strict
    assert grown_plate is not None
    t_out, mirrored_h = host(thick) if want_thick else None, host(mirrored)
    if plate == "only":
        return _Rules(lo, grown_plate, core_h, mirrored_h, t_out)
    assert strict is not None
    return _Rules(lo, strict, core_h, mirrored_h, t_out, plate_grown=grown_plate)


def _plate_launch(
    be: Backend,
    shape: tuple[int, ...],
    box: Any,
    d_data: Any,
    mirrored: Any,
    code: Any,
    thick: Any,
    to_bone: Any,
    core: Any,
    level: float,
) -> tuple[Any, Any]:
    """The cores with the grid's allowance (``PLATE_SHELLS``; the ``PLATE`` kernel, on the device where the voxel
    rules' flat arrays are): ``core`` with 3 where the allowance adds one, and 1 at every core, strict or added (what
    the growth starts from)."""
    from engine.defect.kernel_specs import PLATE

    n = int(np.prod(shape))
    marked, cores = be.empty(n, np.uint8), be.empty(n, np.uint8)
    be.launch(PLATE, shape, [d_data, mirrored, code, thick, to_bone, core, box, float(level), PLATE_SHELLS, marked,
                             cores])  # fmt: skip
    return marked, cores


def _plate_cores(
    code: npt.NDArray[np.uint8],
    thick: npt.NDArray[np.float32],
    to_bone: npt.NDArray[np.float32],
    core: npt.NDArray[np.uint8],
    mirrored: npt.NDArray[np.float32],
    data: npt.NDArray[np.float32],
    sp: FloatArray,
    level: float,
    device: Any = "cpu",
) -> npt.NDArray[np.int64]:
    """The cores with the grid's allowance (``PLATE_SHELLS``) for host arrays of one box, found on ``device`` (a
    ``Backend`` or a device spec; ``_plate_launch``), as indices (z, y, x) in the box: voxels of the mirrored skull
    outside the bone whose sample is absent bone, that are no core, with no bone of the scan within the shell's
    thickness less the voxel's width along the mirrored shell's normal (the mirrored field's unit gradient, Sobel
    3x3x3 in mm, as the growth's; the width capped at the largest voxel side), nor within two such widths, and along
    that normal, within ``PLATE_SHELLS`` shells either way (steps of half the smallest voxel side, samples
    trilinear), no bone of the scan and, once the column has left the mirrored shell's run it starts in, no mirrored
    bone."""
    from engine.backend.select import get_backend

    be = get_backend(device)
    shape = tuple(int(s) for s in code.shape)

    def up(a: Any, dtype: Any) -> Any:
        return be.from_host(np.ascontiguousarray(a, dtype=dtype).reshape(-1))

    box = _box(be, shape, np.zeros(3, np.int64), tuple(float(v) for v in sp))  # type: ignore[arg-type]
    marked, _ = _plate_launch(be, shape, box, up(data, np.float32), up(mirrored, np.float32), up(code, np.uint8),
                              up(thick, np.float32), up(to_bone, np.float32), up(core, np.uint8), level)  # fmt: skip
    return np.argwhere(be.to_host(marked).reshape(shape) == 3)


def _box(be: Backend, shape: tuple[int, ...], lo: Any, sp: tuple[float, float, float]) -> Any:
    """The kernels' ``Box`` of a crop: its shape, first voxel ``lo`` and the grid's spacing."""
    from engine.defect.kernel_specs import BOX

    return be.struct(BOX, nz=shape[0], ny=shape[1], nx=shape[2], lz=int(lo[0]), ly=int(lo[1]), lx=int(lo[2]),
                     sz=float(sp[0]), sy=float(sp[1]), sx=float(sp[2]))  # fmt: skip


def find_region(
    volume_data: npt.NDArray[Any],
    level: float,
    plane: SymmetryPlane,
    grid: Grid,
    bone: BoolArray,
    skull: BoolArray,
    params: DefectParams,
    device: Any,
) -> Region:
    """The defect region (see the module) on ``device`` (a ``Backend``, a Warp device or a device spec). Raises
    ``NoDefectError`` or ``MidlineDefectError``."""
    from engine.backend.select import get_backend
    from engine.defect.kernel_specs import RIDGE
    from engine.defect.ops import distance, upload_mask

    be = get_backend(device)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sp_arr = np.asarray(grid.spacing_zyx)
    rad = np.ceil(THICKNESS_REACH_MM / sp_arr).astype(np.int64)
    s_lo, s_hi = bounding_box(skull)
    n_g, d_g = np.asarray(plane.normal_grid), float(plane.offset_grid_mm)
    lo, hi = _mirror_box(grid, s_lo, s_hi, n_g, d_g, rad + 2)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    data = np.ascontiguousarray(volume_data[box], dtype=np.float32)
    bone_c = np.ascontiguousarray(bone[box])
    skull_c = np.ascontiguousarray(skull[box])
    smin = float(sp_arr.min())
    shape = tuple(int(s) for s in data.shape)
    d_data: Any = be.from_host(data.reshape(-1))
    d_skull: Any = upload_mask(be, skull_c)
    half = distance(be, d_skull, shape, grid.spacing_zyx, inside=True)
    to_bone = distance(be, upload_mask(be, bone_c), shape, grid.spacing_zyx)
    ridge = be.empty(len(d_data), np.uint8)
    be.launch(RIDGE, shape, [half, *shape, ridge])
    to_bone_h = be.to_host(to_bone).reshape(shape)  # sync point: the tissue around the bone and the shell's thickness
    ridge_h = be.to_host(ridge).reshape(shape).astype(bool) & skull_c
    half_at_ridge = be.to_host(half).reshape(shape)[ridge_h]
    band = (to_bone_h > 1.5 * smin) & (to_bone_h <= 1.5 * smin + 2.0)
    tissue = float(np.median(data[band])) if band.any() else float(data.min())
    mid = tissue + 0.5 * (level - tissue) if tissue < level else float(level)
    shell_mm = float(2.0 * np.median(half_at_ridge)) if len(half_at_ridge) else float(sp_arr.max())
    source = _Source(d_data, d_skull, half, lo, float(data.min()), _box(be, shape, lo, grid.spacing_zyx))
    rules = _rules(data, skull_c, bone_c, lo, source, reflection(n_g, d_g), grid, level, mid, be,
                   on_device=(d_data, d_skull, to_bone), plate="both")  # fmt: skip
    seconds["global_rules"] = time.perf_counter() - t0

    skull_mm3 = float(skull.sum()) * grid.voxel_mm3
    v_min = params.min_volume_mm3 if params.min_volume_mm3 is not None else min_defect_volume(shell_mm, skull_mm3)
    region = Region(lo, np.zeros(data.shape, dtype=bool), data, rules.mirrored, bone_c, float(level), tissue,
                    mid, shell_mm, skull_mm3, float(v_min), seconds=seconds)  # fmt: skip
    t1 = time.perf_counter()
    min_core = MIN_CORE_VOXELS * grid.voxel_mm3
    candidates = _plate_pieces(_pieces_of(rules, grid, region, n_g, d_g), rules, grid, region, n_g, d_g, min_core)
    pieces: list[Piece] = []
    # every piece that could be a defect is mirrored locally (until issue 42 only the six with the most core were:
    # a 20 mm cut, whose core is small, lost its turn to the skull base's asymmetries and was reported "smaller than
    # the smallest defect" without being looked at)
    worth = [p for p in candidates if p.core_mm3 >= min_core and p.volume_mm3 >= 0.5 * region.min_volume_mm3]
    # the strict cores' pieces take their turns first; the allowance's pieces are mirrored first, so where two
    # local mirror images overlap a strict piece's is the one kept (its template as without the allowance)
    strict = sorted((p for p in worth if not p.plate), key=lambda p: -p.volume_mm3)[:MAX_LOCAL_PIECES]
    plate = sorted((p for p in worth if p.plate), key=lambda p: -p.volume_mm3)[: MAX_LOCAL_PIECES - len(strict)]
    worth = plate + strict
    for p in candidates:
        if p in worth:
            continue
        if p.core_mm3 < min_core:
            p.reason = _no_core(region, grid)
        elif p.volume_mm3 < 0.5 * region.min_volume_mm3:
            p.reason = f"smaller than the smallest defect ({region.min_volume_mm3:.0f} mm3)"
        else:
            p.reason = f"not looked at: {MAX_LOCAL_PIECES} larger candidates were"
        pieces.append(p)
    pieces.extend(_mirror_all(worth, region, grid, skull, bone, volume_data, n_g, d_g, source, be))
    seconds["local_rules"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    pieces.sort(key=lambda p: -p.volume_mm3)
    region.pieces = pieces
    try:
        _judge(region, grid, params)
    except (NoDefectError, MidlineDefectError) as exc:
        # what a caller measuring the refusal needs (the sweep: which candidate held its cut, and why it went):
        # each candidate's verdict, volume and voxels (whole grid), the skull's shell and the plane (grid mm)
        found = [(p.reason, p.volume_mm3, p.index + region.lo) for p in region.pieces if p.index is not None]
        setattr(exc, "candidates", found)  # noqa: B010 (attributes of this one exception, not of its class)
        setattr(exc, "shell_mm", region.shell_mm)  # noqa: B010
        setattr(exc, "plane_grid", (np.asarray(n_g, dtype=np.float64), d_g))  # noqa: B010
        raise
    seconds["judge"] = time.perf_counter() - t2
    return region


def _plate_pieces(
    strict: list[Piece], rules: _Rules, grid: Grid, region: Region, normal: Any, offset: float, min_core: float
) -> list[Piece]:
    """The candidates: the strict cores' pieces, and the pieces grown from the cores with the grid's allowance
    (``PLATE_SHELLS``) that meet none of those holding at least ``min_core`` of core (a hole the strict rule finds is
    its piece, as before, and no piece of the allowance joins it); such a piece takes the place of the strict
    pieces with too little core that it meets."""
    if rules.plate_grown is None:
        return strict
    firm = np.zeros(rules.grown.shape, dtype=bool)
    shift = region.lo - rules.lo
    for p in strict:
        if p.core_mm3 >= min_core and p.index is not None:
            firm[tuple((p.index + shift).T)] = True
    extra = _pieces_of(rules.with_plate(), grid, region, normal, offset, plate=True, skip=firm)
    if not extra:
        return strict
    covered = np.zeros(rules.grown.shape, dtype=bool)
    for q in extra:
        q.plate = True
        covered[tuple((q.index + shift).T)] = True  # type: ignore[operator]
    kept = [p for p in strict
            if p.core_mm3 >= min_core or p.index is None or not covered[tuple((p.index + shift).T)].any()]  # fmt: skip
    return kept + extra


def _pieces_of(
    rules: _Rules,
    grid: Grid,
    region: Region,
    normal: Any,
    offset: float,
    plate: bool = False,
    skip: BoolArray | None = None,
) -> list[Piece]:
    """The 26-connected pieces of a rules pass that hold a core, with their voxels (in the region's crop); with
    ``plate``, the cores with the grid's allowance count too; none that meets ``skip`` (a mask of the rules' crop)."""
    # the grown voxels' pieces (``label_voxels``: scipy's pieces and numbers, from the few voxels themselves)
    shape = rules.grown.shape
    flat = np.flatnonzero(rules.grown)
    if not len(flat):
        return []
    labels, nl = label_voxels(flat, shape)
    c_at = rules.core.reshape(-1)[flat]
    cores = np.bincount(labels[(c_at == 1) | (c_at == 3)] if plate else labels[c_at == 1], minlength=nl + 1)
    cores[0] = 0
    if skip is not None:  # left out before their voxels are gathered and placed
        cores[labels[skip.reshape(-1)[flat]]] = 0
    with_core = np.flatnonzero(cores)  # the labels holding a core, ascending
    if not len(with_core):
        return []
    vox = grid.voxel_mm3
    in_piece = (cores > 0)[labels]  # a look-up per voxel, not a search
    idx = np.stack(np.unravel_index(flat[in_piece], shape), axis=1)
    lab = labels[in_piece]
    order = np.argsort(lab, kind="stable")
    starts = np.searchsorted(lab[order], with_core)
    ends = np.searchsorted(lab[order], with_core, side="right")
    shift = rules.lo - region.lo
    out = []
    for k, a, b in zip(with_core, starts, ends, strict=True):
        sel = idx[order[a:b]]
        out.append(Piece(label=int(k), voxels=len(sel), volume_mm3=len(sel) * vox, core_mm3=float(cores[k]) * vox,
                         index=sel + shift))  # fmt: skip
    for p in out:
        _place(p, grid, region, normal, offset)
    return out


def _place(p: Piece, grid: Grid, region: Region, normal: Any, offset: float) -> None:
    """The piece's side of the plane and centroid."""
    assert p.index is not None
    xyz = grid.xyz(p.index + region.lo)
    s = xyz @ np.asarray(normal) - offset
    p.side_mm = (float(s.min()), float(np.median(s)), float(s.max()))
    p.centroid_lps_mm = tuple(float(v) for v in grid.to_patient(xyz.mean(axis=0)))  # type: ignore[assignment]


def _threads(count: int) -> int:
    """Threads for ``count`` pieces' host work (scipy's filters, labels and distance transforms release the GIL)."""
    from engine.io.parallel import decode_threads

    return max(1, min(count, decode_threads()))


def _mirror_all(
    worth: list[Piece],
    region: Region,
    grid: Grid,
    skull: BoolArray,
    bone: BoolArray,
    volume_data: npt.NDArray[Any],
    n_g: FloatArray,
    d_g: float,
    source: _Source,
    device: Any,
) -> list[Piece]:
    """``worth`` mirrored locally (``_mirror_locally``), in their order: the local planes and the measures on the
    host's threads, piece by piece side by side; the rules on the device one piece after the other; the local
    mirror images written into ``region.mirrored`` in the pieces' order (a later piece's where two overlap), as
    the serial loop did."""
    from engine.io.parallel import ordered_map

    threads = _threads(len(worth))
    t0 = time.perf_counter()
    planes = list(ordered_map(lambda p: _local_plane(p, region, grid, volume_data, n_g, d_g), worth, threads))
    t1 = time.perf_counter()
    ruled = [_local_rules(p, lp, region, grid, skull, bone, source, device)
             for p, lp in zip(worth, planes, strict=True)]  # fmt: skip
    t2 = time.perf_counter()
    done = list(ordered_map(lambda a: _measure_local(*a, region, grid, bone), zip(worth, planes, ruled, strict=True),
                            threads))  # fmt: skip
    region.seconds.update(local_planes=t1 - t0, local_device=t2 - t1, local_measures=time.perf_counter() - t2)
    out = []
    for local, patch in done:
        if patch is not None:
            dst, values = patch
            region.mirrored[dst] = values
        out.append(local)
    return out


@dataclass
class _LocalPlane:
    """A piece's own mirror plane (``ring_plane``; the global one where the local would move it too far)."""

    normal: FloatArray
    offset: float
    residual: float
    turn_deg: float
    moved_mm: float
    used: bool


def _local_plane(
    p: Piece, region: Region, grid: Grid, volume_data: npt.NDArray[Any], n_g: FloatArray, d_g: float
) -> _LocalPlane:
    """The plane of the bone around a piece (see the module)."""
    assert p.index is not None
    sp_arr = np.asarray(grid.spacing_zyx)
    g_idx = p.index + region.lo
    centre = grid.xyz(g_idx).mean(axis=0)
    n_l, d_l, res = ring_plane(volume_data, grid, n_g, d_g, _ring(g_idx, grid, RING_MM), region.tissue, region.level)
    # how far the local mirror moves the piece's mirror image: a local plane corrects a millimetre's misfit; one
    # that moves it by more has matched something else (the hole itself, when it crosses the midline)
    moved = float(np.linalg.norm(reflect(centre[None, :], n_l, d_l)[0] - reflect(centre[None, :], n_g, d_g)[0]))
    local_ok = moved <= max(MAX_LOCAL_MOVE_MM, 2.0 * float(sp_arr.max()))
    if not local_ok:
        n_l, d_l, res = np.asarray(n_g), float(d_g), float("nan")
    turn = float(np.degrees(np.arccos(min(1.0, abs(float(n_l @ n_g))))))
    return _LocalPlane(n_l, d_l, res, turn, moved, local_ok)


def _local_box(p: Piece, region: Region, grid: Grid) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The box [lo, hi) (whole grid) the rules rerun on around a piece, within the region's crop."""
    assert p.index is not None
    sp_arr = np.asarray(grid.spacing_zyx)
    g_idx = p.index + region.lo
    rad = np.ceil(THICKNESS_REACH_MM / sp_arr).astype(np.int64)
    margin = rad + np.ceil((2 * region.shell_mm + 2 * float(sp_arr.max())) / sp_arr).astype(np.int64) + 2
    r_hi = region.lo + np.asarray(region.data.shape)
    return np.maximum(g_idx.min(axis=0) - margin, region.lo), np.minimum(g_idx.max(axis=0) + 1 + margin, r_hi)


def _local_rules(
    p: Piece, lp: _LocalPlane, region: Region, grid: Grid, skull: BoolArray, bone: BoolArray, source: _Source, be: Any
) -> _Rules:
    """The rules rerun on the box around a piece, mirrored across its own plane (on the device)."""
    lo, hi = _local_box(p, region, grid)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    inner = tuple(slice(int(a - r), int(b - r)) for a, b, r in zip(lo, hi, region.lo, strict=True))
    data = np.ascontiguousarray(region.data[inner])
    return _rules(data, np.ascontiguousarray(skull[box]), np.ascontiguousarray(bone[box]), lo, source,
                  reflection(lp.normal, lp.offset), grid, region.level, region.mid, be, want_thick=True,
                  plate="only" if p.plate else "none")  # fmt: skip


def _measure_local(
    p: Piece, lp: _LocalPlane, rules: _Rules, region: Region, grid: Grid, bone: BoolArray
) -> tuple[Piece, tuple[Any, Any] | None]:
    """The piece again, from the rules rerun across its own plane, measured; and its local mirror image (where in
    ``region.mirrored`` and the values) that replaces the global one around it (the implant's field). Reads
    ``region``, writes nothing of it (the caller writes the mirror images, in order)."""
    from scipy.spatial import cKDTree

    assert p.index is not None
    sp_arr = np.asarray(grid.spacing_zyx)
    g_idx = p.index + region.lo
    n_l, d_l = lp.normal, lp.offset
    lo, hi = _local_box(p, region, grid)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    inner = tuple(slice(int(a - r), int(b - r)) for a, b, r in zip(lo, hi, region.lo, strict=True))
    data = region.data[inner]
    local = Piece(label=p.label, voxels=0, volume_mm3=0.0, core_mm3=0.0, plate=p.plate)
    local.local_normal = tuple(float(v) for v in n_l)  # type: ignore[assignment]
    local.local_offset_mm = d_l
    local.local_residual_mm = None if not np.isfinite(lp.residual) else lp.residual
    local.local_turn_deg = lp.turn_deg
    local.local_move_mm = lp.moved_mm
    local.local_used = lp.used
    # the local pieces that overlap the global piece
    region_probe = Region(lo, rules.grown, data, rules.mirrored, bone[box], region.level, region.tissue, region.mid,
                          region.shell_mm, region.skull_mm3, region.min_volume_mm3)  # fmt: skip
    parts = _pieces_of(rules, grid, region_probe, n_l, d_l, plate=p.plate)
    old = np.zeros(data.shape, dtype=bool)
    inside = np.all((g_idx >= lo) & (g_idx < hi), axis=1)
    old[tuple((g_idx[inside] - lo).T)] = True
    mine = [q for q in parts if q.index is not None and old[tuple(q.index.T)].any()]
    local.side_mm, local.centroid_lps_mm = p.side_mm, p.centroid_lps_mm
    if not mine:
        local.reason = "asymmetry: gone when mirrored across the plane of the bone around it"
        return local, None
    idx = np.concatenate([q.index for q in mine if q.index is not None]) + lo  # whole grid
    local.voxels = len(idx)
    local.volume_mm3 = len(idx) * grid.voxel_mm3
    local.core_mm3 = sum(q.core_mm3 for q in mine)
    local.index = idx - region.lo
    assert rules.thick is not None
    local.shell_mm = float(np.median(rules.thick[tuple((idx - lo).T)]))
    _place(local, grid, region, n_l, d_l)
    # moved bone beside it: anti-cores near the piece, its own mirror image's surroundings left out
    reach = 2.0 * region.shell_mm + float(sp_arr.max())
    anti_idx = np.argwhere(rules.core == 2) + lo
    if len(anti_idx):
        anti_xyz = grid.xyz(anti_idx)
        p_xyz = grid.xyz(idx)
        near = np.isfinite(cKDTree(p_xyz).query(anti_xyz, distance_upper_bound=reach, workers=1)[0])
        mirror_near = np.isfinite(
            cKDTree(reflect(p_xyz, n_l, d_l)).query(anti_xyz, distance_upper_bound=reach, workers=1)[0]
        )
        local.anti_mm3 = float(np.count_nonzero(near & ~mirror_near)) * grid.voxel_mm3
    # the local mirror image replaces the global one around the piece (the implant's field)
    r_hi = region.lo + np.asarray(region.data.shape)
    a, b = np.maximum(lo, region.lo), np.minimum(hi, r_hi)
    dst = tuple(slice(int(u - r), int(v - r)) for u, v, r in zip(a, b, region.lo, strict=True))
    src = tuple(slice(int(u - w), int(v - w)) for u, v, w in zip(a, b, lo, strict=True))
    return local, (dst, rules.mirrored[src])


def _ring(index: npt.NDArray[np.int64], grid: Grid, width_mm: float) -> npt.NDArray[np.int64]:
    """Grid indices of the voxels within ``width_mm`` of a piece (whole-grid ``index``), the piece and the voxels
    touching it left out."""
    from scipy import ndimage as ndi

    sp = np.asarray(grid.spacing_zyx)
    margin = np.ceil(width_mm / sp).astype(np.int64) + 1
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, grid.shape)
    piece = np.zeros(tuple(int(b - a) for a, b in zip(lo, hi, strict=True)), dtype=bool)
    piece[tuple((index - lo).T)] = True
    near = touching(piece)
    ring = (ndi.distance_transform_edt(~piece, sampling=sp) <= width_mm) & ~near
    return np.argwhere(ring) + lo


def _judge(region: Region, grid: Grid, params: DefectParams) -> None:
    """Keep the pieces that are defects; raise when the one that would be kept crosses the midline. Each piece is
    judged on its own (``_passes_first``, ``_measures``, ``_judge_one``), side by side on the host's threads."""
    from engine.io.parallel import ordered_map

    point = None
    if params.point_lps_mm is not None:
        point = grid.from_patient(np.asarray(params.point_lps_mm))
    _merge_overlapping(region, grid)
    live = [p for p in region.pieces if not p.reason and _passes_first(p, region, grid, params, point)]
    # every piece's measures at once, each on a thread of its own (the span too where the rules may stop before
    # they need it: the measures are independent, and the host has the cores), then each piece's verdict
    mirror_bone = region.mirrored >= region.level
    tasks = [(i, name, fn) for i, p in enumerate(live) for name, fn in _measures(p, region, mirror_bone, grid).items()]
    results = ordered_map(lambda t: t[2](), tasks, _threads(len(tasks)))
    measured: list[dict[str, Any]] = [{} for _ in live]
    for (i, name, _), value in zip(tasks, results, strict=True):
        measured[i][name] = value
    verdicts = zip(live, measured, strict=True)
    across = ordered_map(lambda pm: _judge_one(pm[0], pm[1], region, grid), verdicts, _threads(len(live)))
    crossing = [p for p, c in zip(live, across, strict=True) if c]
    if point is not None:  # the one piece nearest the hint point
        kept = [p for p in region.pieces if p.kept]
        if len(kept) > 1:
            nearest = min(
                kept, key=lambda p: float(np.linalg.norm(grid.from_patient(np.asarray(p.centroid_lps_mm)) - point))
            )
            for p in kept:
                if p is not nearest:
                    p.kept, p.reason = False, "not the piece nearest the hint point"
    kept = region.kept
    if crossing and (not kept or max(c.volume_mm3 for c in crossing) >= max(p.volume_mm3 for p in kept)):
        c = max(crossing, key=lambda p: p.volume_mm3)
        raise MidlineDefectError(
            f"the defect ({c.volume_mm3:,.0f} mm3 found by mirroring, {_where(c)}) {c.reason}: the mirror image "
            "lacks that bone too, so mirroring cannot make its template"
        )
    if not kept:
        raise NoDefectError(_no_defect_message(region))
    mask = np.zeros(region.data.shape, dtype=bool)
    for p in kept:
        assert p.index is not None
        mask[tuple(p.index.T)] = True
    region.mask = mask


def _passes_first(p: Piece, region: Region, grid: Grid, params: DefectParams, point: Any) -> bool:
    """The rules that need no measure of the rim (moved bone, size, the hints): whether ``p`` passes them (else
    its ``reason`` says why)."""
    if p.anti_mm3 > MAX_ANTI_SHARE * p.core_mm3:
        p.reason = "moved bone: the scan has bone beside it that the mirror lacks (asymmetry, not a hole)"
        return False
    v_min = _min_volume(p, region, params)
    if p.volume_mm3 < v_min and not _wide_opening(p, grid, params):
        p.reason = (
            f"smaller than the smallest defect ({v_min:.0f} mm3: a {MIN_DEFECT_WIDTH_MM:g} mm wide plug through "
            f"the shell there, {p.shell_mm or region.shell_mm:.1f} mm thick)"
        )
        return False
    if params.side is not None and (p.side_mm[1] > 0) != (params.side == "left"):
        p.reason = f"not on the {params.side} side (the hint)"
        return False
    assert p.index is not None and p.local_normal is not None and p.local_offset_mm is not None
    if point is not None:
        xyz = grid.xyz(p.index + region.lo)
        if float(np.min(np.linalg.norm(xyz - point, axis=1))) > params.point_radius_mm:
            p.reason = f"farther than {params.point_radius_mm:g} mm from the hint point"
            return False
    return True


def _wide_opening(p: Piece, grid: Grid, params: DefectParams) -> bool:
    """Whether a piece under the plug's volume is still a defect by its opening (issue 42): its opening, seen along
    its thinnest axis (``opening_width_mm``), is at least ``MIN_DEFECT_WIDTH_MM`` wide. The plug's thickness is
    the healthy shell's as the grid reads it (``Piece.shell_mm``: the largest ball within reach), which over-reads
    a thin shell on coarse slices (the head phantom's vault at 5 mm slices: read 4.0-5.1 mm where the hole's own
    plug is 1.8-2.4 mm thick, so a 20 mm hole's plug weighed less than the smallest defect's); a hole's plug is as
    wide as its opening whatever the grid, and the other rules still judge it. A ``params.min_volume_mm3`` given is
    used as it is."""
    if params.min_volume_mm3 is not None or p.index is None:
        return False
    return opening_width_mm(p.index, grid.spacing_zyx) >= MIN_DEFECT_WIDTH_MM


def _reach(region: Region, grid: Grid) -> float:
    """How far the rim looks for bone (mm)."""
    return max(region.shell_mm, 3.0 * float(max(grid.spacing_zyx)))


def _measures(p: Piece, region: Region, mirror_bone: BoolArray, grid: Grid) -> dict[str, Any]:
    """The piece's measures that ``_judge_one`` rules on, as calls: its rim, the mirror's fit around it, how far the
    hole goes on toward the plane and past it (only near it) and whether it spans the shell. Each reads ``region``
    only."""
    assert p.index is not None and p.local_normal is not None and p.local_offset_mm is not None
    index, sp = p.index, np.asarray(grid.spacing_zyx)
    g = index + region.lo
    full = np.asarray(grid.shape)
    border = np.any((g == 0) | (g == full - 1), axis=1)
    shell = p.shell_mm if p.shell_mm else region.shell_mm
    fit_reach = 2.0 * region.shell_mm + float(sp.max())
    out: dict[str, Any] = {
        "rim": lambda: rim_of(index, region.bone, grid.spacing_zyx, border, _reach(region, grid)),
        "fit": lambda: local_fit(index, region.bone, mirror_bone, grid.spacing_zyx, fit_reach),
    }
    near_mm = min(abs(p.side_mm[0]), abs(p.side_mm[2]))
    side = grid.xyz(g) @ np.asarray(p.local_normal) - p.local_offset_mm  # the voxels' distances to the plane
    n_zyx = np.asarray(p.local_normal)[::-1]
    if near_mm <= max(region.shell_mm, float(sp.max())):
        out["toward"] = lambda: open_toward_plane(index, region.bone, region.mirrored, grid.spacing_zyx, side, n_zyx,
                                                  max(MIDLINE_REACH_MM, 3.0 * shell))  # fmt: skip
    if near_mm <= MIDLINE_NEAR_MM:
        out["past"] = lambda: past_plane(
            index,
            region.bone,
            grid.spacing_zyx,
            side,
            n_zyx,
            MIDLINE_REACH_MM,
            0.5 * (shell + float(sp.max())),
            MIN_SPAN_WIDTH_MM,
            2.0 * shell + float(sp.max()),
            MIDLINE_NEAR_MM,
        )
    if not _across(p, grid):

        def span() -> Any:  # measured before the rules know they need it: a failure counts only if they do
            try:
                return spans_shell(index, region.bone, region.mirrored, region.level, grid.spacing_zyx,
                                   1.5 * shell + float(sp.max()))  # fmt: skip
            except Exception as exc:  # raised by _judge_one where the span is needed
                return exc

        out["span"] = span
    return out


def lies_across(nearest_mm: float, farthest_mm: float, grid: Grid) -> bool:
    """Whether bone whose signed distances to the plane run from ``nearest_mm`` to ``farthest_mm`` lies on both
    sides of it by more than a voxel (the largest side): a piece, or a cut (the reviewer's sweep), across the
    midline."""
    big = float(max(grid.spacing_zyx))
    return nearest_mm < -big and farthest_mm > big


def midline_tolerance(across: Across) -> float:
    """How far past the midline plane a hole may go (mm) and keep its template (with a warning):
    ``MIDLINE_PAST_MM``, or a voxel's extent along the way to the plane where that is more (the measure's step)."""
    return max(MIDLINE_PAST_MM, across.voxel_mm)


def midline_warning(p: Piece) -> dict[str, Any] | None:
    """The warning (``{"code": "past_midline", "message": ..., "past_midline_mm": ...}``, as the report's warnings
    are) for a kept piece whose hole goes on past the midline plane by less than the tolerance; None where it stops
    short of the plane or was not measured."""
    if p.across is None or p.across.past_mm <= 0.0:
        return None
    message = (
        f"the hole goes on {p.across.past_mm:.1f} mm past the midline plane (along the shell, over a front "
        f"{p.across.front_mm:.0f} mm wide): the mirror image lacks that bone too, so the template stops about as "
        "far short of the plane; check its edge at the midline"
    )
    return {"code": "past_midline", "message": message, "past_midline_mm": round(p.across.past_mm, 2)}


def _across(p: Piece, grid: Grid) -> bool:
    """Whether the piece lies on both sides of its plane by more than a voxel."""
    return lies_across(p.side_mm[0], p.side_mm[2], grid)


def _judge_one(p: Piece, measured: dict[str, Any], region: Region, grid: Grid) -> bool:
    """One piece judged on its ``measured`` (``_measures``' results): its ``reason``, ``kept``, rim and measures
    set, its voxels filled out to the rim when kept; whether it is a hole that crosses the midline. Reads
    ``region``, writes only ``p``."""
    assert p.index is not None
    sp = np.asarray(grid.spacing_zyx)
    full = np.asarray(grid.shape)
    reach = _reach(region, grid)
    shell = p.shell_mm if p.shell_mm else region.shell_mm
    p.fit = measured["fit"]
    across = _across(p, grid)
    toward = measured.get("toward", 0.0)
    p.rim = dataclasses.replace(measured["rim"], open_toward_plane=toward)
    p.across = measured.get("past")
    if across or toward >= MIN_OPEN_TOWARD_PLANE:
        p.reason = "crosses the midline" if across else "the hole goes on past it toward the midline"
        return True
    span = measured["span"]
    if isinstance(span, Exception):
        raise span
    p.span = span
    if p.span.missing < MIN_SPAN_MISSING:
        p.reason = (
            f"not a hole through the shell: on its median column the scan lacks {p.span.missing:.0%} of the "
            f"mirrored shell (a hole lacks it all; elsewhere the scan has bone across the shell): a "
            "partial-thickness dent or asymmetry"
        )
        return False
    if p.span.area_mm2 < math.pi * (MIN_SPAN_WIDTH_MM / 2) ** 2 or p.span.share < MIN_SPAN_SHARE:
        p.reason = (
            f"not a hole through the shell: the scan lacks the whole mirrored shell over {p.span.area_mm2:.0f} mm2 "
            f"({p.span.share:.0%} of its outline; elsewhere the scan has bone across the shell): a "
            "partial-thickness dent or asymmetry"
        )
        return False
    if p.rim.contact < MIN_CONTACT:
        p.reason = f"its rim meets the bone over {p.rim.contact:.0%} only (not a hole's fill)"
        return False
    _to_rim(p, region, grid, shell, border_of=full, reach=reach)
    if p.rim is not None and p.rim.gap_voxels > CLOSE_GAP_VOXELS:
        _close_rim(p, region, grid, shell, border_of=full, reach=reach)
    _cut_necks(p, region, grid, shell)
    if p.rim is not None and p.fit * p.rim.contact < MIN_CONFIDENCE:
        p.reason = (
            f"low confidence: around it the mirror image matches the scan's bone over {p.fit:.0%} (overlap "
            f"within {2.0 * region.shell_mm + float(sp.max()):.0f} mm) and the template meets the hole's rim over "
            f"{p.rim.contact:.0%} (rim gap {p.rim.gap_voxels:.1f} voxels): {p.fit * p.rim.contact:.2f}, under "
            f"{MIN_CONFIDENCE:g}; the two sides differ there (asymmetry, or a pose or slice thickness the mirror "
            "cannot follow), so the template would not fit the hole"
        )
        return False
    if p.volume_mm3 < region.min_volume_mm3 and p.rim is not None and p.rim.gap_voxels > 1.0:
        # under the skull's smallest defect (a thin vault's plate): kept only when its rim closes on the bone
        p.reason = (
            f"smaller than the smallest defect ({region.min_volume_mm3:.0f} mm3) and its rim does not close on "
            f"the bone (gap {p.rim.gap_voxels:.1f} voxels)"
        )
        return False
    # the hole past the plane is judged on a piece that would be a template: where the rules above refuse a piece
    # (a skull base's asymmetry far off, whose paths along a straight line leave the shell and meet no bone) it is
    # not made a midline defect that overrides the one-sided template kept beside it
    if p.across is not None and p.across.past_mm > midline_tolerance(p.across):
        p.reason = (
            f"the hole goes on {p.across.past_mm:.1f} mm past the midline plane (along the shell from the "
            f"template's edge facing it, over a front {p.across.front_mm:.0f} mm wide; more than the "
            f"{midline_tolerance(p.across):.2g} mm a template may stop short of it)"
        )
        return True
    if p.rim is not None and p.rim.gap_voxels > CLOSE_GAP_VOXELS:  # a would-be template only (see its doc)
        _to_rim_across_slices(p, region, grid, shell, border_of=full, reach=reach)
    if p.rim is not None and p.rim.gap_voxels > MAX_RIM_GAP_VOXELS:
        # filled out to the rim, bridged and filled across slices, and still off the bone: the mirror's bone stops
        # short of the hole's rim, so the template would leave the hole open along that stretch (issue 42)
        p.reason = rim_gap_reason(p.rim)
        return False
    p.kept = True
    p.reason = "defect"
    return False


def rim_gap_reason(rim: Rim) -> str:
    """The reason a piece whose rim stays more than ``MAX_RIM_GAP_VOXELS`` off the bone once filled and bridged
    is not a template."""
    return (
        f"its rim does not close on the bone: once filled out to the rim and bridged, the template's rim lies "
        f"{rim.gap_voxels:.1f} voxels ({rim.gap_mm:.1f} mm) from the hole's bone on average and meets it over "
        f"{rim.contact:.0%} only (at most {MAX_RIM_GAP_VOXELS:g} voxel allowed): the mirror's bone stops short of the "
        "hole's rim there, so the template would leave the hole open along its edge"
    )


def neck_parts(index: npt.NDArray[np.int64], spacing_zyx: Any, radius_mm: float) -> npt.NDArray[np.int64] | None:
    """The parts of a piece (voxels ``index``) joined through necks narrower than a ball of ``radius_mm``: the
    piece opened with that ball (a step along a coarser axis counted as the radius at most, as in ``_close_rim``),
    its 26-connected pieces, and every voxel of the piece given to the nearest of them. Per voxel its part (0, 1,
    ...); None when the piece is one part."""
    from scipy import ndimage as ndi

    sp = np.asarray(spacing_zyx, dtype=np.float64)
    lo = index.min(axis=0) - 1
    local = index - lo
    piece = np.zeros(tuple(int(v) for v in local.max(axis=0) + 2), dtype=bool)
    piece[tuple(local.T)] = True
    step = np.minimum(sp, radius_mm)
    inner = ndi.distance_transform_edt(piece, sampling=step) > radius_mm + 1e-6
    opened = (ndi.distance_transform_edt(~inner, sampling=step) <= radius_mm + 1e-6) & piece
    labels, n = ndi.label(opened, structure=CONNECTIVITY)
    if n <= 1:
        return None
    _, near = ndi.distance_transform_edt(labels == 0, sampling=sp, return_indices=True)
    return labels[tuple(near)][tuple(local.T)].astype(np.int64) - 1


def _cut_necks(p: Piece, region: Region, grid: Grid, shell: float) -> None:
    """The filled piece cut apart at its thin necks (``neck_parts``, a ball ``NECK_SHELLS`` shells wide), and each
    part held to the median column's bar (``MIN_SPAN_MISSING``, its columns measured by ``spans_shell``) on its
    own: the parts that are not a hole through the shell (the skull's own asymmetry, a turned skull base or an
    inner wall, joined to the cut through a rim's few voxels) are left out, and the piece's rim and fit are
    measured again on what is left. A piece none of whose parts passes is left as it is."""
    assert p.index is not None
    if len(p.index) < 8:
        return
    part = neck_parts(p.index, grid.spacing_zyx, NECK_SHELLS * shell)
    if part is None:
        return
    sp = np.asarray(grid.spacing_zyx)
    reach_mm = 1.5 * shell + float(sp.max())
    missing = spans_shell(p.index, region.bone, region.mirrored, region.level, grid.spacing_zyx, reach_mm)
    assert missing.column_missing is not None
    medians = np.array([np.median(missing.column_missing[part == k]) for k in range(int(part.max()) + 1)])
    keep = (medians >= MIN_SPAN_MISSING)[part]
    if keep.all() or not keep.any():
        return
    p.cut_mm3 += float(np.count_nonzero(~keep)) * grid.voxel_mm3
    _take(p, p.index[keep], region, grid, border_of=grid.shape, reach=_reach(region, grid))
    assert p.local_normal is not None and p.local_offset_mm is not None
    _place(p, grid, region, p.local_normal, p.local_offset_mm)
    p.span = spans_shell(p.index, region.bone, region.mirrored, region.level, grid.spacing_zyx, reach_mm)
    p.fit = local_fit(p.index, region.bone, region.mirrored >= region.level, grid.spacing_zyx,
                      2.0 * region.shell_mm + float(sp.max()))  # fmt: skip


def _min_volume(p: Piece, region: Region, params: DefectParams) -> float:
    """The smallest defect where the piece is: a ``MIN_DEFECT_WIDTH_MM`` plug through the healthy shell's local
    thickness there (a thin vault's defect is a thin plate), never more than the skull's (``region.min_volume_mm3``).
    A ``params.min_volume_mm3`` given is used as it is."""
    if params.min_volume_mm3 is not None or not p.shell_mm:
        return region.min_volume_mm3
    return min(region.min_volume_mm3, min_defect_volume(p.shell_mm, region.skull_mm3))


def _merge_overlapping(region: Region, grid: Grid) -> None:
    """Pieces that share voxels are one hole: two candidates of the global pass can meet the same piece when each is
    mirrored locally. The larger takes the other's voxels (the smaller is left out, saying so), so no hole is
    counted twice."""
    taken = np.full(region.data.shape, -1, dtype=np.int32)
    owners_of: list[Piece] = []
    live = [p for p in region.pieces if not p.reason and p.index is not None and len(p.index)]
    # the strict cores' pieces first: a piece of the grid's allowance that meets one is left out, not joined (a
    # hole the strict rule finds keeps its template as without the allowance)
    for p in sorted(live, key=lambda q: (q.plate, -q.volume_mm3)):
        assert p.index is not None
        owners = np.unique(taken[tuple(p.index.T)])
        owners = owners[owners >= 0]
        if not len(owners):
            taken[tuple(p.index.T)] = len(owners_of)
            owners_of.append(p)
            continue
        big = owners_of[int(owners[0])]
        if p.plate and not big.plate:
            p.reason = "the same hole as a candidate of the strict cores (they met when mirrored locally): left out"
            continue
        assert big.index is not None
        big.index = np.unique(np.concatenate([big.index, p.index]), axis=0)
        big.voxels = len(big.index)
        big.volume_mm3 = big.voxels * grid.voxel_mm3
        big.core_mm3 += p.core_mm3
        taken[tuple(p.index.T)] = int(owners[0])
        p.reason = "the same hole as a larger candidate (they met when mirrored locally): joined to it"


def _to_rim(
    p: Piece, region: Region, grid: Grid, shell: float, border_of: Any, reach: float, across_slices: bool = False
) -> None:
    """The kept piece filled out to the hole's rim: the mirrored bone missing from the scan within
    ``min(largest voxel side, half the shell)`` mm of it, connected to it. The rules leave out a band along a
    bevelled or partial-volume rim (bone across the shell within its thickness); the mirror's own bone there fills
    it. Its rim is measured again. ``across_slices`` (where the rim gap is still over a voxel): a step along a
    coarser axis counts as that reach at most, so the mirror's bone in the slice beyond the template's last, which
    the scan lacks, joins it (between thick slices the hole's rim lies a slice past the template: the head
    phantom's 5 mm slices)."""
    from scipy import ndimage as ndi

    assert p.index is not None
    sp = np.asarray(grid.spacing_zyx)
    reach_mm = min(float(sp.max()), 0.5 * shell)
    margin = np.ceil(reach_mm / sp).astype(np.int64) + 1
    lo = np.maximum(p.index.min(axis=0) - margin, 0)
    hi = np.minimum(p.index.max(axis=0) + margin + 1, region.bone.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    piece = np.zeros(tuple(int(b - a) for a, b in zip(lo, hi, strict=True)), dtype=bool)
    piece[tuple((p.index - lo).T)] = True
    step = np.minimum(sp, reach_mm) if across_slices else sp
    near = ndi.distance_transform_edt(~piece, sampling=step) <= reach_mm + (1e-6 if across_slices else 0.0)
    fill = near & (region.mirrored[box] >= region.level) & ~region.bone[box]
    labels, _ = ndi.label(fill | piece, structure=CONNECTIVITY)
    keep = np.isin(labels, np.unique(labels[piece]))
    _take(p, np.argwhere(keep) + lo, region, grid, border_of=border_of, reach=reach)


def _take(p: Piece, index: npt.NDArray[np.int64], region: Region, grid: Grid, border_of: Any, reach: float) -> None:
    """The piece made of ``index`` (voxels of the region's crop) from now on: its size, and its rim measured again
    (the scan's border at ``border_of``, bone looked for within ``reach`` mm; how open it is toward the plane kept)."""
    p.index = index
    p.voxels = len(index)
    p.volume_mm3 = p.voxels * grid.voxel_mm3
    g = index + region.lo
    border = np.any((g == 0) | (g == np.asarray(border_of) - 1), axis=1)
    rim = rim_of(index, region.bone, grid.spacing_zyx, border, reach)
    p.rim = dataclasses.replace(rim, open_toward_plane=p.rim.open_toward_plane if p.rim else 0.0)


def _to_rim_across_slices(p: Piece, region: Region, grid: Grid, shell: float, border_of: Any, reach: float) -> None:
    """A kept template's rim gap still over a voxel once bridged: the piece filled out to the rim across slices
    (``_to_rim``'s ``across_slices``), kept where that brings its rim nearer the bone (else the piece is left as it
    was). It runs once the piece is judged: a fill that closes the rim must not lift a piece the mirror does not fit
    over the confidence bar (the turned head phantom's 40 mm cut at 112.5 degrees: rim gap 3.0 -> 1.9 voxels, its
    confidence over the bar, Dice 0.30)."""
    assert p.index is not None and p.rim is not None
    before = (p.index, p.voxels, p.volume_mm3, p.rim)
    _to_rim(p, region, grid, shell, border_of=border_of, reach=reach, across_slices=True)
    if p.rim is None or p.rim.gap_voxels >= before[3].gap_voxels:
        p.index, p.voxels, p.volume_mm3, p.rim = before


def _close_width(shell: float, grid: Grid) -> float:
    """The widest gap between a template and the hole's rim that ``_close_rim`` bridges (mm): half the shell's
    thickness, at least one voxel's smallest side."""
    return max(RIM_CLOSE_SHELLS * shell, float(min(grid.spacing_zyx)))


def _close_rim(p: Piece, region: Region, grid: Grid, shell: float, border_of: Any, reach: float) -> None:
    """A rim gap closed: where the mirror's bone stops short of the hole's rim (an oblique rim between thick
    slices, a mirror a fraction of a voxel off), the template grows across the gap to touch the bone. The template
    and the scan's bone are closed together (a ball half as wide as ``_close_width``, a step along a coarser axis
    counted as its radius: gaps up to that width, or one slice between thick slices, fill);
    what the closing adds outside the bone, within that width of the template and connected to it, joins the
    template. The rim is measured again; the volume added is ``Piece.bridged_mm3``."""
    from scipy import ndimage as ndi

    assert p.index is not None
    if p.rim is None or p.rim.gap_voxels <= 0.0:
        return
    sp = np.asarray(grid.spacing_zyx)
    width = _close_width(shell, grid)
    r = 0.5 * width
    margin = np.ceil(2.0 * width / sp).astype(np.int64) + 2
    lo = np.maximum(p.index.min(axis=0) - margin, 0)
    hi = np.minimum(p.index.max(axis=0) + margin + 1, region.bone.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    piece = np.zeros(tuple(int(b - a) for a, b in zip(lo, hi, strict=True)), dtype=bool)
    piece[tuple((p.index - lo).T)] = True
    bone = region.bone[box]
    both = piece | bone
    # a step along a coarse axis counts as the ball's radius at most: between slices thicker than the ball, the
    # closing still bridges a slice the mirror's bone stops short of (the head phantom's 5 mm slices: the rim's
    # gaps are above and below the template, across slices)
    step = np.minimum(sp, r)
    grown = ndi.distance_transform_edt(~both, sampling=step) <= r + 1e-6
    closed = ndi.distance_transform_edt(grown, sampling=step) > r + 1e-6
    to_piece = ndi.distance_transform_edt(~piece, sampling=step)
    add = closed & ~both & (to_piece <= width + 1e-6)
    if not add.any():
        return
    labels, _ = ndi.label(add | piece, structure=CONNECTIVITY)
    keep = np.isin(labels, np.unique(labels[piece]))
    before = len(p.index)
    _take(p, np.argwhere(keep) + lo, region, grid, border_of=border_of, reach=reach)
    p.bridged_mm3 = (p.voxels - before) * grid.voxel_mm3


def _no_core(region: Region, grid: Grid) -> str:
    """Why a piece without a core is left out, in the scan's own measures."""
    t = region.shell_mm
    vox = float(max(grid.spacing_zyx))
    return (
        f"no core: the scan has bone within the healthy shell's thickness ({t:.1f} mm) of every voxel of it: "
        f"asymmetry, or a hole narrower than about twice that ({2 * t:.0f} mm, {2 * t / vox:.1f} of its largest "
        f"voxel side {vox:.2g} mm) that mirroring cannot tell from asymmetry at this voxel size"
    )


def _where(p: Piece) -> str:
    x, y, z = p.centroid_lps_mm
    side = "left" if p.side_mm[1] > 0 else "right"
    return f"centred at ({x:.0f}, {y:.0f}, {z:.0f}) mm LPS, {abs(p.side_mm[1]):.0f} mm {side} of the plane"


def _no_defect_message(region: Region) -> str:
    head = (
        f"no one-sided defect found: mirroring the skull across its symmetry plane leaves no missing bone of at "
        f"least {region.min_volume_mm3:,.0f} mm3 whose rim meets the bone (a defect centred on the midline is "
        "missing on both sides and cannot be found or filled by mirroring)"
    )
    cands = [p for p in region.pieces if p.core_mm3 > 0]
    if not cands:
        return head + "; the scan looks intact at this level"
    p = max(cands, key=lambda p: p.volume_mm3)
    return head + f"; the largest candidate ({p.volume_mm3:,.0f} mm3, {_where(p)}) was left out: {p.reason}"


def local_fit(
    index: npt.NDArray[np.int64], bone: BoolArray, mirror: Any, spacing_zyx: tuple[float, float, float], reach_mm: float
) -> float:
    """How well the mirror matches the bone around a piece: the overlap (intersection over union) of the mirrored
    bone and the bone within ``reach_mm`` of the piece, the piece left out."""
    from scipy import ndimage as ndi

    sp = np.asarray(spacing_zyx)
    margin = np.ceil(reach_mm / sp).astype(np.int64) + 1
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, bone.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    piece = np.zeros(tuple(int(b - a) for a, b in zip(lo, hi, strict=True)), dtype=bool)
    piece[tuple((index - lo).T)] = True
    ring = (ndi.distance_transform_edt(~piece, sampling=sp) <= reach_mm) & ~piece
    b, m = bone[box] & ring, mirror[box] & ring
    union = int((b | m).sum())
    return float((b & m).sum()) / union if union else 0.0


def patient_bounds(mask: BoolArray, lo: npt.NDArray[np.int64], grid: Grid) -> tuple[FloatArray, FloatArray]:
    """The mask's voxel centres' bounds in the patient frame (x, y, z mm): the eight box corners mapped."""
    a, b = bounding_box(mask)
    corners = np.array([[z, y, x] for z in (a[0], b[0] - 1) for y in (a[1], b[1] - 1) for x in (a[2], b[2] - 1)])
    p = grid.to_patient(grid.xyz(corners + lo))
    return p.min(axis=0), p.max(axis=0)
