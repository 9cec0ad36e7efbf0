"""The unfilter kernels' block sizes and their wavefront's length, for the host (no Warp import)."""

from __future__ import annotations

BLOCK = 32  # samples of a row one thread reconstructs per launch
BAND = 4  # rows one thread reconstructs per launch (unfilter.cl defines the same two)


def wavefront_steps(height: int, width: int) -> int:
    """Launches of the unfilter kernel that reconstruct slices of ``height`` x ``width``: a column block's band
    follows its left neighbour's by one launch."""
    return -(-height // BAND) + -(-width // BLOCK) - 1
