"""Accuracy metrics of a bone surface against its scan and against a reference surface.

Three families (definitions in ``docs/metrics.md``):

* **Slice similarity** (the paper's RMSE % and SSIM %, made exact, plus Dice): the mesh's cross-section at each
  slice plane ``z = k * dz`` is rasterised onto the slice's pixel centres (``y = j * dy``, ``x = i * dx``, mm, from
  the first sample) and compared with the ground truth ``volume[k] >= level``. See :func:`rasterize_slices`.
* **Surface distance**: closest-point distances in mm, both ways, from area-weighted random samples on each
  surface, through a Warp BVH query (``wp.mesh_query_point_no_sign``; CPU or CUDA). See :class:`DistanceReference`.
* **Mesh quality**: watertight, manifold, components, Euler characteristic (``engine.surface.meshcheck``), the
  distribution of each triangle's smallest angle, and volume / area change against a reference surface.

Meshes follow the engine's conventions: vertices (V, 3) (z, y, x) in mm, faces (F, 3) integer, outward when the
vertices are taken in (x, y, z) order. Everything works in face chunks, so memory stays bounded on 10^7-face meshes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from engine.surface.meshcheck import validate_mesh

_CHUNK = 1 << 21  # faces per chunk


def _check_mesh(verts: npt.ArrayLike, faces: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    v, f = validate_mesh(verts, faces)
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"Expected float vertices of shape (V, 3), got {v.dtype} {v.shape}")
    return v, f


def even_slices(n_slices: int, max_slices: int | None) -> npt.NDArray[np.int64]:
    """Slice indices to compare: all of ``range(n_slices)``, or ``max_slices`` of them evenly spread (first and last
    included)."""
    if n_slices < 1:
        raise ValueError(f"Expected at least one slice, got {n_slices}")
    if max_slices is None or max_slices >= n_slices:
        return np.arange(n_slices, dtype=np.int64)
    if max_slices < 1:
        raise ValueError(f"Expected max_slices >= 1, got {max_slices}")
    return np.unique(np.round(np.linspace(0, n_slices - 1, max_slices)).astype(np.int64))


def _expand(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ranges ``[lo[i], hi[i])``: the owner ``i`` and the value of every element, in order."""
    n = np.maximum(hi - lo, 0)
    owner = np.repeat(np.arange(len(lo)), n)
    start = np.cumsum(n) - n
    return owner, lo[owner] + (np.arange(len(owner)) - start[owner])


