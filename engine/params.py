"""Parameters of the reconstruction pipeline: frozen dataclasses that round-trip through JSON.

Defaults are the paper's best combination (EMC33GPU: 3x3x3 Gaussian, MC33, reduction factor 0.2, one
surface-preserving Laplacian iteration at 0.5 degrees). Importing this module never loads Warp.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any

from engine.defect.params import DefectParams

# lower HU bounds of InVesalius' threshold presets (adult); "bone" is the usual 300 HU
ISO_PRESETS_HU: dict[str, float] = {"bone": 300.0, "compact-bone": 662.0, "spongy-bone": 148.0}
# speck removal by default: pieces smaller than this many voxels' volume are dropped (IslandParams)
DEFAULT_SPECK_VOXELS = 4.0
# image stacks carry no orientation: which end of the stack is the patient's head (OrientParams)
FIRST_SLICE_CHOICES = ("superior", "inferior")
# physically plausible voxel sizes: 0.1 um (beyond any micro-CT) to 10 cm (beyond any clinical slice gap)
SPACING_MM_MIN, SPACING_MM_MAX = 1e-4, 100.0
# levels, offsets and volumes must stay finite in float32 (the device's type)
FLOAT32_MAX = 3.4028234663852886e38
INT32_MAX = 2**31 - 1  # counts (faces, pieces) are int32 on the device and in the mesh arrays


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise ValueError(message)


def _finite(value: float | None, name: str, *, lo: float = -FLOAT32_MAX, hi: float = FLOAT32_MAX) -> None:
    """None, or a real number within [lo, hi] (NaN and infinities refused)."""
    if value is None:
        return
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    _check(ok and lo <= value <= hi, f"{name} must be a finite number in [{lo:g}, {hi:g}], got {value!r}")


def _integer(value: int | None, name: str, lo: int, hi: int = INT32_MAX) -> None:
    """None, or an integer (not a bool, not a float) within [lo, hi]: the counts the stages loop over or size arrays
    by, where a float or a bool would fail deep inside a stage rather than here."""
    if value is None:
        return
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    _check(ok and lo <= value <= hi, f"{name} must be an integer in [{lo}, {hi}], got {value!r}")


# ------------------------------------------------------------------------------------------ decimation targets
MIN_TRIANGLES = 4  # a decimated closed piece keeps at least a tetrahedron: DecimateParams.max_triangles' floor


def is_reduction(value: object) -> bool:
    """The one rule for a reduction factor (the fraction of faces a decimation keeps): a real number in (0, 1], not
    a bool, not NaN. ``DecimateParams``, ``target_faces`` (the numpy entry point) and the paper's sweep use it."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        return False
    number = float(value)  # (a numpy float compares the same)
    return math.isfinite(number) and 0 < number <= 1


def check_reduction(value: object) -> float:
    """``value`` as a reduction factor (``is_reduction``).

    Raises:
        ValueError: not a real number in (0, 1].
    """
    _check(is_reduction(value), f"reduction must be in (0, 1], got {value}")
    return float(value)  # type: ignore[arg-type]


def target_faces(n_faces: int, reduction: float | None, max_triangles: int | None, *, least: int = 1) -> int:
    """The face count a decimation of ``n_faces`` asks for: ``reduction`` of them (at least one) or
    ``max_triangles`` (an integer >= ``least``); exactly one of the two is given.

    Raises:
        ValueError: neither or both given, or a value outside its rule.
    """
    if (reduction is None) == (max_triangles is None):
        raise ValueError("Give exactly one of reduction (fraction of faces kept) or max_triangles")
    if reduction is not None:
        check_reduction(reduction)
        return max(round(reduction * n_faces), 1)
    _integer(max_triangles, "max_triangles", least)
    return int(max_triangles)  # type: ignore[arg-type]


