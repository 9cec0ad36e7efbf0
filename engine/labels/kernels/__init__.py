"""Kernels of the per-label meshing: Warp (``labels.py``) and their OpenCL C twins (``labels.cl``)."""
