"""Warp's types of the backend's packed vector elements beyond ``wp.vec3`` / ``wp.vec3i``: ``vec10d`` (``VEC10D``,
ten float64: a quadric, whose kernels live in ``engine.decimation.kernels.quadrics``)."""

from __future__ import annotations

import warp as wp

vec10d = wp.types.vector(length=10, dtype=wp.float64)
