"""``preview.png``: a thumbnail of the model, rendered by a device kernel on any backend (``engine.backend``: the
Warp kernel ``engine.export.kernels.layout.rasterize_nearest`` or its OpenCL C twin ``kernels/preview.cl``; no
display, no OpenGL; on the CPU where there is no GPU).

An orthographic z-buffer rasteriser: the mesh, in the glTF frame (+Y up, +Z toward the viewer: the patient's
front), is turned a little for a three-quarter view and fitted into the image with a margin. One thread per
front-facing triangle tests every pixel centre in its bounding box with edge functions and takes the atomic min of
a packed (depth, triangle) key per pixel (``engine.export.kernels.layout.rasterize_nearest``): the nearest triangle
wins, ties go to the lower index, so the image is the same on every run and device. Each seen pixel is then shaded
on the host from its triangle. Shading is Lambert with the vertex normals interpolated, one
light from the upper left front and some ambient light; the background is transparent. Rendered at twice the size
and averaged down (anti-aliasing).
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.backend.base import VEC3I, Backend, Kernel
from engine.export.glb import BONE_MATERIAL, gltf_mesh

SUPERSAMPLE = 2
LIGHT = np.array([-0.4, 0.6, 1.0]) / np.linalg.norm([-0.4, 0.6, 1.0])
AMBIENT = 0.28
EMPTY = np.iinfo(np.int64).max  # a pixel no triangle covers
_EMPTY32 = np.iinfo(np.int32).max
_W, _CL = "engine.export.kernels.layout", "engine.export.kernels:preview.cl"
RASTERIZE = Kernel("preview.rasterize", f"{_W}:rasterize_nearest", f"{_CL}:rasterize_nearest")
# OpenCL without 64-bit atomics: the depth, then the triangle at that depth (OpenCL C only: Warp has 64-bit atomics)
RASTER_DEPTH = Kernel("preview.depth", f"{_W}:rasterize_nearest", f"{_CL}:raster_depth")
RASTER_TRIANGLE = Kernel("preview.triangle", f"{_W}:rasterize_nearest", f"{_CL}:raster_triangle")
INT64_ATOMICS = "cl_khr_int64_extended_atomics"


def _backend(device: Any) -> Backend:
    """The backend of ``device`` (None: Warp's current device)."""
    from engine.backend.select import get_backend

    if device is None:
        import warp as wp

        device = wp.get_device()
    return get_backend(device)


def rasterize(
    device: Any,
    px: npt.NDArray[np.float64],
    py: npt.NDArray[np.float64],
    depth: npt.NDArray[np.float64],
    tris: npt.NDArray[np.int32],
    n: int,
    *,
    two_pass: bool | None = None,
) -> npt.NDArray[np.int64]:
    """The z-buffer of an ``n`` x ``n`` image (see the module): per pixel ``(depth code << 32) | triangle`` of the
    nearest triangle (ties: the lower index), ``EMPTY`` where none; the same on every backend. ``two_pass``: OpenCL
    in two passes of 32-bit atomics (by default where the device lacks 64-bit atomic min)."""
    be = _backend(device)
    nearest = be.full(n * n, EMPTY, np.int64)
    if not len(tris):
        return be.to_host(nearest)
    args = [be.from_host(a.astype(np.float32)) for a in (px, py, depth)]
    args.append(be.from_host(tris, VEC3I))
    if two_pass is None:
        two_pass = be.kind == "opencl" and INT64_ATOMICS not in be.device.extensions  # type: ignore[attr-defined]
    if not (two_pass and be.kind == "opencl"):
        be.launch(RASTERIZE, len(tris), [*args, n, nearest])
        return be.to_host(nearest)
    zbuf = be.full(n * n, _EMPTY32, np.int32)
    winner = be.full(n * n, _EMPTY32, np.int32)
    be.launch(RASTER_DEPTH, len(tris), [*args, n, zbuf])
    be.launch(RASTER_TRIANGLE, len(tris), [*args, n, zbuf, winner])
    code, tri = be.to_host(zbuf).astype(np.int64), be.to_host(winner).astype(np.int64)
    return np.where(code == _EMPTY32, EMPTY, (code << 32) | tri)


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
    device: Any = None,
) -> npt.NDArray[np.uint8]:
    """Render a mesh given in the glTF frame to an RGBA image.

    Args:
        positions: (V, 3) vertices (any unit; +Y up, +Z toward the viewer).
        faces: (F, 3) counter-clockwise (outward) triangles.
        normals: (V, 3) unit vertex normals.
        size: the image's width and height in pixels.
        yaw_deg, pitch_deg: the turn of the model for the view.
        margin: free border, as a fraction of the size.
        device: where it rasterises: a ``Backend``, a device spec or a Warp device (None: Warp's current one).

    Returns:
        (size, size, 4) uint8 RGBA; alpha 0 where no surface is seen.
    """
    rot = _view(yaw_deg, pitch_deg)
    pos = np.asarray(positions, dtype=np.float64) @ rot.T
    nrm = np.asarray(normals, dtype=np.float64) @ rot.T
    tris = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    n = size * SUPERSAMPLE
    lo, hi = pos[:, :2].min(axis=0), pos[:, :2].max(axis=0)
    scale = (1 - 2 * margin) * n / max(float((hi - lo).max()), 1e-12)
    centre = (lo + hi) / 2
    px = (pos[:, 0] - centre[0]) * scale + n / 2  # image x to the right
    py = n / 2 - (pos[:, 1] - centre[1]) * scale  # image y downward: +Y up is the top
    near, far = pos[:, 2].max(), pos[:, 2].min()
    depth = (near - pos[:, 2]) / max(near - far, 1e-12)  # 0 nearest the viewer (larger z), 1 farthest
    shade = AMBIENT + (1 - AMBIENT) * np.clip(nrm @ LIGHT, 0.0, 1.0)

    key = rasterize(device, px, py, depth, tris, n)
    covered = key != EMPTY
    # each seen pixel's shade: its nearest triangle's vertex shades, interpolated at the pixel centre (float64)
    pix = np.flatnonzero(covered)
    vid = tris[(key[pix] & 0xFFFFFFFF).astype(np.int64)]
    sx, sy = pix % n + 0.5, pix // n + 0.5
    xs, ys = px[vid], py[vid]
    area = (xs[:, 1] - xs[:, 0]) * (ys[:, 2] - ys[:, 0]) - (xs[:, 2] - xs[:, 0]) * (ys[:, 1] - ys[:, 0])
    w0 = ((xs[:, 1] - sx) * (ys[:, 2] - sy) - (xs[:, 2] - sx) * (ys[:, 1] - sy)) / area
    w1 = ((xs[:, 2] - sx) * (ys[:, 0] - sy) - (xs[:, 0] - sx) * (ys[:, 2] - sy)) / area
    weights = np.clip(np.stack([w0, w1, 1.0 - w0 - w1], axis=1), 0.0, 1.0)
    light = np.zeros(n * n)
    light[pix] = (weights * shade[vid]).sum(axis=1) / np.maximum(weights.sum(axis=1), 1e-12)
    colour = np.asarray(BONE_MATERIAL["pbrMetallicRoughness"]["baseColorFactor"][:3]) * 255.0
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
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None = None,
    size: int = 320,
    *,
    device: Any = None,
) -> bytes:
    """A ``size`` x ``size`` PNG thumbnail of an engine mesh (the glTF files' view: head up, face forward),
    rasterised on ``device`` (``render``'s).

    Raises:
        InputError: an empty or malformed mesh.
    """
    import imageio.v3 as iio

    positions, normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    buf = io.BytesIO()
    iio.imwrite(buf, render(positions, tris, normals, size, device=device), extension=".png")
    return buf.getvalue()
