"""Static objects: a sparse voxel radiance field, its numba kernels, training, the bake into a
PlenOctree, and the run folder (``dbb-train plenoctree``)."""
