"""``preview.png``: a thumbnail of the model rendered on the CPU with numpy (no display, no OpenGL).

An orthographic z-buffer rasteriser: the mesh, in the glTF frame (+Y up, +Z toward the viewer: the patient's
front), is turned a little for a three-quarter view, fitted into the image with a margin, and its front-facing
triangles are scan-converted in batches (every pixel centre inside a triangle's bounding box is tested with
edge functions, the nearest sample per pixel wins). Shading is Lambert with the vertex normals interpolated, one
light from the upper left front and some ambient light; the background is transparent. Rendered at twice the size
and averaged down (anti-aliasing).
"""

from __future__ import annotations

import io

import numpy as np
import numpy.typing as npt

from engine.export.glb import BONE_MATERIAL, gltf_mesh

SUPERSAMPLE = 2
BATCH_SAMPLES = 1 << 21  # candidate pixels tested at once (memory bound)
LIGHT = np.array([-0.4, 0.6, 1.0]) / np.linalg.norm([-0.4, 0.6, 1.0])
AMBIENT = 0.28


def _view(yaw_deg: float, pitch_deg: float) -> npt.NDArray[np.float64]:
    """Rotation: turn the model by ``yaw`` about +Y, then tilt it by ``pitch`` about +X (toward the viewer)."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    yaw = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pitch = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return pitch @ yaw


def render(
    positions: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals: npt.ArrayLike,
    size: int = 320,
    *,
    yaw_deg: float = 25.0,
    pitch_deg: float = 12.0,
    margin: float = 0.06,
) -> npt.NDArray[np.uint8]:
    """Render a mesh given in the glTF frame to an RGBA image.

    Args:
        positions: (V, 3) vertices (any unit; +Y up, +Z toward the viewer).
        faces: (F, 3) counter-clockwise (outward) triangles.
        normals: (V, 3) unit vertex normals.
        size: the image's width and height in pixels.
        yaw_deg, pitch_deg: the turn of the model for the view.
        margin: free border, as a fraction of the size.

    Returns:
        (size, size, 4) uint8 RGBA; alpha 0 where no surface is seen.
    """
    rot = _view(yaw_deg, pitch_deg)
    pos = np.asarray(positions, dtype=np.float64) @ rot.T
    nrm = np.asarray(normals, dtype=np.float64) @ rot.T
    tris = np.asarray(faces, dtype=np.int64)
    n = size * SUPERSAMPLE
    lo, hi = pos[:, :2].min(axis=0), pos[:, :2].max(axis=0)
    scale = (1 - 2 * margin) * n / max(float((hi - lo).max()), 1e-12)
    centre = (lo + hi) / 2
    px = (pos[:, 0] - centre[0]) * scale + n / 2  # image x to the right
    py = n / 2 - (pos[:, 1] - centre[1]) * scale  # image y downward: +Y up is the top
    depth = -pos[:, 2]  # nearer to the viewer (larger z) is smaller
    shade = AMBIENT + (1 - AMBIENT) * np.clip(nrm @ LIGHT, 0.0, 1.0)

    x0, y0 = px[tris], py[tris]
    area = (x0[:, 1] - x0[:, 0]) * (y0[:, 2] - y0[:, 0]) - (x0[:, 2] - x0[:, 0]) * (y0[:, 1] - y0[:, 0])
    keep = area < -1e-12  # counter-clockwise in y-up is clockwise in the y-down image: front faces
    tris, x0, y0, area = tris[keep], x0[keep], y0[keep], area[keep]
    bx0 = np.clip(np.ceil(x0.min(axis=1) - 0.5), 0, n).astype(np.int64)
    bx1 = np.clip(np.floor(x0.max(axis=1) - 0.5), -1, n - 1).astype(np.int64)
    by0 = np.clip(np.ceil(y0.min(axis=1) - 0.5), 0, n).astype(np.int64)
    by1 = np.clip(np.floor(y0.max(axis=1) - 0.5), -1, n - 1).astype(np.int64)
    w, h = np.maximum(bx1 - bx0 + 1, 0), np.maximum(by1 - by0 + 1, 0)
    counts = w * h
    zbuf = np.full(n * n, np.inf)
    light = np.zeros(n * n)
    start = 0
    while start < len(tris):
        stop = start + max(1, int(np.searchsorted(np.cumsum(counts[start:]), BATCH_SAMPLES)))
        sel = np.arange(start, min(stop, len(tris)))
        start = sel[-1] + 1
        reps = counts[sel]
        if reps.sum() == 0:
            continue
        t = np.repeat(sel, reps)
        k = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
        sx = bx0[t] + k % w[t] + 0.5
        sy = by0[t] + k // w[t] + 0.5
        xs, ys = x0[t], y0[t]
        # barycentric weights from the edge functions (signed areas over the triangle's)
        w0 = ((xs[:, 1] - sx) * (ys[:, 2] - sy) - (xs[:, 2] - sx) * (ys[:, 1] - sy)) / area[t]
        w1 = ((xs[:, 2] - sx) * (ys[:, 0] - sy) - (xs[:, 0] - sx) * (ys[:, 2] - sy)) / area[t]
        w2 = 1.0 - w0 - w1
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        t, w0, w1, w2 = t[inside], w0[inside], w1[inside], w2[inside]
        pix = (sy[inside].astype(np.int64)) * n + sx[inside].astype(np.int64)
        vid = tris[t]
        z = w0 * depth[vid[:, 0]] + w1 * depth[vid[:, 1]] + w2 * depth[vid[:, 2]]
        s = w0 * shade[vid[:, 0]] + w1 * shade[vid[:, 1]] + w2 * shade[vid[:, 2]]
        order = np.lexsort((z, pix))  # by pixel, nearest first
        pix, z, s = pix[order], z[order], s[order]
        first = np.ones(len(pix), dtype=bool)
        first[1:] = pix[1:] != pix[:-1]
        pix, z, s = pix[first], z[first], s[first]
        nearer = z < zbuf[pix]
        zbuf[pix[nearer]] = z[nearer]
        light[pix[nearer]] = s[nearer]
    colour = np.asarray(BONE_MATERIAL["pbrMetallicRoughness"]["baseColorFactor"][:3]) * 255.0
    covered = np.isfinite(zbuf)
    rgba = np.zeros((n * n, 4))
    rgba[covered, :3] = light[covered, None] * colour
    rgba[covered, 3] = 255.0
    # premultiplied average of each SUPERSAMPLE x SUPERSAMPLE block, then back to straight alpha
    rgba[:, :3] *= rgba[:, 3:] / 255.0
    blocks = rgba.reshape(size, SUPERSAMPLE, size, SUPERSAMPLE, 4).mean(axis=(1, 3))
    alpha = blocks[..., 3:]
    blocks[..., :3] = np.divide(blocks[..., :3] * 255.0, alpha, out=np.zeros_like(blocks[..., :3]), where=alpha > 0)
    return np.clip(np.rint(blocks), 0, 255).astype(np.uint8)


def to_preview_png(
    vertices_zyx_mm: npt.ArrayLike, faces: npt.ArrayLike, normals_zyx: npt.ArrayLike | None = None, size: int = 320
) -> bytes:
    """A ``size`` x ``size`` PNG thumbnail of an engine mesh (the glTF files' view: head up, face forward).

    Raises:
        InputError: an empty or malformed mesh.
    """
    import imageio.v3 as iio

    positions, normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    buf = io.BytesIO()
    iio.imwrite(buf, render(positions, tris, normals, size), extension=".png")
    return buf.getvalue()