def check_spacing_zyx_mm(spacing: object) -> tuple[float, float, float]:
    """A voxel size (z, y, x) in mm as three floats within [SPACING_MM_MIN, SPACING_MM_MAX].

    Raises:
        ValueError: not three numbers, or one of them non-finite or outside the plausible range.
    """
    try:
        values = tuple(float(v) for v in spacing)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError(f"Expected a voxel size of three numbers (z, y, x) in mm, got {spacing!r}") from None
    _check(len(values) == 3, f"Expected a voxel size of three numbers (z, y, x) in mm, got {spacing!r}")
    for axis, v in zip("zyx", values, strict=True):
        _check(
            math.isfinite(v) and SPACING_MM_MIN <= v <= SPACING_MM_MAX,
            f"Expected a voxel size between {SPACING_MM_MIN:g} and {SPACING_MM_MAX:g} mm, got {v!r} mm along "
            f"{axis} in {spacing!r}",
        )
    return values  # type: ignore[return-value]


# ------------------------------------------------------------------------------------------ voxel size order
# every voxel size in bonemesh is (z, y, x): the API's "spacing", the page's field, the CLI's --voxel-size, the
# library's spacing_zyx_mm. CT images have square pixels (y = x); two sizes equal within this share are "equal"
_SAME = 0.01
_UNSQUARE = 1.1  # in-plane sizes that differ by more than this ratio (and match no other order) are warned about


def _same(a: float, b: float) -> bool:
    return abs(a - b) <= _SAME * max(a, b)


def spacing_order_warning(spacing_zyx_mm: object) -> dict[str, Any] | None:
    """A warning when a voxel size given as (z, y, x) looks swapped, else None (also for values that are not a
    voxel size: ``check_spacing_zyx_mm`` refuses those).

    CT images have square pixels, so y and x are expected equal. Given (a, a, b) or (a, b, a) with a != b, the two
    equal values are probably the in-plane ones and the order was x, y, z (most tools' and most READMEs' order):
    the likely voxel size is (b, a, a). Given three different values whose y and x differ by more than 10 %, the
    order is questioned without a guess.

    Returns:
        ``{"code": "voxel_size_order", "message": ..., "given_zyx_mm": [z, y, x], "likely_zyx_mm": [z, y, x] or
        None}``; the message names the axes, each front end adds how to give the size there.
    """
    try:
        z, y, x = check_spacing_zyx_mm(spacing_zyx_mm)
    except ValueError:
        return None
    if _same(y, x):
        return None
    given = f"z {z:g}, y {y:g}, x {x:g} mm"
    likely: list[float] | None = None
    if _same(z, y) or _same(z, x):
        odd = x if _same(z, y) else y
        likely = [odd, z, z]
        message = (
            f"the voxel size {given} looks swapped: CT images have square pixels (y = x), so these values are "
            f"probably in x, y, z order, i.e. z {odd:g}, y {z:g}, x {z:g} mm"
        )
    elif max(y, x) / min(y, x) > _UNSQUARE:
        message = (
            f"the voxel size {given} has unequal in-plane sizes (y {y:g} mm, x {x:g} mm), while CT images have "
            "square pixels: check the order (z: slice step, y: row spacing, x: column spacing)"
        )
    else:
        return None
    return {"code": "voxel_size_order", "message": message, "given_zyx_mm": [z, y, x], "likely_zyx_mm": likely}


@dataclass(frozen=True)
class PreprocessParams:
    """Optional per-slice preprocessing (the paper's) and a crop box.

    Applied in this order: the crop, then per slice the threshold, the area opening, and Canny last (the
    opening removes the specks before the edges are traced).

    Args:
        threshold: set samples below this value (volume units) to the volume's minimum; None: off.
        canny_sigma: replace each slice by its Canny edge map (scikit-image) with this sigma; None: off.
        area_opening_px: remove bright specks smaller than this many pixels per slice; None: off.
        crop_zyx_mm: ((z0, z1), (y0, y1), (x0, x1)) box in mm from the first sample; None: whole volume.
    """

    threshold: float | None = None
    canny_sigma: float | None = None
    area_opening_px: int | None = None
    crop_zyx_mm: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] | None = None

    def __post_init__(self) -> None:
        _finite(self.threshold, "threshold")
        _finite(self.canny_sigma, "canny_sigma", hi=1e4)
        _check(self.canny_sigma is None or self.canny_sigma > 0, f"canny_sigma must be > 0, got {self.canny_sigma}")
        _integer(self.area_opening_px, "area_opening_px", 1)
        if self.crop_zyx_mm is not None:
            _check(
                len(self.crop_zyx_mm) == 3 and all(len(r) == 2 and r[0] < r[1] for r in self.crop_zyx_mm),
                f"crop_zyx_mm must be three (lo, hi) ranges in mm with lo < hi, got {self.crop_zyx_mm}",
            )
            for lo, hi in self.crop_zyx_mm:
                _finite(lo, "crop_zyx_mm")
                _finite(hi, "crop_zyx_mm")


