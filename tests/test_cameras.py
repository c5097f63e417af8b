"""Camera conventions: OpenCV inside, OpenGL in transforms files, converted in one place."""

import numpy as np

from dbb_capture.geometry.cameras import Intrinsics, project_points
from dbb_capture.geometry.rays import camera_rays, pixel_grid
from dbb_capture.geometry.transforms import invert_rigid, look_at
from dbb_capture.geometry.conventions import opencv_from_opengl, opengl_from_opencv


def test_opengl_opencv_round_trip_and_axes():
    c2w = look_at(np.array([0.1, -0.5, -0.4]), np.zeros(3), np.array([0, 0, -1.0]))
    gl = opengl_from_opencv(c2w)
    assert np.allclose(opencv_from_opengl(gl), c2w)
    # OpenGL cameras look along their -z; OpenCV along +z: same world direction.
    assert np.allclose(-gl[:3, 2], c2w[:3, 2])
    assert np.allclose(gl[:3, 3], c2w[:3, 3])


def test_look_at_keeps_image_up_toward_up():
    up = np.array([0, 0, -1.0])
    c2w = look_at(np.array([0.3, -0.6, -0.5]), np.array([0.1, 0.1, 0.0]), up)
    R = c2w[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1)
    # Image up is camera -y; it must have a positive component along the world up.
    assert (-R[:, 1]) @ up > 0.5
    # The target projects to the principal point.
    intr = Intrinsics(640, 480, 500, 500, 319.5, 239.5)
    uv = project_points(np.array([0.1, 0.1, 0.0]), c2w, intr)
    assert np.allclose(uv, [319.5, 239.5], atol=1e-9)


def test_invert_rigid():
    c2w = look_at(np.array([1.0, 2, 3]), np.zeros(3), np.array([0, 0, 1.0]))
    assert np.allclose(invert_rigid(c2w) @ c2w, np.eye(4), atol=1e-12)


def test_camera_rays_invert_projection_with_distortion():
    intr = Intrinsics(640, 480, 520, 515, 322.3, 236.9, (-0.28, 0.09, 0.001, -0.0007, -0.01))
    px = pixel_grid(640, 480)[::37, ::41].reshape(-1, 2)
    rays = camera_rays(intr, px)
    pts = rays * 0.7  # points along each ray, camera frame = world frame here
    uv = project_points(pts, np.eye(4), intr)
    assert np.abs(uv - px).max() < 1e-3
