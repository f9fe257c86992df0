"""Triangle meshes as opaque geometry: a wp.Mesh BVH per mesh in the surface pass, loaded through trimesh."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from conftest import DEVICE, axis_camera, cloud_under_shared_light, homogeneous_volume, scene_of
from volren.camera import Camera
from volren.data import load_mesh_file
from volren.errors import VolrenError
from volren.render import DSSRM, DSSRMConfig
from volren.scene import DirectionalLight, Plane, Sphere, TriangleMesh

CAM = Camera(position=(0.0, 0.4, 3.2), width=64, height=48)


def render(scene, cams=(CAM,)):
    return DSSRM(DSSRMConfig(samples=64, light_samples=32, light_grid=16), device=DEVICE).render(scene, list(cams))


def ground_quad(y: float, half: float = 50.0) -> TriangleMesh:
    v = np.array([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]])
    return TriangleMesh(v, np.array([[0, 2, 1], [0, 3, 2]]), albedo=0.5)


def test_mesh_quad_equals_the_analytic_plane():
    base = cloud_under_shared_light(64)  # its atol was set under that light
    plane = render(dataclasses.replace(base, opaque=(Plane((0, -0.6, 0), (0, 1, 0), 0.5),)))
    mesh = render(dataclasses.replace(base, opaque=(ground_quad(-0.6),)))
    d = CAM.ray_directions()
    with np.errstate(divide="ignore"):
        hit = np.where(d[..., 1] < 0, (-0.6 - CAM.position[1]) / d[..., 1], np.inf)
    near = hit < 30.0  # the quad ends 50 m out; the plane goes on to the horizon
    assert near.sum() > 0.3 * near.size
    np.testing.assert_allclose(mesh.images[0][near], plane.images[0][near], atol=1e-5)
    np.testing.assert_allclose(mesh.depths[0][near], plane.depths[0][near], rtol=1e-5)


def test_icosphere_matches_the_analytic_sphere():
    """A finely tessellated sphere: the centre pixel's depth within the tessellation error, shading within 1%."""
    ico = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    light = [DirectionalLight((0, 0, -1), 2.0)]
    volume = homogeneous_volume(0.5, albedo=0.5)
    cam = axis_camera((0.0, 0.0, 4.0))
    a = render(dataclasses.replace(scene_of(volume, lights=light), opaque=(Sphere((0, 0, 2), 0.3, 0.6),)), [cam])
    mesh = TriangleMesh(np.add(ico.vertices, (0, 0, 2)), ico.faces, albedo=0.6)
    b = render(dataclasses.replace(scene_of(volume, lights=light), opaque=(mesh,)), [cam])
    assert b.depths[0][16, 16] == pytest.approx(a.depths[0][16, 16], abs=2e-3)
    np.testing.assert_allclose(b.images[0][16, 16], a.images[0][16, 16], rtol=1e-2)


def test_mesh_casts_shadows_on_other_surfaces():
    """A mesh slab between the light and the ground leaves only ambient light on the ground below it."""
    slab = trimesh.creation.box(extents=(1.0, 0.1, 1.0))
    blocker = TriangleMesh(np.add(slab.vertices, (0, 1.0, 0)), slab.faces)
    scene = dataclasses.replace(
        scene_of(homogeneous_volume(0.0, n=2), lights=[DirectionalLight((0, -1, 0), 2.0)], ambient=0.1),
        opaque=(Plane((0, -0.5, 0), (0, 1, 0), 0.5), blocker),
    )
    cam = Camera(position=(2.5, 0.5, 0.0), look_at=(0.0, -0.5, 0.0), width=33, height=33, fov_y=10)  # under the slab
    shaded = render(scene, [cam]).images[0][16, 16, 0]
    assert shaded == pytest.approx(0.5 * 0.1, rel=1e-4)  # albedo * ambient, the direct light blocked


def test_load_mesh_file_round_trip(tmp_path):
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    path = tmp_path / "box.obj"
    box.export(path)
    mesh = load_mesh_file(path, scale=2.0, translate=(1.0, 0.0, 0.0), albedo=(0.2, 0.4, 0.6))
    assert len(mesh.faces) == len(box.faces)
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-1.0, -1.0, -0.5], atol=1e-5)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [3.0, 1.0, 0.5], atol=1e-5)
    assert mesh.albedo == (0.2, 0.4, 0.6)


def test_mesh_errors(tmp_path):
    with pytest.raises(VolrenError, match="not found"):
        load_mesh_file(tmp_path / "missing.obj")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(VolrenError, match=r"bad\.ply"):
        load_mesh_file(bad)
    with pytest.raises(VolrenError, match="face indices"):
        TriangleMesh(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(VolrenError, match="vertices"):
        TriangleMesh(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))


USDA_QUAD = """#usda 1.0
def Xform "root" (
)
{
    double3 xformOp:translate = (1, 2, 3)
    uniform token[] xformOpOrder = ["xformOp:translate"]
    def Mesh "quad"
    {
        point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
    }
}
"""


def test_usd_meshes_load_in_world_coordinates(tmp_path):
    path = tmp_path / "quad.usda"
    path.write_text(USDA_QUAD)
    mesh = load_mesh_file(path)
    np.testing.assert_allclose(mesh.vertices, [[1, 2, 3], [2, 2, 3], [2, 3, 3], [1, 3, 3]])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])  # the quad fan-triangulated


def test_the_bunny_that_ships_with_warp_loads():
    import os

    import warp

    bunny = os.path.join(os.path.dirname(warp.__file__), "examples", "assets", "bunny.usd")
    if not os.path.exists(bunny):
        pytest.skip("this warp-lang build ships no example assets")
    mesh = load_mesh_file(bunny)
    assert len(mesh.faces) > 10_000 and np.all(np.isfinite(mesh.vertices))


def test_bad_usd_and_non_manifold_meshes(tmp_path):
    empty = tmp_path / "empty.usda"
    empty.write_text('#usda 1.0\ndef Xform "root"\n{\n}\n')
    with pytest.raises(VolrenError, match="no triangles"):
        load_mesh_file(empty)
    broken = tmp_path / "broken.usda"
    broken.write_text("#usda 1.0\ndef Mesh (\n")
    with pytest.raises(VolrenError, match="cannot read"):
        load_mesh_file(broken)
    fin = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]],
                          faces=[[0, 1, 2], [0, 1, 3], [0, 1, 4]], process=False)  # three sheets on edge 0-1
    path = tmp_path / "fins.obj"
    fin.export(path)
    with pytest.raises(VolrenError, match="non-manifold"):
        load_mesh_file(path)
