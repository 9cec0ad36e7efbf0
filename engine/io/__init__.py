"""Loaders: slice stacks and DICOM series -> (z, y, x) arrays."""
