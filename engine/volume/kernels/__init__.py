"""Warp kernels on volumes (``gaussian``). No host logic lives here."""
