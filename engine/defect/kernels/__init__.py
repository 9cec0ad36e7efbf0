"""Warp kernels of the defect template (``edt``: exact Euclidean distance transform; ``mirror``: the mirrored scan
and the voxel tests of the defect rules). No host logic lives here."""
