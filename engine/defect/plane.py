"""The bone's symmetry plane: the mirror that maps the skull's surface onto itself best.

1. The skull (``grid.bone_and_skull``: the largest piece at or above the level) and its surface voxels, in the
   grid's mm.
2. Candidates: the planes through the skull's centroid normal to its three principal axes and to the three grid
   axes; each is scored by the median distance from the mirrored surface to the surface, and the two best are
   refined.
3. Refinement: mirror-ICP constrained to reflections (3 parameters: the normal's two angles and the offset).
   Every iteration mirrors a fixed sample of surface points, pairs each with the nearest surface voxel (a k-d
   tree on the host, or on a device a closest-feature transform of the surface: issue 42, ``find_symmetry_plane``'s
   ``device``) and takes a Gauss-Newton step on the point-to-point distances with Cauchy weights (the scale follows the
   median distance), so that the bone missing from one side (the defect) and the unpaired parts of the face and
   neck barely pull on the plane. A point hint leaves out the bone around the point and around its mirror image.
4. The residual: the root mean square of the 80 % smallest distances (mm), with the median and the share of
   mirrored points within one voxel diagonal of the surface (``inlier_fraction``). A bone without a mirror plane
   (``inlier_fraction`` under ``MIN_INLIER_FRACTION``) is refused (``NoSymmetryError``).

The normal is turned toward the patient's left (+x of LPS), so a positive signed distance is the left side.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.defect.grid import FloatArray, Grid, bone_and_skull, reflect, surface_voxels
from engine.errors import NoSymmetryError
from engine.types import Volume

N_SAMPLES = 6_000  # mirrored surface points per iteration
SCORE_SAMPLES = 2_000  # mirrored points that rank the candidates
CANDIDATE_VOXELS = 200_000  # about as many of the skull's voxels give the principal axes (every k-th)
GOOD_INLIER_FRACTION = 0.8  # a refined candidate this good is not compared with the next
MAX_SURFACE = 150_000  # surface voxels paired with (a random subset beyond this)
MAX_ITERATIONS = 40
# converged: the last step turned the normal by less than 0.006 degrees and moved it by less than 0.01 mm
TOL_RAD, TOL_MM = 1e-4, 0.01
# the refinement starts on every COARSE_STRIDE-th sample point until its steps are under COARSE_TOL times the
# tolerance, then goes on with all of them (issue 42: the plane's host time)
COARSE_STRIDE, COARSE_TOL = 4, 10.0
# the device's nearest-surface query looks at every voxel within the bound that the nearest voxel's closest feature
# gives, where they are at most this many (exact there; a point farther off keeps that feature: an outlier)
MAX_SCAN = 4_096
TRIM = 0.8  # the residual: RMS of this share of the smallest distances
# a bone is mirror-symmetric when at least this share of its mirrored surface lies within a voxel diagonal of its
# surface (real skulls: 0.8-0.99; an intact skull with its face and neck, 0.8 at 3.2 mm voxels)
MIN_INLIER_FRACTION = 0.5
METHOD = (
    "mirror-ICP constrained to reflections: principal-axis and grid-axis candidates, Gauss-Newton on nearest "
    "surface distances with Cauchy weights"
)


@dataclass(frozen=True)
class SymmetryPlane:
    """A mirror plane ``normal . p = offset_mm`` in the patient frame (LPS mm; ``normal`` a unit vector turned toward
    the patient's left), and the same plane in the grid (``normal_grid`` . (x, y, z) mm = ``offset_grid_mm``).

    ``residual_mm``: RMS of the 80 % smallest distances from the mirrored surface to the surface; ``median_mm``:
    their median; ``inlier_fraction``: the share within one voxel diagonal. ``point_lps_mm``: the point of the plane
    nearest to the skull's centroid.
    """

    normal: tuple[float, float, float]
    offset_mm: float
    point_lps_mm: tuple[float, float, float]
    residual_mm: float
    median_mm: float
    inlier_fraction: float
    normal_grid: tuple[float, float, float]
    offset_grid_mm: float
    method: str = METHOD
    iterations: int = 0
    seconds: float = 0.0
    candidates: list[dict[str, Any]] = field(default_factory=list, compare=False, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (``defect.json``'s ``plane``)."""
        return {
            "normal_lps": [round(v, 6) for v in self.normal],
            "offset_mm": round(self.offset_mm, 4),
            "point_lps_mm": [round(v, 3) for v in self.point_lps_mm],
            "residual_mm": round(self.residual_mm, 4),
            "median_mm": round(self.median_mm, 4),
            "inlier_fraction": round(self.inlier_fraction, 4),
            "method": self.method,
            "iterations": self.iterations,
            "seconds": round(self.seconds, 4),
        }

    def signed_distance_grid(self, xyz: FloatArray) -> FloatArray:
        """Signed distances (mm, + on the patient's left) of grid points (N, 3)."""
        return np.asarray(xyz) @ np.asarray(self.normal_grid) - self.offset_grid_mm


def _tangents(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


class _TreeNearest:
    """Nearest surface voxels on the host: a k-d tree's exact queries (scipy)."""

    def __init__(self, surface: FloatArray) -> None:
        from scipy.spatial import cKDTree

        # exact nearest neighbours either way; the unbalanced tree builds in a third of the time
        self.tree = cKDTree(surface, balanced_tree=False, compact_nodes=False)

    def __call__(self, q: FloatArray) -> npt.NDArray[np.int64]:
        # 6,000 points: starting threads costs more than it saves
        return np.asarray(self.tree.query(q, workers=1)[1], dtype=np.int64)


class _DeviceNearest:
    """Nearest surface voxels on a backend (issue 42): the closest-feature transform of the surface voxels over
    their bounding box, once (``ops.closest_feature``), then per query each point's nearest surface voxel among the
    voxels within the distance to the closest feature of its nearest voxel (``ops.nearest_feature``): one upload
    of the points and one read-back of their pairs.
    The k-d tree's pairs (to float32 rounding and ties) but for points so far from the surface that the voxels
    within the bound are more than ``MAX_SCAN``."""

    #: device bytes per voxel of the grid: the skull, its flags and their compaction; the box's two float32 and
    #: two int32 fields and the passes' scratch
    BYTES_PER_VOXEL = 40

    def __init__(self, be: Any, grid: Grid, surf_idx: npt.NDArray[np.int64], centroid: FloatArray) -> None:
        from engine.defect.kernel_specs import BOX
        from engine.defect.ops import closest_feature

        self.be = be
        lo = surf_idx.min(axis=0)
        shape = tuple(int(v) for v in surf_idx.max(axis=0) - lo + 1)
        sp = grid.spacing_zyx
        flat = np.ravel_multi_index(tuple((surf_idx - lo).T), shape).astype(np.int32)
        self.features = be.from_host(flat)
        self.rank = closest_feature(be, self.features, shape, sp)
        self.box = be.struct(BOX, nz=shape[0], ny=shape[1], nx=shape[2], lz=int(lo[0]), ly=int(lo[1]),
                             lx=int(lo[2]), sz=float(sp[0]), sy=float(sp[1]), sx=float(sp[2]))  # fmt: skip
        self.shift = np.asarray(centroid, dtype=np.float64) - grid.xyz(lo)  # centred grid mm -> the box's mm
        self.capacity = 0
        self.points: Any = None
        self.out: Any = None
        self.scratch: Any = None

    @classmethod
    def fits(cls, be: Any, shape: tuple[int, ...]) -> bool:
        """Whether the plane's device work on a grid of ``shape`` fits the backend's default working set (and its
        flat indices an int32)."""
        n = int(np.prod(shape))
        return n < 2**31 and n * cls.BYTES_PER_VOXEL <= int(be.default_budget())

    def __call__(self, q: FloatArray) -> npt.NDArray[np.int64]:
        from engine.defect.ops import nearest_feature, nearest_parts

        be, count = self.be, len(q)
        if count > self.capacity:
            self.capacity = count
            self.points = be.empty(3 * count, np.float32)
            self.out = be.empty(count, np.int32)
            parts = count * nearest_parts(be)
            self.scratch = (be.empty(parts, np.float32), be.empty(parts, np.int32))
        be.upload(self.points, np.ascontiguousarray(q + self.shift, dtype=np.float32).reshape(-1))
        nearest_feature(be, self.points, count, self.rank, self.features, self.box, self.out, max_scan=MAX_SCAN,
                        scratch=self.scratch)  # fmt: skip
        pairs: npt.NDArray[np.int64] = be.to_host(self.out, count=count).astype(np.int64)  # sync point
        return pairs


class _SkullOnDevice:
    """The skull mask on a backend: its voxels and surface voxels found there (``ops.set_voxels``: the host's
    ``np.argwhere`` and ``grid.surface_voxels``, the same indices in the same order) and its Sobel gradient at the
    surface voxels (``ops.sobel``: the host's ``surface_normals``' integer sums)."""

    def __init__(self, be: Any, skull: Any) -> None:
        from engine.defect.ops import upload_mask

        self.be = be
        self.shape = tuple(int(v) for v in skull.shape)
        self.mask = upload_mask(be, skull)

    def _index(self, flat: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        return np.stack(np.unravel_index(flat, self.shape), axis=1)

    def voxels(self, most: int) -> npt.NDArray[np.int64]:
        """(N, 3) indices (z, y, x) of every k-th of the skull's voxels, k the smallest that keeps N at about
        ``most`` or under (``np.argwhere(skull)[::k]``)."""
        from engine.defect.ops import set_voxels

        flat = set_voxels(self.be, self.mask, self.shape)
        return self._index(flat[:: max(1, len(flat) // most)])

    def surface(self) -> npt.NDArray[np.int64]:
        """(N, 3) indices (z, y, x) of the skull's voxels with a face neighbour outside it."""
        from engine.defect.ops import set_voxels

        return self._index(set_voxels(self.be, self.mask, self.shape, surface=True))

    def sobel(self, index_zyx: npt.NDArray[np.int64]) -> npt.NDArray[np.int32]:
        """The integer Sobel gradient (x, y, z) of the skull at voxels (N, 3) (z, y, x)."""
        from engine.defect.ops import sobel

        flat = np.ravel_multi_index(tuple(np.asarray(index_zyx).T), self.shape).astype(np.int32)
        return sobel(self.be, self.mask, self.shape, self.be.from_host(flat), len(flat))


class _Fit:
    """Mirror-ICP over a fixed sample of surface points (grid mm, centred on the skull's centroid), point-to-plane:
    each mirrored point's residual is its offset from its nearest surface voxel along that voxel's normal, so that
    the voxels' staircase does not hold the plane to the grid's axes. ``nearest`` pairs points (N, 3) with the rank
    of their nearest surface voxel (``_TreeNearest`` on the host, ``_DeviceNearest`` on a backend)."""

    def __init__(
        self,
        surface: FloatArray,
        normals: FloatArray,
        sample: FloatArray,
        voxel_diag: float,
        max_spacing: float,
        nearest: Callable[[FloatArray], npt.NDArray[np.int64]],
    ) -> None:
        self.nearest = nearest
        self.surface = surface
        self.normals = normals
        self.p = sample
        self.voxel_diag = voxel_diag
        self.floor = max_spacing  # the Cauchy scale never drops below a voxel: the surface is known to that
        self.keep = np.ones(len(sample), dtype=bool)

    def pairs(self, n: FloatArray, d: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per sample point: the distance of its mirror image to the nearest surface voxel, the offset along that
        voxel's normal, and the normal."""
        q = reflect(self.p, n, d)
        j = self.nearest(q)
        off = q - self.surface[j]
        nu = self.normals[j]
        return np.sqrt(np.einsum("ij,ij->i", off, off)), np.einsum("ij,ij->i", off, nu), nu

    def score(self, n: FloatArray, d: float) -> float:
        """The median distance of a few mirrored points (a candidate's rank)."""
        q = reflect(self.p[:SCORE_SAMPLES], n, d)
        off = q - self.surface[self.nearest(q)]
        return float(np.median(np.sqrt(np.einsum("ij,ij->i", off, off))))

    def refine(self, n: FloatArray, d: float, exclude: Any = None) -> tuple[FloatArray, float, int]:
        """Gauss-Newton from (n, d): first on every ``COARSE_STRIDE``-th sample point (the far-off start's
        iterations cost a quarter), then on all of them to convergence (the same fixed point)."""
        n = n / np.linalg.norm(n)
        full = self.p
        if len(full) >= 4 * COARSE_STRIDE * 100:
            self.p = full[::COARSE_STRIDE]
            try:
                keep = self.keep
                self.keep = keep[::COARSE_STRIDE]
                coarse = None if exclude is None else (lambda n, d: exclude(n, d)[::COARSE_STRIDE])
                n, d, it0 = self._iterate(n, d, coarse, COARSE_TOL)
            finally:
                self.p, self.keep = full, keep
        else:
            it0 = 0
        n, d, it = self._iterate(n, d, exclude, 1.0)
        return n, d, it0 + it

    def _iterate(self, n: FloatArray, d: float, exclude: Any, tol: float) -> tuple[FloatArray, float, int]:
        it = 0
        for it in range(1, MAX_ITERATIONS + 1):  # noqa: B007 - the count is reported
            if exclude is not None:
                self.keep = exclude(n, d)
            dist, r, nu = self.pairs(n, d)
            k = self.keep
            p = self.p
            if not k.all():  # (a hint's exclusion: else the copies would be the arrays themselves)
                p, dist, r, nu = p[k], dist[k], r[k], nu[k]
            scale = max(self.floor, 1.5 * float(np.median(dist)))
            w = 1.0 / (1.0 + (dist / scale) ** 2)
            s = p @ n - d
            e1, e2 = _tangents(n)
            # derivatives of the mirror image p' = p - 2 (n.p - d) n along the normal's two turns and the offset,
            # projected on the paired voxel's normal
            j1 = -2.0 * ((p @ e1) * (nu @ n) + s * (nu @ e1))
            j2 = -2.0 * ((p @ e2) * (nu @ n) + s * (nu @ e2))
            j3 = 2.0 * (nu @ n)
            jac = np.stack([j1, j2, j3], axis=1)
            h = (jac * w[:, None]).T @ jac
            g = (jac * w[:, None]).T @ r
            step = -np.linalg.solve(h + 1e-9 * np.eye(3), g)
            n = n + step[0] * e1 + step[1] * e2
            n /= np.linalg.norm(n)
            d = d + step[2]
            if abs(step[0]) + abs(step[1]) < tol * TOL_RAD and abs(step[2]) < tol * TOL_MM:
                break
        return n, float(d), it

    def residuals(self, n: FloatArray, d: float) -> tuple[float, float, float]:
        dist, _, _ = self.pairs(n, d)
        dist = np.sort(dist[self.keep])
        m = max(1, int(TRIM * len(dist)))
        return (
            float(np.sqrt(np.mean(dist[:m] ** 2))),
            float(np.median(dist)),
            float(np.mean(dist <= self.voxel_diag)),
        )


def surface_normals(mask: Any, index_zyx: Any, spacing_xyz: FloatArray) -> FloatArray:
    """Outward unit normals (grid x, y, z) at mask voxels: the mask's Sobel gradient (3x3x3, mm), reversed."""
    padded = np.pad(np.asarray(mask, dtype=bool), 1)
    flat = padded.ravel()
    stride = np.asarray(padded.strides, dtype=np.int64) // padded.itemsize
    base = (np.asarray(index_zyx, dtype=np.int64) + 1) @ stride  # flat indices: one gather per neighbour
    comps = [np.zeros(len(base), dtype=np.int32) for _ in range(3)]  # x, y, z: integer sums, exact
    weights = {-1: 1, 0: 2, 1: 1}
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dz == dy == dx == 0:
                    continue
                v = flat[base + (dz * stride[0] + dy * stride[1] + dx * stride[2])].view(np.int8)
                for axis, o in ((0, dx), (1, dy), (2, dz)):
                    if o:
                        others = [dx, dy, dz]
                        others.pop(axis)
                        w = weights[others[0]] * weights[others[1]]
                        comps[axis] += w * o * v
    return _unit_normals(np.stack(comps, axis=1), spacing_xyz)


def _unit_normals(sobel_xyz: Any, spacing_xyz: FloatArray) -> FloatArray:
    """Outward unit normals from the mask's integer Sobel gradient (x, y, z): the gradient in mm, reversed."""
    grad = np.asarray(sobel_xyz).astype(np.float64)
    grad /= spacing_xyz
    normal = -grad
    norm = np.linalg.norm(normal, axis=1, keepdims=True)
    return np.where(norm > 0, normal / np.maximum(norm, 1e-12), 0.0)


WHERE = ("auto", "device", "host")


def _device_for(device: Any, where: str, shape: tuple[int, ...]) -> Any:
    """The backend the plane's work runs on (``find_symmetry_plane``'s ``device`` and ``where``), or None: the
    host."""
    if where not in WHERE:
        raise ValueError(f"where is one of {', '.join(WHERE)}, got {where!r}")
    if device is None or where == "host":
        return None
    from engine.device import resolve_backend

    be = resolve_backend(device)
    if where == "auto" and be.is_host:
        return None
    return be if _DeviceNearest.fits(be, shape) else None


def skull_masks(data: Any, level: float, device: Any = None, where: str = "auto") -> tuple[Any, Any]:
    """The bone and the skull (``grid.bone_and_skull``: the same masks) with the skull's pieces found where
    ``find_symmetry_plane`` would work with the same ``device`` and ``where`` (``ops.bone_and_skull`` on a device,
    scipy on the host).

    Raises:
        EmptySurfaceError: nothing is at or above the level.
    """
    be = _device_for(device, where, tuple(int(s) for s in np.shape(data)))
    if be is None:
        return bone_and_skull(data, level)
    from engine.defect.ops import bone_and_skull as bone_and_skull_on

    return bone_and_skull_on(be, data, level)


def find_symmetry_plane(
    volume: Volume,
    level: float,
    hint: Any = None,
    *,
    orient: Any = None,
    skull: Any = None,
    seed: int = 0,
    device: Any = None,
    where: str = "auto",
) -> SymmetryPlane:
    """The bone's mirror plane (see the module's description).

    Args:
        volume: the scan.
        level: the bone level in the volume's units.
        hint: None, a side ("left" or "right": not used for the plane, only turned into nothing here), a point
            (x, y, z) in the patient frame (mm) in or next to the defect, or ``DefectParams`` (its point).
        orient: ``engine.params.OrientParams`` placing an image stack in the patient frame (default: the stack
            convention); DICOM places itself.
        skull: the skull mask (bool, the volume's shape) when the caller has it already (else ``skull_masks``).
        seed: the surface sample's seed (the result is deterministic for a given seed).
        device: None (the nearest surface voxels from a k-d tree on the host), or "cpu", "cuda[:N]", "opencl[:N]"
            or a ``Backend``: the skull's surface found and the nearest surface voxels looked up in a closest-feature
            transform there (the same plane to a few thousandths of a degree and of a voxel), as ``where`` says.
        where: "auto" (on the device unless it is the host's CPU, where the tree is faster: Warp's CPU path,
            PoCL), "device" (there whatever it is) or "host" (the tree). The host's tree too where the device's
            work would not fit its working set.

    Returns:
        The plane, its residual and how it was found.

    Raises:
        EmptySurfaceError: no bone at the level.
        NoSymmetryError: no mirror plane fits the bone.
    """
    t0 = time.perf_counter()
    grid = Grid.of(volume, orient)
    rng = np.random.default_rng(seed)
    be = _device_for(device, where, grid.shape)
    if skull is None:
        _, skull = skull_masks(volume.data, level, be, "host" if be is None else "device")
    on_device = _SkullOnDevice(be, skull) if be is not None else None
    surf_idx = surface_voxels(skull) if on_device is None else on_device.surface()
    if len(surf_idx) > MAX_SURFACE:
        surf_idx = surf_idx[np.sort(rng.choice(len(surf_idx), MAX_SURFACE, replace=False))]
    if on_device is None:
        normals = surface_normals(skull, surf_idx, grid.spacing_xyz)
    else:
        normals = _unit_normals(on_device.sobel(surf_idx), grid.spacing_xyz)
    surface = grid.xyz(surf_idx)
    centroid = surface.mean(axis=0)
    surface = surface - centroid
    pick = rng.choice(len(surface), min(N_SAMPLES, len(surface)), replace=False)
    sample = surface[np.sort(pick)]
    sp = grid.spacing_xyz
    nearest: Callable[[FloatArray], npt.NDArray[np.int64]] | None = None
    if be is not None:
        nearest = _DeviceNearest(be, grid, surf_idx, centroid)
    fit = _Fit(surface, normals, sample, float(np.linalg.norm(sp)), float(sp.max()), nearest or _TreeNearest(surface))

    exclude = None
    point = _hint_point(hint)
    if point is not None:
        h = grid.from_patient(np.asarray(point)) - centroid
        radius = float(getattr(hint, "point_radius_mm", 40.0))

        def exclude(n: FloatArray, d: float) -> Any:
            hm = reflect(h[None, :], n, d)[0]
            far = (np.linalg.norm(sample - h, axis=1) > radius) & (np.linalg.norm(sample - hm, axis=1) > radius)
            return far if far.sum() >= 100 else np.ones(len(sample), dtype=bool)

    # candidates: principal axes of the skull's voxels and the grid axes, through the centroid
    if on_device is None:
        at = np.argwhere(skull)
        at = at[:: max(1, len(at) // CANDIDATE_VOXELS)]
    else:
        at = on_device.voxels(CANDIDATE_VOXELS)
    voxels = grid.xyz(at) - centroid
    _, axes = np.linalg.eigh(np.cov(voxels.T))
    candidates = [axes[:, k] for k in range(3)] + [np.eye(3)[k] for k in range(3)]
    scored = sorted(((fit.score(c, 0.0), i, c) for i, c in enumerate(candidates)), key=lambda t: (t[0], t[1]))
    best: tuple[float, FloatArray, float, int] | None = None
    for _, _, c in scored[:2]:  # the best candidate, and the second where the best does not fit well
        n, d, its = fit.refine(c, 0.0, exclude)
        rms, _, share = fit.residuals(n, d)
        if best is None or rms < best[0]:
            best = (rms, n, d, its)
        if share >= GOOD_INLIER_FRACTION:
            break
    assert best is not None
    _, n, d, its = best
    rms, median, inliers = fit.residuals(n, d)
    d_grid = d + float(n @ centroid)
    if n @ grid.left_in_grid() < 0:  # the normal toward the patient's left
        n, d_grid = -n, -d_grid
    n_p, off_p = grid.plane_to_patient(n, d_grid)
    foot = centroid - (centroid @ n - d_grid) * n
    plane = SymmetryPlane(
        normal=tuple(float(v) for v in n_p),  # type: ignore[arg-type]
        offset_mm=off_p,
        point_lps_mm=tuple(float(v) for v in grid.to_patient(foot)),  # type: ignore[arg-type]
        residual_mm=rms,
        median_mm=median,
        inlier_fraction=inliers,
        normal_grid=tuple(float(v) for v in n),  # type: ignore[arg-type]
        offset_grid_mm=d_grid,
        iterations=its,
        seconds=time.perf_counter() - t0,
        candidates=[{"median_mm": round(s, 4), "normal_grid": [round(float(v), 4) for v in c]} for s, _, c in scored],
    )
    if inliers < MIN_INLIER_FRACTION:
        raise NoSymmetryError(
            f"the bone has no mirror plane: at best {inliers:.0%} of its mirrored surface lies within a voxel of "
            f"its surface (residual {rms:.2f} mm); a template cannot be mirrored from it"
        )
    return plane


RING_SAMPLES = 6_000  # voxels of the ring around a piece that its plane is fitted on


def ring_plane(
    data: Any,
    grid: Grid,
    normal: FloatArray,
    offset: float,
    ring_index: Any,
    tissue: float,
    level: float,
    *,
    seed: int = 0,
) -> tuple[FloatArray, float, float]:
    """The mirror plane that best maps the scan onto itself on a ring of voxels around a defect (grid indices
    ``ring_index``, the defect left out): least squares (soft L1) of the difference between each voxel's bone
    fraction and its mirror image's (trilinear), the bone fraction being the sample scaled from the tissue (0) to
    the level (1), clipped to [0, 1.5]. Sub-voxel: the samples are interpolated, not thresholded. Starts from
    ``normal . g = offset`` (grid); returns the plane and the RMS of the differences. The Jacobian is the
    interpolant's own gradient (``_trilinear``), from the same samples as the residuals: one look-up per step
    where differences took four."""
    from scipy.optimize import least_squares

    idx = np.asarray(ring_index)
    if len(idx) < 100:
        return np.asarray(normal, dtype=np.float64), float(offset), float("nan")
    contrast = max(float(level - tissue), 1e-6)

    def bone_fraction(values: Any) -> Any:
        return np.clip((values - tissue) / contrast, 0.0, 1.5)

    rng = np.random.default_rng(seed)
    if len(idx) > RING_SAMPLES:
        # most samples where the bone fraction is not clipped (the bone's surfaces: what moves the fit), the rest
        # anywhere in the ring
        raw = (np.asarray(data[tuple(idx.T)], dtype=np.float64) - tissue) / contrast
        edge = np.flatnonzero((raw > 0.0) & (raw < 1.5))
        n_edge = min(len(edge), int(0.75 * RING_SAMPLES))
        pick = rng.choice(edge, n_edge, replace=False) if n_edge else np.zeros(0, dtype=np.int64)
        unpicked = np.ones(len(idx), dtype=bool)
        unpicked[pick] = False
        rest = np.flatnonzero(unpicked)  # the ring's other samples, ascending (a set difference without sorting)
        pick = np.concatenate([pick, rng.choice(rest, RING_SAMPLES - n_edge, replace=False)])
        idx = idx[np.sort(pick)]
    sp = np.asarray(grid.spacing_zyx)
    pts = grid.xyz(idx)
    centre = pts.mean(axis=0)

    own = bone_fraction(np.asarray(data[tuple(idx.T)], dtype=np.float64))
    n0 = np.asarray(normal, dtype=np.float64)
    e1, e2 = _tangents(n0)
    d0 = float(offset - n0 @ centre)

    def plane_of(x: Any) -> tuple[FloatArray, float, float]:
        u = n0 + x[0] * e1 + x[1] * e2
        length = float(np.linalg.norm(u))
        return u / length, float(d0 + x[2]), length

    rel = pts - centre
    last: dict[str, Any] = {}

    def evaluate(x: Any) -> tuple[Any, Any]:
        """The residuals and their Jacobian at ``x`` (one evaluation serves both of the solver's calls)."""
        key = np.asarray(x, dtype=np.float64).tobytes()
        if last.get("key") != key:
            n, d, length = plane_of(x)
            s = rel @ n - d
            q = rel - 2.0 * s[:, None] * n + centre
            value, grad = _trilinear(data, q[:, ::-1] / sp)
            grad = grad[:, ::-1] / sp[::-1]  # d value / d q (x, y, z mm)
            inside = (value > tissue) & (value < tissue + 1.5 * contrast)  # not clipped
            dq_dm = grad * (inside / contrast)[:, None]  # d residual / d q
            jac = np.empty((len(q), 3))
            for k, e in enumerate((e1, e2)):
                dn = (e - n * (n @ e)) / length  # the unit normal's turn along the parameter
                # q = p - 2 (n.p - d) n: dq = -2 ((p.dn) n + s dn)
                dq = -2.0 * ((rel @ dn)[:, None] * n + s[:, None] * dn)
                jac[:, k] = np.einsum("ij,ij->i", dq_dm, dq)
            jac[:, 2] = 2.0 * (dq_dm @ n)
            last.update(key=key, fun=bone_fraction(value) - own, jac=jac)
        return last["fun"], last["jac"]

    fit = least_squares(lambda x: evaluate(x)[0], np.zeros(3), jac=lambda x: evaluate(x)[1], loss="soft_l1",
                        f_scale=0.3, x_scale=[1e-3, 1e-3, 0.1], max_nfev=12, ftol=1e-6, xtol=1e-6)  # fmt: skip
    n, d = plane_of(fit.x)[:2]
    if n @ n0 < 0:
        n, d = -n, -d
    return n, float(d + n @ centre), float(np.sqrt(np.mean(fit.fun**2)))


def _trilinear(data: npt.NDArray[Any], at: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The trilinear interpolant of ``data`` at (N, 3) index coordinates (z, y, x), the edges' values beyond them
    (``ndi.map_coordinates(..., order=1, mode="nearest")``), and its gradient (N, 3) per index step (z, y, x; 0 along
    an axis where the point lies beyond the edge)."""
    shape = np.asarray(data.shape)
    c = np.clip(at, 0.0, shape - 1)
    i0 = np.minimum(np.floor(c).astype(np.int64), np.maximum(shape - 2, 0))
    f = c - i0
    up = (shape > 1).astype(np.int64)  # the next sample along each axis (the same one along an axis of one)
    iz, iy, ix = i0[:, 0], i0[:, 1], i0[:, 2]
    if data.flags.c_contiguous:  # one flat index per corner (a third of the time of three)
        flat, strides = data.reshape(-1), np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
        base = (iz * shape[1] + iy) * shape[2] + ix

        def corner(a: int, b: int, k: int) -> Any:
            return flat[base + int(np.array([a, b, k]) * up @ strides)]
    else:  # a crop of the scan: indices, not a copy

        def corner(a: int, b: int, k: int) -> Any:
            return data[iz + a * up[0], iy + b * up[1], ix + k * up[2]]

    v = np.empty((2, 2, 2, len(c)))
    for a in range(2):
        for b in range(2):
            for k in range(2):
                v[a, b, k] = corner(a, b, k)
    fz, fy, fx = f[:, 0], f[:, 1], f[:, 2]
    vx = v[:, :, 0] + fx * (v[:, :, 1] - v[:, :, 0])  # (2, 2, N): along x
    vxy = vx[:, 0] + fy * (vx[:, 1] - vx[:, 0])  # (2, N): then y
    value = vxy[0] + fz * (vxy[1] - vxy[0])
    gz = vxy[1] - vxy[0]
    dy = vx[:, 1] - vx[:, 0]
    gy = dy[0] + fz * (dy[1] - dy[0])
    dx = v[:, :, 1] - v[:, :, 0]
    dxy = dx[:, 0] + fy * (dx[:, 1] - dx[:, 0])
    gx = dxy[0] + fz * (dxy[1] - dxy[0])
    beyond = (at < 0.0) | (at > shape - 1)
    grad = np.where(beyond, 0.0, np.stack([gz, gy, gx], axis=1))
    return value, grad


def reflection(normal: Any, offset: float) -> tuple[FloatArray, FloatArray]:
    """The mirror across ``normal . p = offset`` as ``p -> a @ p + b``."""
    n = np.asarray(normal, dtype=np.float64)
    return np.eye(3) - 2.0 * np.outer(n, n), 2.0 * offset * n


def _hint_point(hint: Any) -> tuple[float, float, float] | None:
    if hint is None or isinstance(hint, str):
        return None
    point = getattr(hint, "point_lps_mm", hint)
    if point is None:
        return None
    p = tuple(float(v) for v in point)
    if len(p) != 3:
        raise ValueError(f"a point hint is (x, y, z) in mm, got {point!r}")
    return p  # type: ignore[return-value]