@dataclass(frozen=True)
class GaussianParams:
    """3x3x3 Gaussian smoothing of the volume on the device.

    Args:
        sigma_voxels: standard deviation in voxels (0.5, MATLAB's imgaussfilt3 default for a 3x3x3 kernel).
    """

    sigma_voxels: float = 0.5

    def __post_init__(self) -> None:
        _finite(self.sigma_voxels, "sigma_voxels", hi=1e4)
        _check(self.sigma_voxels > 0, f"sigma_voxels must be > 0, got {self.sigma_voxels}")


@dataclass(frozen=True)
class IsoParams:
    """Iso level: an explicit value in the volume's units, a HU preset, or Otsu when neither is given.

    Args:
        iso: level in the volume's units.
        preset: one of ``ISO_PRESETS_HU`` (needs HU data, or ``hu_offset`` for stacks that store HU + offset).
        hu_offset: stored value = HU + hu_offset (e.g. 1024 for PNG stacks of HU + 1024).
        closed: close the surface at the volume's borders (watertight output).
    """

    iso: float | None = None
    preset: str | None = None
    hu_offset: float | None = None
    closed: bool = True

    def __post_init__(self) -> None:
        _check(not (self.iso is not None and self.preset is not None), "give either iso or preset, not both")
        _check(self.iso is None or math.isfinite(self.iso), f"iso must be finite, got {self.iso}")
        _finite(self.iso, "iso")
        _finite(self.hu_offset, "hu_offset")
        _check(
            self.preset is None or self.preset in ISO_PRESETS_HU,
            f"preset must be one of {sorted(ISO_PRESETS_HU)}, got {self.preset!r}",
        )


@dataclass(frozen=True)
class IslandParams:
    """Island removal. Args: min_volume_mm3: drop pieces smaller than this; keep_largest: keep the N largest.

    min_volume_voxels: when ``min_volume_mm3`` is None, drop pieces smaller than this many voxels' volume
    (specks a printer or a viewer cannot show); None or 0: no volume limit unless ``min_volume_mm3`` is given.
    """

    min_volume_mm3: float | None = None
    keep_largest: int | None = None
    min_volume_voxels: float | None = DEFAULT_SPECK_VOXELS

    def min_volume_for(self, spacing_zyx_mm: tuple[float, float, float]) -> float | None:
        """The volume limit in mm3 for a grid of this spacing: ``min_volume_mm3``, else ``min_volume_voxels``
        voxels' volume, else None (no limit)."""
        if self.min_volume_mm3 is not None:
            return self.min_volume_mm3
        if not self.min_volume_voxels:
            return None
        return float(self.min_volume_voxels * spacing_zyx_mm[0] * spacing_zyx_mm[1] * spacing_zyx_mm[2])

    def __post_init__(self) -> None:
        _finite(self.min_volume_mm3, "min_volume_mm3")
        _check(
            self.min_volume_mm3 is None or self.min_volume_mm3 >= 0,
            f"min_volume_mm3 must be >= 0, got {self.min_volume_mm3}",
        )
        _integer(self.keep_largest, "keep_largest", 1)
        _check(
            self.min_volume_voxels is None or (math.isfinite(self.min_volume_voxels) and self.min_volume_voxels >= 0),
            f"min_volume_voxels must be a finite number >= 0, got {self.min_volume_voxels}",
        )


