"""Device operations of the defect template on Warp arrays (kernels in ``engine.defect.kernels``): the exact
Euclidean distance transform and the mask selections."""

from __future__ import annotations

from typing import Any

BIG_MM = 1.0e30  # "no feature": the distance where a transform found nothing


def distance(mask: Any, spacing_zyx: tuple[float, float, float], *, inside: bool = False) -> Any:
    """Exact Euclidean distance (mm, float32 ``wp.array3d``) from every voxel to the nearest set voxel of ``mask``
    (uint8 ``wp.array3d``), or with ``inside`` to the nearest clear voxel; ``BIG_MM`` where there is none.

    Felzenszwalb and Huttenlocher's separable transform: one pass per axis, one thread per grid line.
    """
    import warp as wp

    from engine.defect.kernels.edt import edt_pass_kernel, features_kernel, sqrt_kernel

    dev = mask.device
    shape = tuple(int(n) for n in mask.shape)
    n = shape[0] * shape[1] * shape[2]
    flat = mask.reshape((n,))
    f = wp.empty(n, dtype=wp.float32, device=dev)
    g = wp.empty(n, dtype=wp.float32, device=dev)
    wp.launch(features_kernel, dim=n, inputs=[flat, int(inside), f], device=dev)
    scratch = n + n // min(shape) + 1  # (length + 1) entries per line, on the axis with the most lines
    v = wp.empty(scratch, dtype=wp.int32, device=dev)
    zb = wp.empty(scratch, dtype=wp.float32, device=dev)
    for axis in (2, 1, 0):
        wp.launch(
            edt_pass_kernel,
            dim=n // shape[axis],
            inputs=[f, g, wp.vec3i(*shape), axis, float(spacing_zyx[axis]), v, zb],
            device=dev,
        )
        f, g = g, f
    wp.launch(sqrt_kernel, dim=n, inputs=[f, g], device=dev)
    return g.reshape(shape)


def select(src: Any, value: int) -> Any:
    """uint8 mask: src == value."""
    import warp as wp

    from engine.defect.kernels.mirror import select_kernel

    out = wp.empty(src.shape, dtype=wp.uint8, device=src.device)
    wp.launch(select_kernel, dim=src.shape, inputs=[src, int(value), out], device=src.device)
    return out


def bits(src: Any, which: int) -> Any:
    """uint8 mask: any of the bits ``which`` set in src."""
    import warp as wp

    from engine.defect.kernels.mirror import bits_kernel

    out = wp.empty(src.shape, dtype=wp.uint8, device=src.device)
    wp.launch(bits_kernel, dim=src.shape, inputs=[src, int(which), out], device=src.device)
    return out
