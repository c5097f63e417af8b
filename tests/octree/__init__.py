"""Tests of dbb_capture.octree: the PlenOctree format, its renderers and the numba walk."""
