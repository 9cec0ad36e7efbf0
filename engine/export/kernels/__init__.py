"""Warp kernels that lay a finished mesh out for its files and rasterise its preview (``layout``), and the layout's
OpenCL C twins (``layout.cl``, named in ``engine.export.kernel_specs``). No host logic lives here."""
