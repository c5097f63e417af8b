"""Proxy meshes: bundle space, closed meshes within the budget, collision nodes in the glb."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import gltf_reports

from dbb_capture.bundle.proxy import (
    MAX_TRIANGLES,
    bundle_from_board,
    density_level,
    occupancy_mesh,
    read_glb,
    sphere_proxy,
    static_proxy,
    transform_points,
    write_glb,
)


def _ellipsoid_grid(G=64, radii=(0.06, 0.04, 0.08), center=(0.3, 0.1, -0.08)):
    lo = np.asarray(center) - 0.1
    hi = np.asarray(center) + 0.1
    ax = [lo[i] + (np.arange(G) + 0.5) / G * 0.2 for i in range(3)]
    P = np.stack(np.meshgrid(*ax, indexing="ij"), -1)
    q = (((P - center) / np.asarray(radii)) ** 2).sum(-1)
    return q, lo, hi


def test_bundle_space_is_object_centred_y_up_right_handed():
    c = np.array([0.3, 0.1, -0.08])
    for up in ([0, 0, -1.0], [0, 0, 1.0], [1.0, 0, 0]):
        T = bundle_from_board(c, np.array(up))
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(transform_points(T, c), 0)
        assert np.allclose(transform_points(T, c + np.array(up)), [0, 1, 0])    # up becomes +Y
    # Board face up (up = -z): bundle +X stays the board's x axis.
    T = bundle_from_board(c, np.array([0, 0, -1.0]))
    assert np.allclose(T[0, :3], [1, 0, 0])


def test_voxels_make_one_closed_mesh_within_the_budget():
    import trimesh

    q, lo, hi = _ellipsoid_grid()
    mask = q <= 1
    mask[2:5, 2:5, 2:5] = True                        # a stray blob: not the largest part
    mask[30:34, 30:34, 30:34] = False                 # a cavity: filled
    v, f = occupancy_mesh(mask, lo, hi, max_triangles=800)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and len(f) <= 800 and m.volume > 0
    want = 4 / 3 * math.pi * 0.06 * 0.04 * 0.08
    assert m.volume == pytest.approx(want, rel=0.06)
    assert m.bounds[0][0] > lo[0] + 0.03                # the stray blob near the corner is gone


def test_static_proxy_from_a_soft_density_grid(tmp_path):
    import trimesh

    q, lo, hi = _ellipsoid_grid(G=96)
    sigma = 60.0 / (1 + np.exp((q - 1) * 12))          # soft edge, ~60 per metre inside
    sigma[q > 1.6] = 0
    np.savez_compressed(tmp_path / "density_grid.npz", sigma=sigma.astype(np.float16), bbox_min=lo, bbox_max=hi)
    assert 20 < density_level(sigma) < 40
    T = bundle_from_board((lo + hi) / 2, np.array([0, 0, -1.0]))
    p = static_proxy(tmp_path / "density_grid.npz", T)
    assert p.method == "marching cubes" and p.watertight and len(p.faces) <= MAX_TRIANGLES
    m = trimesh.Trimesh(p.vertices, p.faces)
    assert m.volume == pytest.approx(4 / 3 * math.pi * 0.06 * 0.04 * 0.08, rel=0.08)
    # Bundle space: +Y is up (board -z), so the 0.08 m radius along board z is the Y extent.
    ext = m.bounds[1] - m.bounds[0]
    assert ext[1] == pytest.approx(0.16, abs=0.01) and ext[0] == pytest.approx(0.12, abs=0.01)
    hull = trimesh.Trimesh(p.hull_vertices, p.hull_faces)
    assert hull.is_watertight and hull.volume >= m.volume * 0.999


def test_glb_has_collision_nodes_and_reads_back_watertight(tmp_path):
    import pygltflib

    T = bundle_from_board(np.array([0.3, 0.1, -0.05]), np.array([0, 0, -1.0]))
    p = sphere_proxy(0.05, T, np.array([0.3, 0.1, -0.05]), "test sphere")
    write_glb(tmp_path / "proxy.glb", p, "toy")
    g = pygltflib.GLTF2().load(str(tmp_path / "proxy.glb"))
    assert sorted(n.name for n in g.nodes) == ["toy-colonly", "toy-convcolonly"]
    meshes = read_glb(tmp_path / "proxy.glb")
    col = meshes["toy-colonly"]
    assert col.is_watertight
    assert np.allclose(col.bounds, [[-0.05] * 3, [0.05] * 3], atol=2e-3)   # centred on the origin


def test_glb_passes_the_khronos_validator_without_a_hint(tmp_path):
    """The Khronos glTF validator finds no error, warning, info or hint in a proxy file (buffer
    views say whether they hold vertices or indices)."""
    q, lo, hi = _ellipsoid_grid()
    sigma = np.where(q > 1.6, 0.0, 60.0 / (1 + np.exp((q - 1) * 12)))     # soft edge, ~60 per metre inside
    np.savez_compressed(tmp_path / "density_grid.npz", sigma=sigma.astype(np.float16), bbox_min=lo, bbox_max=hi)
    T = bundle_from_board((lo + hi) / 2, np.array([0, 0, -1.0]))
    write_glb(tmp_path / "proxy.glb", static_proxy(tmp_path / "density_grid.npz", T), "toy")
    (report,) = gltf_reports(tmp_path / "proxy.glb")
    assert (report["errors"], report["warnings"], report["infos"], report["hints"]) == (0, 0, 0, 0), report


def test_the_proxy_is_cut_at_the_board_plane_and_rests_on_it(tmp_path):
    """An object whose sphere reaches 15 mm under the table (as the static sample's does): the
    proxy's base lies on the board plane, closed, and valid glTF; a sphere proxy is flattened too."""
    import trimesh

    from dbb_capture.bundle.proxy import SupportPlane

    up = np.array([0, 0, -1.0])
    center = (0.3, 0.1, -0.085)                                     # 85 mm above the board
    q, lo, hi = _ellipsoid_grid(radii=(0.06, 0.04, 0.1), center=center)
    sigma = np.where(q > 1.6, 0.0, 60.0 / (1 + np.exp((q - 1) * 12)))
    np.savez_compressed(tmp_path / "density_grid.npz", sigma=sigma.astype(np.float16), bbox_min=lo, bbox_max=hi)
    T = bundle_from_board(np.asarray(center), up)
    support = SupportPlane.board(up)
    plane = support.in_bundle(T)
    assert plane["normal"] == [0.0, 1.0, 0.0] and plane["point"] == pytest.approx([0.0, -0.085, 0.0])
    floor_y = plane["point"][1]
    uncut = static_proxy(tmp_path / "density_grid.npz", T)
    assert uncut.vertices[:, 1].min() - floor_y < -0.012            # reaches under the table
    p = static_proxy(tmp_path / "density_grid.npz", T, support=support)
    assert abs(p.vertices[:, 1].min() - floor_y) < 1e-3 and p.base_m == 0.0
    assert p.watertight and len(p.faces) <= MAX_TRIANGLES and "cut at the board plane" in p.note
    assert abs(p.hull_vertices[:, 1].min() - floor_y) < 1e-3
    base = p.vertices[np.abs(p.vertices[:, 1] - floor_y) < 1e-4]     # a flat base, about the cut's 63 mm
    assert 0.05 < np.ptp(base[:, 0]) < 0.064
    # Volume: the ellipsoid less its cap under the table (a cap of 0.15 of the height: 6.1 % of it).
    full = 4 / 3 * math.pi * 0.06 * 0.04 * 0.1
    assert trimesh.Trimesh(p.vertices, p.faces).volume == pytest.approx(full * (1 - 0.0607), rel=0.06)
    s = sphere_proxy(0.1, T, np.asarray(center), "sphere", support)
    assert s.watertight and abs(s.vertices[:, 1].min() - floor_y) < 1e-9 and s.vertices[:, 1].max() == pytest.approx(0.1)
    write_glb(tmp_path / "cut.glb", p, "toy")
    write_glb(tmp_path / "sphere.glb", s, "toy")
    for r in gltf_reports(tmp_path / "cut.glb", tmp_path / "sphere.glb"):
        assert (r["errors"], r["warnings"], r["infos"], r["hints"]) == (0, 0, 0, 0), r
    col = read_glb(tmp_path / "cut.glb")["toy-colonly"]             # as an engine reads it (float32)
    assert col.is_watertight and abs(col.bounds[0][1] - floor_y) < 1e-3
