"""Geometry shared by every stage: rigid transforms, camera models, the camera and pixel
conventions (and the only conversions between them), pixels to rays, viewpoints, and the
spherical-harmonic basis of the radiance fields. Imports nothing of ours but :mod:`..core`."""
