"""The backends' own kernels: stream compaction (``compact.py``, Warp; Warp scans with ``wp.utils.array_scan``)
and the OpenCL backend's scan and compaction (``scan.cl``)."""