@dataclass(frozen=True)
class DecimateParams:
    """Quadric-error decimation to a target face count: exactly one of the two fields is set.

    Args:
        reduction: fraction of the faces kept (0 < R <= 1, ``is_reduction``); the default, 0.2, is the paper's.
        max_triangles: or the face count to reach (an integer >= ``MIN_TRIANGLES``); give it with
            ``reduction=None``.
    """

    reduction: float | None = 0.2
    max_triangles: int | None = None

    def __post_init__(self) -> None:
        _check(
            self.reduction is None or self.max_triangles is None,
            f"give either reduction or max_triangles, not both (got reduction={self.reduction}, max_triangles="
            f"{self.max_triangles}; reduction defaults to {DecimateParams.reduction}: with max_triangles pass "
            "reduction=None)",
        )
        _check(self.reduction is not None or self.max_triangles is not None, "give reduction or max_triangles")
        if self.reduction is not None:
            check_reduction(self.reduction)
        _integer(self.max_triangles, "max_triangles", MIN_TRIANGLES)

    def target_faces(self, n_faces: int) -> int:
        """The face count asked for of a mesh of ``n_faces`` (``engine.params.target_faces``)."""
        return target_faces(n_faces, self.reduction, self.max_triangles, least=MIN_TRIANGLES)


def decimate_of(reduction: float | None = None, max_triangles: int | None = None) -> DecimateParams:
    """The one rule for a decimation target given by a person or a client (the CLI's ``--reduction`` /
    ``--max-triangles``, the API's ``reduction`` / ``max_triangles``): one or the other, not both; neither keeps the
    default reduction.

    Raises:
        ValueError: both given, or a value ``DecimateParams`` refuses.
    """
    if reduction is not None and max_triangles is not None:
        raise ValueError("give reduction (--reduction) or max_triangles (--max-triangles), not both")
    if max_triangles is not None:
        return DecimateParams(reduction=None, max_triangles=max_triangles)
    return DecimateParams() if reduction is None else DecimateParams(reduction=reduction)


def islands_of(
    min_volume_mm3: float | None = None,
    keep_largest: int | None = None,
    *,
    keep_specks: bool = False,
    min_volume_voxels: float | None = DEFAULT_SPECK_VOXELS,
) -> IslandParams | None:
    """The one rule for speck removal as a person or a client asks for it: ``keep_specks`` (the CLI's
    ``--keep-specks``, the API's ``"islands": null``) keeps pieces of any size, and only ``keep_largest`` may then
    still apply (None: no island step at all); otherwise pieces below ``min_volume_mm3`` (else ``min_volume_voxels``
    voxels' volume) are dropped.

    Raises:
        ValueError: ``keep_specks`` with ``min_volume_mm3``, or a value ``IslandParams`` refuses.
    """
    if keep_specks:
        if min_volume_mm3 is not None:
            raise ValueError(
                'give min_island_mm3 (--min-island-mm3) or keep pieces of any size (--keep-specks, "islands": '
                "null), not both"
            )
        return None if keep_largest is None else IslandParams(keep_largest=keep_largest, min_volume_voxels=None)
    return IslandParams(min_volume_mm3=min_volume_mm3, keep_largest=keep_largest, min_volume_voxels=min_volume_voxels)


@dataclass(frozen=True)
class SmoothParams:
    """Surface-preserving Laplacian smoothing. Args: iterations (>= 1); angle_deg: largest face-normal turn."""

    iterations: int = 1
    angle_deg: float = 0.5

    def __post_init__(self) -> None:
        _integer(self.iterations, "iterations", 1, 10_000)
        _check(0 < self.angle_deg < 90, f"angle_deg must be in (0, 90), got {self.angle_deg}")


@dataclass(frozen=True)
class ExportParams:
    """Output budgets. Args: phone_max_triangles (Draco GLB); ar_max_triangles (plain GLB for AR viewers)."""

    phone_max_triangles: int = 100_000
    ar_max_triangles: int = 50_000

    def __post_init__(self) -> None:
        for name in ("phone_max_triangles", "ar_max_triangles"):
            _integer(getattr(self, name), name, 100)


