"""Warp kernels of Marching Cubes 33 (``mc33``). No host logic lives here."""
