"""Imaging methods on frames: compositing, descattering, separation, quality measures.

Numpy in, numpy out; bad input raises :class:`polarstripe.imaging.validation.ImagingError`.
"""
