"""Warp kernels of the paper's metrics (``distance``). No host logic lives here."""
