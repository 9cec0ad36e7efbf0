"""Device kernels of the loaders (``unfilter``: PNG rows). No host logic lives here."""