def _sections(tri: np.ndarray, planes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Oriented segments where triangles (F, 3, 3) (z, y, x) float64 cross the planes ``z = planes[k]`` (sorted).

    A vertex is *above* a plane when ``z > plane`` and *below* otherwise (a vertex on the plane is below: the
    plane is pushed up by an infinitesimal amount). Each vertex gets one side, so the segments of a closed mesh
    always join into closed loops, however many vertices lie on the plane. A triangle crosses when its vertices
    are not all on one side; its segment runs from the crossing on edge (alone, next) to the one on edge
    (previous, alone) when the lone vertex is above, the other way when it is below, which makes every loop turn
    counter-clockwise in (x, y) around the inside of an outward mesh.

    Returns:
        ``(k, p, q)``: plane index (P,), segment start and end (P, 2) as (y, x) float64.
    """
    z = tri[:, :, 0]
    lo = np.searchsorted(planes, z.min(axis=1), side="left")  # first plane with zmin <= plane
    hi = np.searchsorted(planes, z.max(axis=1), side="left")  # first plane with zmax <= plane
    face, k = _expand(lo, hi)
    z0 = planes[k]
    above = z[face] > z0[:, None]
    lone_above = above.sum(axis=1) == 1
    i = np.argmax(above == lone_above[:, None], axis=1)
    a = tri[face, i]
    b = tri[face, (i + 1) % 3]
    c = tri[face, (i + 2) % 3]
    p_ab = a[:, 1:] + ((z0 - a[:, 0]) / (b[:, 0] - a[:, 0]))[:, None] * (b[:, 1:] - a[:, 1:])
    p_ca = a[:, 1:] + ((z0 - a[:, 0]) / (c[:, 0] - a[:, 0]))[:, None] * (c[:, 1:] - a[:, 1:])
    start = np.where(lone_above[:, None], p_ab, p_ca)
    end = np.where(lone_above[:, None], p_ca, p_ab)
    return k, start, end


def rasterize_slices(
    verts: npt.ArrayLike,
    faces: npt.ArrayLike,
    shape_zyx: tuple[int, int, int],
    spacing_zyx_mm: tuple[float, float, float],
    z_indices: npt.ArrayLike | None = None,
) -> npt.NDArray[np.bool_]:
    """Rasterise a closed mesh's cross-sections at slice planes onto the slices' pixel centres.

    The section at plane ``z = k * dz`` is a set of closed, oriented polygons (see :func:`_sections` for the rule
    that makes planes through vertices safe). Pixel ``(j, i)`` at ``(y, x) = (j * dy, i * dx)`` is inside when the
    polygons' winding number around it is not zero (nonzero rule: for an outward mesh the winding is +1 inside,
    and overlaps left by self-intersections still count as inside). The winding is counted along each pixel row
    ``y = j * dy`` with the same half-open rule (an endpoint is above the row when ``y > j * dy``); a crossing at
    ``x_c`` counts for the pixels with ``i * dx < x_c``. All tests compare the stored coordinates exactly, and the
    grid positions ``k * dz``, ``j * dy``, ``i * dx`` are float32 products as in the MC33 kernel, so a vertex on the
    grid compares equal to it: the result is reproducible bit for bit, and a closed box whose corners lie on grid
    points covers exactly the samples in ``[lo, hi)`` along each axis.

    Args:
        verts: (V, 3) vertices (z, y, x) in mm (float32 or float64).
        faces: (F, 3) integer faces of a closed mesh (open borders leave unmatched crossings).
        shape_zyx: the volume's (nz, ny, nx).
        spacing_zyx_mm: (dz, dy, dx) in mm.
        z_indices: slice indices (default: all ``nz``).

    Returns:
        (K, ny, nx) bool, in the order of ``z_indices``.

    Raises:
        ValueError: malformed mesh, shape or spacing.
    """
    v32, f = _check_mesh(verts, faces)
    nz, ny, nx = (int(s) for s in shape_zyx)
    dz, dy, dx = (float(s) for s in spacing_zyx_mm)
    if min(nz, ny, nx) < 1 or min(dz, dy, dx) <= 0:
        raise ValueError(f"Expected a positive shape and spacing, got {shape_zyx} and {spacing_zyx_mm}")
    ks = np.arange(nz) if z_indices is None else np.asarray(z_indices, dtype=np.int64).reshape(-1)
    order = np.argsort(ks, kind="stable")
    # grid positions are float32 products, as the MC33 kernel computes its vertices: a vertex on a plane, row or
    # column compares equal to it (then float64 from here on)
    planes = (ks[order].astype(np.float32) * np.float32(dz)).astype(np.float64)
    rows_y = (np.arange(ny, dtype=np.float32) * np.float32(dy)).astype(np.float64)
    cols_x = (np.arange(nx, dtype=np.float32) * np.float32(dx)).astype(np.float64)
    diff = np.zeros((len(ks), ny, nx + 1), np.int32)
    for lo in range(0, len(f), _CHUNK):
        tri = f[lo : lo + _CHUNK]
        z = v32[tri, 0].astype(np.float64)
        crossing = np.searchsorted(planes, z.min(axis=1)) < np.searchsorted(planes, z.max(axis=1))
        k, p, q = _sections(v32[tri[crossing]].astype(np.float64), planes)
        ylo = np.minimum(p[:, 0], q[:, 0])
        yhi = np.maximum(p[:, 0], q[:, 0])
        seg, j = _expand(np.searchsorted(rows_y, ylo, side="left"), np.searchsorted(rows_y, yhi, side="left"))
        yr = rows_y[j]
        ps, qs = p[seg], q[seg]
        xc = ps[:, 1] + (yr - ps[:, 0]) / (qs[:, 0] - ps[:, 0]) * (qs[:, 1] - ps[:, 1])
        sign = np.where(qs[:, 0] > yr, 1, -1).astype(np.int32)
        col = np.searchsorted(cols_x, xc, side="left")  # pixels i < col lie left of the crossing
        kk = k[seg]
        np.add.at(diff, (kk, j, np.zeros_like(j)), sign)
        np.add.at(diff, (kk, j, col), -sign)
    winding = np.cumsum(diff[:, :, :nx], axis=2)
    out = np.empty((len(ks), ny, nx), bool)
    out[order] = winding != 0
    return out


def slice_similarity(
    verts: npt.ArrayLike,
    faces: npt.ArrayLike,
    volume: npt.NDArray[Any],
    level: float,
    spacing_zyx_mm: tuple[float, float, float],
    *,
    max_slices: int | None = None,
) -> dict[str, Any]:
    """The paper's similarity, made exact: RMSE %, SSIM % and Dice between the mesh's sections and the slices.

    For each compared slice ``k`` (all, or ``max_slices`` evenly spread), ``model = rasterize_slices(...)[k]`` and
    ``truth = volume[k] >= level`` are binary images (0/1). Per slice, ``RMSE = sqrt(mean((model - truth)^2))``
    (the square root of the fraction of pixels that differ) and ``SSIM`` is scikit-image's
    ``structural_similarity`` with ``data_range=1`` (7x7 uniform window). ``rmse_pct = 100 * (1 - RMSE)`` and
    ``ssim_pct = 100 * SSIM`` are averaged over the slices. ``dice = 2 |A and B| / (|A| + |B|)`` is pooled over all
    compared pixels (1 when both are empty).

    Args:
        verts, faces: the closed mesh (vertices (z, y, x) mm, first sample at the origin).
        volume: (nz, ny, nx) scan, after the same crop as the mesh.
        level: iso level in the volume's units (ground truth: samples at or above it).
        spacing_zyx_mm: (dz, dy, dx) in mm.
        max_slices: compare at most this many slices (evenly spread); None: all.

    Returns:
        ``rmse_pct``, ``ssim_pct``, ``dice``, ``slices`` (indices compared), ``rmse_pct_per_slice``,
        ``ssim_pct_per_slice``.

    Raises:
        ValueError: malformed mesh or volume, or slices smaller than the 7x7 SSIM window.
    """
    from skimage.metrics import structural_similarity

    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise ValueError(f"Expected a 3-D volume (nz, ny, nx), got shape {vol.shape}")
    if min(vol.shape[1:]) < 7:
        raise ValueError(f"Expected slices of at least 7x7 pixels for SSIM, got {vol.shape[1:]}")
    ks = even_slices(vol.shape[0], max_slices)
    model = rasterize_slices(verts, faces, vol.shape, spacing_zyx_mm, ks)
    rmse, ssim = [], []
    both = total = 0
    for m, k in zip(model, ks, strict=True):
        truth = vol[k] >= level
        rmse.append(100.0 * (1.0 - float(np.sqrt(np.count_nonzero(m != truth) / m.size))))
        ssim.append(
            100.0 * float(structural_similarity(truth.astype(np.float64), m.astype(np.float64), data_range=1.0))
        )
        both += int(np.count_nonzero(m & truth))
        total += int(np.count_nonzero(m)) + int(np.count_nonzero(truth))
    return {
        "rmse_pct": float(np.mean(rmse)),
        "ssim_pct": float(np.mean(ssim)),
        "dice": 1.0 if total == 0 else 2.0 * both / total,
        "slices": ks.tolist(),
        "rmse_pct_per_slice": rmse,
        "ssim_pct_per_slice": ssim,
    }


def sample_surface(verts: npt.ArrayLike, faces: npt.ArrayLike, n_points: int, seed: int = 0) -> npt.NDArray[np.float32]:
    """``n_points`` points drawn uniformly by area on the mesh (seeded): (n_points, 3) float32, (z, y, x) mm."""
    v, f = _check_mesh(verts, faces)
    if len(f) == 0 or n_points < 1:
        raise ValueError(f"Expected a non-empty mesh and n_points >= 1, got {len(f)} faces and {n_points}")
    area = np.empty(len(f), np.float64)
    for lo in range(0, len(f), _CHUNK):
        t = v[f[lo : lo + _CHUNK]].astype(np.float64)
        area[lo : lo + len(t)] = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    cum = np.cumsum(area)
    rng = np.random.default_rng(seed)
    face = np.minimum(np.searchsorted(cum, rng.uniform(0.0, cum[-1], n_points), side="right"), len(f) - 1)
    del cum, area
    r1 = np.sqrt(rng.uniform(size=n_points))[:, None]
    r2 = rng.uniform(size=n_points)[:, None]
    t = v[f[face]].astype(np.float64)
    pts = (1 - r1) * t[:, 0] + r1 * (1 - r2) * t[:, 1] + r1 * r2 * t[:, 2]
    return pts.astype(np.float32)


class SurfaceQuery:
    """Closest-point distances to one mesh through a Warp BVH (``wp.Mesh``), on CPU or CUDA.

    Args:
        verts: (V, 3) vertices (z, y, x) mm.
        faces: (F, 3) integer faces (non-empty).
        device: "auto", "cpu", "cuda" or "cuda:N".

    Warp leaves out of the search triangles that are (nearly) degenerate for their edge lengths; their
    neighbours cover the same place, so distances change by far less than a voxel.
    """

    def __init__(self, verts: npt.ArrayLike, faces: npt.ArrayLike, device: str = "auto") -> None:
        import warp as wp

        from engine.device import resolve_device

        v, f = _check_mesh(verts, faces)
        if len(f) == 0:
            raise ValueError("Expected a non-empty mesh to measure distances to")
        self.device = resolve_device(device)
        self._points = wp.array(np.ascontiguousarray(v, dtype=np.float32), dtype=wp.vec3, device=self.device)
        self._indices = wp.array(
            np.ascontiguousarray(f, dtype=np.int32).reshape(-1), dtype=wp.int32, device=self.device
        )
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)
        span = np.ptp(v, axis=0) if len(v) else np.zeros(3)
        self._max_dist = float(4.0 * np.linalg.norm(span) + 1e6)

    def distances(self, points: npt.ArrayLike, batch: int = 1 << 22) -> npt.NDArray[np.float64]:
        """(N,) distances in mm from ``points`` (N, 3) (z, y, x) mm to the mesh."""
        import warp as wp

        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        out = np.empty(len(pts), np.float64)
        from engine.paper.kernels.distance import closest_distance_kernel as kernel

        for lo in range(0, len(pts), batch):
            chunk = wp.array(pts[lo : lo + batch], dtype=wp.vec3, device=self.device)
            d = wp.empty(len(chunk), dtype=float, device=self.device)
            wp.launch(kernel, dim=len(chunk), inputs=[self._mesh.id, chunk, self._max_dist, d], device=self.device)
            out[lo : lo + len(chunk)] = d.numpy()  # sync point
        if np.any(out < 0):
            raise RuntimeError("a closest-point query found no face within the search radius")
        return out


def _summary(d: np.ndarray) -> dict[str, float]:
    return {"mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max())}


class DistanceReference:
    """A reference surface, sampled and indexed once, to measure other meshes against (both ways).

    Args:
        verts, faces: the reference mesh (vertices (z, y, x) mm).
        n_points: samples drawn on each surface (area-uniform, seeded).
        seed: the sampling seed (the reference and the compared mesh use ``seed`` and ``seed + 1``).
        device: "auto", "cpu", "cuda" or "cuda:N" for the BVH queries.
    """

    def __init__(
        self,
        verts: npt.ArrayLike,
        faces: npt.ArrayLike,
        *,
        n_points: int = 200_000,
        seed: int = 0,
        device: str = "auto",
    ) -> None:
        self.n_points = int(n_points)
        self.seed = int(seed)
        self.device = device
        self.query = SurfaceQuery(verts, faces, device)
        self.samples = sample_surface(verts, faces, self.n_points, self.seed)

    def compare(self, verts: npt.ArrayLike, faces: npt.ArrayLike) -> dict[str, Any]:
        """Distances between a mesh and the reference, in mm.

        Returns:
            ``to_reference`` and ``from_reference`` (each ``mean_mm``, ``p95_mm``, ``max_mm``: from the mesh's
            samples to the reference surface, and from the reference's samples to the mesh), and symmetric
            ``mean_mm`` (mean of all samples both ways), ``p95_mm`` (the larger p95) and ``hausdorff_mm``
            (the larger max; a sampled estimate, never above the true Hausdorff distance).
        """
        to_ref = self.query.distances(sample_surface(verts, faces, self.n_points, self.seed + 1))
        from_ref = SurfaceQuery(verts, faces, self.device).distances(self.samples)
        a, b = _summary(to_ref), _summary(from_ref)
        return {
            "to_reference": a,
            "from_reference": b,
            "mean_mm": float((to_ref.sum() + from_ref.sum()) / (len(to_ref) + len(from_ref))),
            "p95_mm": max(a["p95_mm"], b["p95_mm"]),
            "hausdorff_mm": max(a["max_mm"], b["max_mm"]),
        }


def surface_distance(
    verts: npt.ArrayLike,
    faces: npt.ArrayLike,
    ref_verts: npt.ArrayLike,
    ref_faces: npt.ArrayLike,
    *,
    n_points: int = 200_000,
    seed: int = 0,
    device: str = "auto",
) -> dict[str, Any]:
    """Distances between two meshes, both ways (see :meth:`DistanceReference.compare`)."""
    return DistanceReference(ref_verts, ref_faces, n_points=n_points, seed=seed, device=device).compare(verts, faces)


def volume_area(verts: npt.ArrayLike, faces: npt.ArrayLike) -> tuple[float, float]:
    """Signed volume (mm^3, positive for an outward closed mesh) and area (mm^2), float64 sums over face chunks."""
    v, f = _check_mesh(verts, faces)
    vol = area = 0.0
    for lo in range(0, len(f), _CHUNK):
        t = v[f[lo : lo + _CHUNK]][:, :, ::-1].astype(np.float64)  # (x, y, z)
        vol += float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum()) / 6.0
        area += float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()) / 2.0
    return vol, area


def min_angles_deg(verts: npt.ArrayLike, faces: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Each triangle's smallest interior angle in degrees, (F,) float32 (0 for a degenerate triangle)."""
    v, f = _check_mesh(verts, faces)
    out = np.empty(len(f), np.float32)
    for lo in range(0, len(f), _CHUNK):
        t = v[f[lo : lo + _CHUNK]].astype(np.float64)
        e = [t[:, 1] - t[:, 0], t[:, 2] - t[:, 1], t[:, 0] - t[:, 2]]
        sq = np.stack([np.einsum("ij,ij->i", x, x) for x in e], axis=1)  # squared edge lengths
        shortest = np.argmin(sq, axis=1)
        r = np.arange(len(t))
        # the smallest angle faces the shortest edge: law of cosines
        a2 = sq[r, shortest]
        b2 = sq[r, (shortest + 1) % 3]
        c2 = sq[r, (shortest + 2) % 3]
        denom = 2.0 * np.sqrt(b2 * c2)
        cos = np.divide(b2 + c2 - a2, denom, out=np.ones_like(denom), where=denom > 0)
        out[lo : lo + len(t)] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def mesh_quality(
    verts: npt.ArrayLike,
    faces: npt.ArrayLike,
    *,
    stats: dict[str, Any] | None = None,
    reference_stats: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Topology, triangle shape and volume / area change of a mesh.

    Args:
        verts, faces: the mesh.
        stats: its ``engine.surface.meshcheck.mesh_stats`` when already known (the pipeline report has them).
        reference_stats: the reference surface's ``mesh_stats``, for the changes.

    Returns:
        ``watertight``, ``manifold``, ``components``, ``euler``, ``volume_mm3``, ``area_mm2`` (absolute values),
        ``min_angle_deg`` (``min``, ``p1``, ``p5``, ``p50`` of the per-triangle smallest angle),
        ``below_10deg`` and ``below_20deg`` (fractions of triangles), and with a reference
        ``volume_change_pct`` and ``area_change_pct`` (100 * (this / reference - 1)).
    """
    from engine.surface.meshcheck import mesh_stats

    st = stats if stats is not None else mesh_stats(np.asarray(verts), np.asarray(faces))
    ang = min_angles_deg(verts, faces)
    out: dict[str, Any] = {
        "watertight": bool(st["watertight"]),
        "manifold": bool(st["manifold"]),
        "components": int(st["components"]),
        "euler": int(st["euler"]),
        "volume_mm3": abs(float(st["volume_mm3"])),
        "area_mm2": float(st["area_mm2"]),
        "min_angle_deg": {
            "min": float(ang.min()) if len(ang) else 0.0,
            **{f"p{p}": float(np.percentile(ang, p)) if len(ang) else 0.0 for p in (1, 5, 50)},
        },
        "below_10deg": float(np.mean(ang < 10)) if len(ang) else 0.0,
        "below_20deg": float(np.mean(ang < 20)) if len(ang) else 0.0,
    }
    if reference_stats is not None:
        ref_vol, ref_area = abs(float(reference_stats["volume_mm3"])), float(reference_stats["area_mm2"])
        out["volume_change_pct"] = 100.0 * (out["volume_mm3"] / ref_vol - 1.0) if ref_vol else float("nan")
        out["area_change_pct"] = 100.0 * (out["area_mm2"] / ref_area - 1.0) if ref_area else float("nan")
    return out
