"""Warp kernel of the stream compaction (``engine.backend.warp_backend.WarpBackend.compact``)."""

from __future__ import annotations

import warp as wp


@wp.kernel
def compact_kernel(
    flags: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.int32),
    indices: wp.array(dtype=wp.int32),
    ranks: wp.array(dtype=wp.int32),
):
    """Flagged position ``i`` goes to ``indices[pos[i]]``; ``ranks[i]`` is its place, or -1."""
    i = wp.tid()
    if flags[i] != 0:
        indices[pos[i]] = i
        ranks[i] = pos[i]
    else:
        ranks[i] = -1
