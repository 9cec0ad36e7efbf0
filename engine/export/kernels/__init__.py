"""Warp kernels that lay a finished mesh out for its files and rasterise its preview (``layout``). No host logic
lives here."""
