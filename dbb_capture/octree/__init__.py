"""PlenOctrees: the svox ``N3Tree`` format and its RGBA renderers (numba and PyTorch), all a bundle
consumer needs; nothing here imports the trainer."""
