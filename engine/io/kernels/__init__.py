"""Device kernels of the loaders (``unfilter``: PNG rows; ``steps``: its block sizes and launch count, shared with the
host without importing Warp). No host logic lives here."""
