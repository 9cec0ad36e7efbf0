"""Warp kernels of ``engine.io`` (imported only where a device decodes: they import Warp)."""