@dataclass(frozen=True)
class OrientParams:
    """How an image stack (PNG/TIFF/JPEG/BMP slices, ``.npy``) lies in the patient; DICOM ignores it (its headers
    place every slice in the patient frame).

    The assumed convention is the DICOM axial display: image column index to the patient's left (the patient's
    right on the image's left), image row index to posterior (anterior at the top), and the stack from the head
    down (the first slice superior, the scan order of most CT series and of the bundled headsq head).

    Args:
        first_slice: "superior" (default) or "inferior" (stacks sorted by ascending position, e.g. exported by
            3D Slicer or ITK, and the cranium/head-phantom PNGs in ../shared/data).
        flip_lr: the image's left is the patient's left (mirror left-right).
        flip_ap: the image's top is posterior (mirror anterior-posterior).
    """

    first_slice: str = "superior"
    flip_lr: bool = False
    flip_ap: bool = False

    def __post_init__(self) -> None:
        _check(
            self.first_slice in FIRST_SLICE_CHOICES,
            f"first_slice must be one of {list(FIRST_SLICE_CHOICES)}, got {self.first_slice!r}",
        )


@dataclass(frozen=True)
class BodyMaskParams:
    """Bone inside the patient's body outline only, for HU data (DICOM CT, or stacks with ``iso.hu_offset``).

    The body outline is the tissue at or above ``outline_hu`` that is below the bone level, with its holes filled
    slice by slice: bone covered by soft tissue lies inside it, while the couch and head holders, which touch air,
    do not. A connected bone piece (voxels at or above the level) is kept when at least ``min_inside_fraction`` of
    its voxels lie inside the outline (dilated by ``dilate_mm`` in-plane); the others are set below the level
    before meshing.

    Args:
        outline_hu: air/tissue threshold of the outline in HU (-500: halfway from air to water).
        dilate_mm: grow the filled outline in-plane by this much (0: off; a millimetre or more also takes in
            the partial-volume rim around a couch or a holder, so keep it small).
        min_inside_fraction: a piece is bone of the body when at least this fraction of it is inside (0 < f <= 1).
        min_bone_mm3: when pieces were dropped and less bone than this is left inside the body, the scan has no
            bone in the body (ctpace at 300 HU: the couch outside, a few specks inside): the run fails saying so.
    """

    outline_hu: float = -500.0
    dilate_mm: float = 0.0
    min_inside_fraction: float = 0.5
    min_bone_mm3: float = 1000.0

    def __post_init__(self) -> None:
        _check(math.isfinite(self.outline_hu), f"outline_hu must be finite, got {self.outline_hu}")
        _check(math.isfinite(self.dilate_mm) and self.dilate_mm >= 0, f"dilate_mm must be >= 0, got {self.dilate_mm}")
        _check(
            0 < self.min_inside_fraction <= 1, f"min_inside_fraction must be in (0, 1], got {self.min_inside_fraction}"
        )
        _check(
            math.isfinite(self.min_bone_mm3) and self.min_bone_mm3 >= 0,
            f"min_bone_mm3 must be >= 0, got {self.min_bone_mm3}",
        )


@dataclass(frozen=True)
class RoiParams:
    """A region of interest cropped before anything runs (``engine.labels.pieces.crop_roi``).

    Args:
        box: three (lo, hi) ranges, lo < hi: voxel indices (z, y, x; lo inclusive, hi exclusive, as a slice) with
            ``units="voxels"``, or patient-frame (LPS) x, y, z in mm with ``units="mm"`` (the box's corners are
            taken into the grid; the samples inside are kept).
        units: "voxels" or "mm".
    """

    box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
    units: str = "voxels"

    def __post_init__(self) -> None:
        _check(self.units in ("voxels", "mm"), f"roi units must be 'voxels' or 'mm', got {self.units!r}")
        ok = len(self.box) == 3 and all(len(r) == 2 for r in self.box)
        _check(ok, f"roi must be three (lo, hi) ranges, got {self.box}")
        for lo, hi in self.box:
            _finite(lo, "roi")
            _finite(hi, "roi")
            _check(lo < hi, f"roi ranges need lo < hi, got ({lo}, {hi})")
            if self.units == "voxels":
                _check(float(lo).is_integer() and float(hi).is_integer() and lo >= 0, f"roi voxel indices must be "
                       f"whole numbers >= 0, got ({lo}, {hi})")  # fmt: skip


