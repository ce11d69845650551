"""Imaging methods on frames: compositing, descattering, separation, quality measures (numpy in, numpy out)."""
