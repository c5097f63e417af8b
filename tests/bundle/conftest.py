"""The export command in-process, and cameras files (the runs and bundles: tests/conftest.py)."""

from __future__ import annotations

import json

import torch
from click.testing import CliRunner
from dbb_capture.cli.export import main

from dbb_capture.datasets.transforms import intrinsics_fields

torch.set_num_threads(1)


def run_cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def write_cameras(frames, path, per_frame=False, drop_intrinsics=False):
    from dbb_capture.geometry.conventions import opengl_from_opencv

    doc = {"frames": [{"file_path": f"images/{f.name}.jpg",
                       "transform_matrix": opengl_from_opencv(f.c2w).tolist()} for f in frames]}
    intr = intrinsics_fields(frames[0].intr)
    if not drop_intrinsics:
        if per_frame:
            for d in doc["frames"]:
                d.update(intr)
        else:
            doc.update(intr)
    path.write_text(json.dumps(doc))
    return path