@dataclass(frozen=True)
class PiecesParams:
    """Keep the ``count`` largest bone pieces of a CT as separate parts (``engine.labels.pieces.bone_pieces``).

    Args:
        count: pieces kept (1..1000), largest first.
        connectivity: 6 (faces), 18 (faces and edges) or 26 (also corners): which voxels touch.
        min_voxels: pieces smaller than this are never kept (specks).
    """

    count: int = 2
    connectivity: int = 26
    min_voxels: int = 4

    def __post_init__(self) -> None:
        _integer(self.count, "pieces count", 1, 1000)
        _check(self.connectivity in (6, 18, 26), f"connectivity must be 6, 18 or 26, got {self.connectivity}")
        _integer(self.min_voxels, "min_voxels", 1)


_NESTED = {
    "preprocess": PreprocessParams,
    "gaussian": GaussianParams,
    "iso": IsoParams,
    "islands": IslandParams,
    "decimate": DecimateParams,
    "smooth": SmoothParams,
    "export": ExportParams,
    "orient": OrientParams,
    "body": BodyMaskParams,
    "defect": DefectParams,
}


@dataclass(frozen=True)
class ReconParams:
    """The whole pipeline; a stage whose params are None is skipped (iso and export always run).

    By default the model is bone only: ``body`` drops bone outside the body outline (HU data) and ``islands``
    drops specks below ``DEFAULT_SPECK_VOXELS`` voxels; set either to None to keep what it would drop. ``orient``
    places image stacks in the patient frame (DICOM carries its own). ``defect`` (off unless given) also finds the
    bone's one-sided defect and its mirrored template (``engine.defect``: ``implant.stl``, ``defect.json``).
    """

    preprocess: PreprocessParams | None = None
    gaussian: GaussianParams | None = field(default_factory=GaussianParams)
    iso: IsoParams = field(default_factory=IsoParams)
    islands: IslandParams | None = field(default_factory=IslandParams)
    decimate: DecimateParams | None = field(default_factory=DecimateParams)
    smooth: SmoothParams | None = field(default_factory=SmoothParams)
    export: ExportParams = field(default_factory=ExportParams)
    orient: OrientParams = field(default_factory=OrientParams)
    body: BodyMaskParams | None = field(default_factory=BodyMaskParams)
    defect: DefectParams | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (tuples become lists)."""
        out = dataclasses.asdict(self)
        if self.defect is not None:
            out["defect"] = self.defect.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ReconParams:
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError naming them."""
        if not isinstance(data, dict):
            raise ValueError(f"Expected a JSON object of parameters, got {type(data).__name__}")
        unknown = set(data) - set(_NESTED)
        if unknown:
            raise ValueError(f"Unknown parameter groups {sorted(unknown)}; expected some of {sorted(_NESTED)}")
        kwargs: dict[str, Any] = {}
        for name, kind in _NESTED.items():
            if name not in data:
                continue
            value = data[name]
            if value is None:
                kwargs[name] = None
                continue
            if not isinstance(value, dict):
                raise ValueError(f"Expected {name} to be an object, got {type(value).__name__}")
            names = {f.name for f in dataclasses.fields(kind)}
            bad = set(value) - names
            if bad:
                raise ValueError(f"Unknown {name} parameters {sorted(bad)}; expected some of {sorted(names)}")
            if name == "preprocess" and value.get("crop_zyx_mm") is not None:
                value = {**value, "crop_zyx_mm": tuple(tuple(r) for r in value["crop_zyx_mm"])}
            kwargs[name] = DefectParams.from_dict(value) if name == "defect" else kind(**value)
        return cls(**kwargs)
