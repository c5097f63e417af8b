"""Tests of dbb_capture.static: the voxel field, its kernels and training, the bake, the run folder."""
