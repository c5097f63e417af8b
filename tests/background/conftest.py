"""Views of the plate capture, the true silhouette and the matte's IoU, and a ring of walls."""

from __future__ import annotations

import cv2
import numpy as np
import torch
from conftest import UP, ring_cameras

from dbb_capture.background.rays import RayBank, TrainingView
from dbb_capture.capture.footage import open_footage
from dbb_capture.crops.camera import crop_maps
from dbb_capture.crops.object import object_crop
from dbb_capture.geometry.conventions import opencv_from_opengl
from dbb_capture.geometry.rays import pixel_rays
from dbb_capture.geometry.transforms import look_at
from dbb_capture.synth.capture import load_ground_truth


def capture_views(cap, name, key):
    intr, cams, _ = load_ground_truth(cap)
    frames = list(open_footage(cap / name).read(range(len(cams[key]))))
    return [TrainingView(f.image, intr, opencv_from_opengl(np.array(c["transform_matrix"])))
            for f, c in zip(frames, cams[key])]


def true_alpha(cap, index, cam, intr, c2w):
    m = cv2.imread(str(cap / "ground_truth" / "masks" / f"{index:05d}.png"), cv2.IMREAD_GRAYSCALE)
    mx, my = crop_maps(cam, intr, c2w, 1)
    return cv2.remap(m, mx, my, cv2.INTER_LINEAR) > 127


def matte_ious(cap, model, video, center, radius, up):
    """IoU of the matte (64 px crops) with the true silhouette in every second video frame."""
    ious = []
    for i, v in enumerate(video[::2]):
        oc = object_crop(v.image, v.intr, v.c2w, center, radius, up, 64, 0.9, model.render,
                         guessed=model.guessed)
        truth = true_alpha(cap, 2 * i, oc.cam, v.intr, v.c2w)
        pred = oc.rgba[..., 3] > 127
        ious.append((truth & pred).sum() / (truth | pred).sum())
    return np.array(ious)


def wall_bank(center, radius_wall=2.5, n_views=16, size=40):
    """Rays of a ring of cameras looking up and away past the object at a textured spherical
    wall of radius ``radius_wall`` around ``center`` (none meets the board plane): colour from
    the wall point's direction, a checker of 8-degree cells."""
    o_all, d_all, c_all = [], [], []
    for m in ring_cameras(center, n=n_views):
        eye = m[:3, 3]
        target = center + 2.0 * (center - eye) * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, -0.8])
        cam = look_at(eye, target, UP)
        from dbb_capture.geometry.cameras import Intrinsics

        o, d = [a.reshape(-1, 3) for a in pixel_rays(Intrinsics(size, size, 60.0, 60.0, (size - 1) / 2, (size - 1) / 2), cam, np.float64)]
        oc = o - center
        b = (oc * d).sum(1)
        t = -b + np.sqrt(b * b - (oc * oc).sum(1) + radius_wall ** 2)
        q = (oc + t[:, None] * d) / radius_wall
        az, el = np.degrees(np.arctan2(q[:, 1], q[:, 0])), np.degrees(np.arcsin(q[:, 2]))
        check = ((np.floor(az / 8) + np.floor(el / 8)) % 2)[:, None]
        o_all.append(o), d_all.append(d), c_all.append(np.where(check > 0, [0.8, 0.7, 0.3], [0.2, 0.3, 0.6]))
    o, d, c = (torch.from_numpy(np.concatenate(x)).float() for x in (o_all, d_all, c_all))
    return RayBank(o, d, c)
