"""Deterministic bone-like CT phantom for isosurface benchmarks, in "HU + 1024" units.

``bone_phantom((nz, ny, nx))`` builds a long bone shaft along z inside soft tissue:

* air around the body (~0), a fat layer (~930) and muscle (~1050);
* a cortical tube (~2000-2800) with an elliptical cross-section, flared toward both ends and closed by end
  plates, wall thickness ``CORTEX_FRACTION`` of the mean radius (at least ``MIN_CORTEX_VOXELS``);
* marrow (~990) inside the tube, and trabecular (spongy) bone (struts ~1300-1600) filling both end regions,
  the struts thinning out toward mid-shaft. The struts are the band ``|n| < eps`` of a smooth random field ``n``
  (a sum of random 3-D plane waves, evaluated per plane as a small matrix product);
* a defect in the middle: a V-shaped wedge cut through one side of the cortex, and a drilled hole through
  both walls a little lower;
* 1-voxel partial-volume edges and Gaussian noise (sigma ``NOISE_HU``).

Generation runs plane by plane along z into one preallocated array, in a thread pool (numpy and BLAS release
the GIL); each task holds float32 temporaries of a single plane only. Every plane depends only on ``seed`` and
its z index, so the result does not depend on the thread count.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import numpy.typing as npt

BONE_LEVEL = 1324.5  # 300 HU + 1024 + 0.5: the iso level for bone
AIR, FAT, MUSCLE, MARROW = 0.0, 930.0, 1050.0, 990.0
CORTEX_MEAN, CORTEX_SWING = 2400.0, 350.0  # cortex in [2050, 2750] before noise
TRABECULAR = 1480.0  # strut value (partial volume brings thin struts down toward marrow)
NOISE_HU = 20.0
CORTEX_FRACTION = 0.06
MIN_CORTEX_VOXELS = 2.5
N_WAVES = 24
NOISE_BANK = 8

_SUPPORTED = (np.uint16, np.int16, np.float32)


def _waves(rng: np.random.Generator, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random plane waves: wave vectors (K, 3) in rad/voxel (z, y, x) and phases (K,)."""
    _, ny, nx = shape
    period = max(7.0, min(ny, nx) / 40.0)  # trabecular spacing, voxels
    d = rng.standard_normal((N_WAVES, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = (2.0 * np.pi / period) * rng.uniform(0.7, 1.4, N_WAVES)
    kvec = d * k[:, None]
    phase = rng.uniform(0.0, 2.0 * np.pi, N_WAVES)
    return kvec, phase, np.sqrt(2.0 / N_WAVES) * np.ones(N_WAVES)


def _soft(d: np.ndarray) -> np.ndarray:
    """Inside fraction for a signed distance in voxels (negative inside), 1-voxel ramp; in place."""
    np.subtract(0.5, d, out=d)
    np.clip(d, 0.0, 1.0, out=d)
    return d


def bone_phantom(
    shape: tuple[int, int, int] = (256, 256, 256),
    seed: int = 0,
    dtype: Any = np.uint16,
    *,
    workers: int | None = None,
) -> npt.NDArray[Any]:
    """Return a deterministic bone-like CT volume (nz, ny, nx) in HU + 1024 units.

    Args:
        shape: (nz, ny, nx), each at least 8.
        seed: random seed; same seed and shape give the same volume.
        dtype: uint16 (default), int16 or float32.
        workers: threads (default: the CPU count, at most 16); the result does not depend on it.

    Raises:
        ValueError: bad shape or dtype.
    """
    shape_t = tuple(int(s) for s in shape)
    if len(shape_t) != 3 or min(shape_t) < 8:
        raise ValueError(f"Expected shape (nz, ny, nx) with every size >= 8, got {shape!r}")
    dt = np.dtype(dtype)
    if dt.type not in _SUPPORTED:
        raise ValueError(f"Expected dtype uint16, int16 or float32, got {dt}")
    out = np.empty(shape_t, dtype=dt)
    planes = _Planes(shape_t, int(seed), out)
    n_workers = int(workers) if workers else min(os.cpu_count() or 1, 16)
    if n_workers <= 1:
        for z in range(shape_t[0]):
            planes.plane(z)
    else:
        with ThreadPoolExecutor(max_workers=n_workers) as ex:
            for _ in ex.map(planes.plane, range(shape_t[0])):
                pass
    return out


class _Planes:
    """The phantom's geometry, its wave and noise banks, made once; ``plane(z)`` writes one z plane of ``out``
    (thread-safe: each thread has its own scratch planes)."""

    def __init__(self, shape_t: tuple[int, ...], seed: int, out: npt.NDArray[Any]) -> None:
        nz, ny, nx = shape_t
        self.nz, self.ny, self.nx, self.out = nz, ny, nx, out
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0xB0E]))
        self.kvec, self.phase, amp = _waves(rng, shape_t)
        # geometry, in voxels
        cy0, cx0 = (ny - 1) / 2.0, (nx - 1) / 2.0
        self.a_bone, self.b_bone = a_bone, b_bone = 0.26 * nx, 0.21 * ny  # shaft semi-axes (x, y)
        self.r_mean = r_mean = float(np.sqrt(a_bone * b_bone))
        wall = max(MIN_CORTEX_VOXELS, CORTEX_FRACTION * r_mean)
        self.z_lo, self.z_hi = 0.04 * (nz - 1), 0.96 * (nz - 1)  # end plates (outer faces)
        self.end_len = 0.22 * (nz - 1)  # trabecular/flared end regions
        a_body, b_body = 0.47 * nx, 0.44 * ny
        fat_w = max(2.0, 0.03 * min(nx, ny))
        self.z_mid = 0.5 * (nz - 1)
        self.wedge_half_z, self.wedge_half_ang = max(3.0, 0.05 * nz), np.deg2rad(22.0)
        self.wedge_dir = np.deg2rad(35.0)
        self.hole_z, self.hole_r = 0.36 * (nz - 1), max(2.0, 0.12 * r_mean)
        self.phase_cortex = phase_cortex = rng.uniform(0, 2 * np.pi, 3)

        self.y = y = np.arange(ny, dtype=np.float32) - np.float32(cy0)
        self.x = x = np.arange(nx, dtype=np.float32) - np.float32(cx0)
        # in-plane wave factors: cos/sin(k_x x) (nx, K), k_y y (ny, K)
        bx = np.outer(x, self.kvec[:, 2]).astype(np.float32)
        cos_bx, sin_bx = np.cos(bx), np.sin(bx)
        self.ay = np.outer(y, self.kvec[:, 1]).astype(np.float32)
        v_mat = np.concatenate([cos_bx, -sin_bx], axis=1) * np.concatenate([amp, amp]).astype(np.float32)[None, :]
        self.v_mat_t = np.ascontiguousarray(v_mat.T)  # (2K, nx)

        # body (soft tissue) does not vary with z: precompute the in-plane tissue value
        yy, xx = y[:, None], x[None, :]
        rho_body = np.sqrt((xx / a_body) ** 2 + (yy / b_body) ** 2).astype(np.float32)
        r_body = np.float32(np.sqrt(a_body * b_body))
        d_body = (rho_body - 1.0) * r_body
        f_body = _soft(d_body.copy())
        f_muscle = _soft(d_body + np.float32(fat_w))
        self.tissue = (AIR + (FAT - AIR) * f_body + (MUSCLE - FAT) * f_muscle).astype(np.float32)
        angle = np.arctan2(yy * np.float32(a_bone / b_bone), xx).astype(np.float32)  # shaft angle, (ny, nx)
        self.cortex_ang = (CORTEX_SWING * 0.6 * np.cos(2 * angle + phase_cortex[0])).astype(np.float32)

        # noise: a bank of Gaussian planes, each z takes one rolled by a per-z pseudo-random offset (cheap and
        # deterministic; drawing 1G fresh normals would dominate the generation time)
        bank_rng = np.random.default_rng(np.random.SeedSequence([seed, 0xB0E, 1]))
        self.bank = bank_rng.standard_normal((NOISE_BANK, ny, nx), dtype=np.float32)
        self.bank *= np.float32(NOISE_HU)
        self.offs = bank_rng.integers(0, 1 << 30, size=(nz, 3))
        self.wall_v = np.float32(max(wall, 1.0))
        dt = out.dtype
        self.lo, self.hi = (
            (0.0, 65535.0) if dt == np.uint16 else ((-32768.0, 32767.0) if dt == np.int16 else (None, None))
        )
        self.local = threading.local()

    def scratch(self) -> dict[str, np.ndarray]:
        s = getattr(self.local, "s", None)
        if s is None:  # one set of one-plane float32 buffers per thread, reused (no per-plane allocation)
            s = {k: np.empty((self.ny, self.nx), np.float32) for k in ("d", "fo", "fi", "c", "inner", "t")}
            self.local.s = s
        return s

    def add_noise(self, v: np.ndarray, z: int) -> None:
        """v += bank[k] rolled by (dy, dx), without a temporary."""
        ny, nx, offs = self.ny, self.nx, self.offs
        k, dy, dx = int(offs[z, 0]) % NOISE_BANK, int(offs[z, 1]) % ny, int(offs[z, 2]) % nx
        src = self.bank[k]
        v[dy:, dx:] += src[: ny - dy, : nx - dx]
        v[dy:, :dx] += src[: ny - dy, nx - dx :]
        v[:dy, dx:] += src[ny - dy :, : nx - dx]
        v[:dy, :dx] += src[ny - dy :, nx - dx :]

    def store(self, z: int, v: np.ndarray) -> None:
        self.add_noise(v, z)
        if self.lo is not None:
            np.clip(v, self.lo, self.hi, out=v)
            np.rint(v, out=v)
        self.out[z] = v

    def plane(self, z: int) -> None:
        s = self.scratch()
        zf = float(z)
        dz_out = max(self.z_lo - zf, zf - self.z_hi)  # axial signed distance to the end plates
        if dz_out >= 0.5:  # beyond the bone's ends: soft tissue only
            np.copyto(s["c"], self.tissue)
            self.store(z, s["c"])
            return
        c, r, py, px, t_end, cy = self._cortex(s, zf, dz_out)
        self._defects(c, r, py, px, zf, cy)
        inner = self._cavity(s, zf, t_end)
        # compose: tissue -> bone (cortex) -> cavity
        t = s["t"]
        np.subtract(inner, c, out=t)
        t *= s["fi"]
        c += t
        c -= self.tissue
        c *= s["fo"]
        c += self.tissue
        self.store(z, c)

    def _cortex(self, s: dict[str, np.ndarray], zf: float, dz_out: float) -> tuple[Any, ...]:
        """The bone's outer and cavity fractions (``fo``, ``fi``) and the cortex's value ``c`` of plane z."""
        nz, ny, nx = self.nz, self.ny, self.nx
        # shaft axis wanders a little; ends flare (metaphysis)
        t_end = max(0.0, 1.0 - min(zf - self.z_lo, self.z_hi - zf) / self.end_len)  # 0 mid-shaft .. 1 at the ends
        flare = 1.0 + 0.35 * t_end * t_end
        cy = 0.03 * ny * np.sin(2 * np.pi * zf / nz + 0.3)
        cx = 0.04 * nx * np.sin(np.pi * zf / nz + 1.1)
        r = np.float32(self.r_mean * flare)
        px = (self.x - np.float32(cx)) / np.float32(self.a_bone * flare)
        py = (self.y - np.float32(cy)) / np.float32(self.b_bone * flare)
        d, fo, fi, c = s["d"], s["fo"], s["fi"], s["c"]
        np.add((py * py)[:, None], (px * px)[None, :], out=d)
        np.sqrt(d, out=d)
        d -= np.float32(1.0)
        d *= r  # ~ radial signed distance to the outer surface (voxels)
        np.maximum(d, np.float32(dz_out), out=fo)
        _soft(fo)  # bone (outer) fraction
        d += self.wall_v
        np.maximum(d, np.float32(dz_out + self.wall_v), out=fi)
        _soft(fi)  # cavity fraction
        swing = np.float32(CORTEX_MEAN + CORTEX_SWING * 0.4 * np.sin(6.0 * zf / nz + self.phase_cortex[1]))
        np.add(self.cortex_ang, swing, out=c)
        return c, r, py, px, t_end, cy

    def _defects(self, c: np.ndarray, r: Any, py: np.ndarray, px: np.ndarray, zf: float, cy: float) -> None:
        """The cortex's defect: a wedge (V-shaped in z) and a drilled hole (along x, through both walls)."""
        dzm = abs(zf - self.z_mid)
        if dzm < self.wedge_half_z:  # a few planes: temporaries are fine
            half = self.wedge_half_ang * (1.0 - dzm / self.wedge_half_z)
            ang = np.arctan2(py[:, None], px[None, :]) - np.float32(self.wedge_dir)  # angle around the shaft centre
            f_def = np.abs(np.arctan2(np.sin(ang), np.cos(ang))) - np.float32(half)
            f_def *= r  # arc length ~ voxels
            _soft(f_def)
            c += (MUSCLE - c) * f_def
        dzh = zf - self.hole_z
        if abs(dzh) < self.hole_r + 1.0:
            hy = np.sqrt(max(self.hole_r * self.hole_r - dzh * dzh, 0.0))
            f_h = np.abs(self.y - np.float32(cy)) - np.float32(hy)
            _soft(f_h)
            c += (MUSCLE - c) * f_h[:, None]

    def _cavity(self, s: dict[str, np.ndarray], zf: float, t_end: float) -> np.ndarray:
        """The cavity: marrow and trabecular struts (a band of a smooth random field), denser toward the ends."""
        inner = s["inner"]
        inner.fill(MARROW)
        if t_end > 0.0:
            u = self.ay + (self.kvec[:, 0] * zf + self.phase).astype(np.float32)[None, :]  # (ny, K)
            n = np.concatenate([np.cos(u), np.sin(u)], axis=1) @ self.v_mat_t  # (ny, nx): sum cos(k.x + phase)
            np.abs(n, out=n)
            n -= np.float32(0.45 * t_end - 0.12)
            n *= np.float32(1.0 / 0.12)  # ~1 voxel ramp of the band edge
            _soft(n)
            n *= np.float32(TRABECULAR - MARROW)
            inner += n
        return inner


if __name__ == "__main__":  # pragma: no cover - quick look
    import sys
    import time

    def _say(msg: str) -> None:
        sys.stdout.write(msg + "\n")

    shp = tuple(int(s) for s in (sys.argv[1] if len(sys.argv) > 1 else "256,256,256").split(","))
    t0 = time.perf_counter()
    vol = bone_phantom(shp)  # type: ignore[arg-type]
    dt_s = time.perf_counter() - t0
    _say(
        f"shape={vol.shape} dtype={vol.dtype} {dt_s:.2f}s min={vol.min()} max={vol.max()} "
        f"bone_frac={(vol > BONE_LEVEL).mean():.4f}"
    )
