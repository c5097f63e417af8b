"""Deep Billboard capture toolkit: footage -> poses -> mattes -> crops -> model -> bundle.

Stages (one module each): ``io`` (footage), ``board``/``poses`` (ChArUco camera poses),
``background`` (clean-plate radiance field, mattes), ``crops`` (normalized RGBA crops),
``fields``/``octree`` (static objects), ``rssm`` (dynamic objects), ``bundle`` (export)
and ``synth`` (synthetic captures with ground truth).
"""

__version__ = "0.1.0"
