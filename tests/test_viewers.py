"""Viewer rigs of paper 003's evaluation (wandering viewers, fixed frustum overlap, the arc) and the fog CLI; every
rig keeps every viewer of every fog scene in its walkable space (outside every mesh, inside the floor's bounds)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import DEVICE
from volren.camera import Camera
from volren.errors import VolrenError
from volren.viewers import EYE_HEIGHT, WalkArea, arc_viewers, overlap_viewers, wandering_viewers

BASE = Camera(position=(0.0, 1.7, 5.0), look_at=(0.0, 1.7, 0.0), width=160, height=90, fov_y=60.0)


def yaw(cam: Camera) -> float:
    d = np.subtract(cam.look_at, cam.position)
    return math.atan2(d[0], -d[2])


def test_wandering_viewers_stay_in_the_area_and_move():
    area = WalkArea((-10.0, -5.0), (10.0, 5.0), obstacles=((-1.0, -5.0, 1.0, 3.0),))  # a wall with a door at z > 3
    for t in (0.0, 3.0, 40.0):
        views = wandering_viewers(BASE, 16, area, time=t, seed=1)
        p = np.array([v.position for v in views])
        assert area.walkable(p[:, 0], p[:, 2]).all()
        assert np.all(np.abs(p[:, 0]) > 1.3) or np.all(p[np.abs(p[:, 0]) <= 1.3, 2] > 3.3)
        assert np.allclose(p[:, 1], EYE_HEIGHT)
    a = wandering_viewers(BASE, 4, area, time=0.0)
    b = wandering_viewers(BASE, 4, area, time=1.0)
    step = np.linalg.norm(np.subtract(a[0].position, b[0].position))
    assert 0.5 < step < 2.0  # about walking speed


@pytest.mark.parametrize("overlap", [0.1, 0.5, 1.0])
def test_overlap_rig_shares_the_requested_fraction_of_the_horizontal_fov(overlap):
    views = overlap_viewers(BASE, 4, overlap)
    h_fov = 2 * math.atan(BASE.tan_half_fov * BASE.width / BASE.height)
    steps = np.diff([yaw(v) for v in views])
    np.testing.assert_allclose(np.abs(steps), (1 - overlap) * h_fov, atol=1e-9)
    assert all(v.position == BASE.position for v in views)


def test_bad_rigs():
    with pytest.raises(VolrenError, match="overlap"):
        overlap_viewers(BASE, 2, 1.5)
    with pytest.raises(VolrenError, match="viewer count"):
        wandering_viewers(BASE, 0, WalkArea((0, 0), (1, 1)))
    with pytest.raises(VolrenError, match="no room"):
        WalkArea((0, 0), (0.5, 3))
    with pytest.raises(VolrenError, match="found no walk"):
        wandering_viewers(BASE, 1, WalkArea((0, 0), (10, 10), obstacles=((-1, -1, 11, 11),)))


def test_viewers_of_different_sizes_render_as_if_alone():
    from volren.data.fog_scenes import fog_scene, fog_scene_camera
    from volren.render import FogConfig, FogRenderer

    spot = fog_scene_camera("courtyard")
    big = Camera(position=spot["position"], look_at=spot["look_at"], width=64, height=36)
    small = Camera(position=(0.0, 1.7, 0.0), look_at=(5.0, 1.0, 5.0), width=40, height=40, fov_y=70.0)
    scene = fog_scene("courtyard")
    config = FogConfig(sharing="none", slices=16, temporal=False)
    both = FogRenderer(config, device=DEVICE).render(scene, [big, small])
    assert [i.shape for i in both.images] == [(36, 64, 4), (40, 40, 4)]
    for cam, image in zip([big, small], both.images, strict=True):
        alone = FogRenderer(config, device=DEVICE).render(scene, [cam]).images[0]
        np.testing.assert_array_equal(image, alone)


@pytest.mark.parametrize("rig", ["wander", "overlap"])
def test_rig_option(capfd, tmp_path, rig):
    from test_cli import ok, stats_of

    out = tmp_path / rig
    ok(capfd, "render", "--method", "fog", "--scene", "hall", "--width", "32", "--height", "18", "--slices", "16",
       "--device", "cpu", "--views", "3", "--rig", rig, "--frames", "2", "--out", out)
    frames = stats_of(out)["frames"]
    assert len(frames) == 2 and frames[0]["settings"]["views"] == 3


def contains(mesh, points: np.ndarray) -> np.ndarray:
    """Whether each point lies inside the closed mesh (its parts do not overlap): an odd number of crossings along a
    ray in a direction no face of the scenes lies along."""
    tris = mesh.vertices[mesh.faces].astype(np.float64)
    d = np.array([0.5771, 0.0113, 0.8166])
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = points[:, None, :] - tris[None, :, 0]
    u = np.einsum("nij,ij->ni", s, p) * inv
    q = np.cross(s, e1[None])
    v = (q @ d) * inv
    t = np.einsum("ij,nij->ni", e2, q) * inv
    hits = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hits.sum(1) % 2 == 1


BODY = [(dx, y, dz) for y in (0.1, 0.9, EYE_HEIGHT) for dx, dz in ((0, 0), (0.2, 0), (-0.2, 0), (0, 0.2), (0, -0.2))]
"""points of a viewer's body relative to its eye's floor point: feet, waist, eyes, each with 0.2 m around them"""


@pytest.mark.parametrize("name", ["hall", "courtyard", "dynamic"])
def test_every_rig_keeps_every_viewer_in_the_scenes_walkable_space(name):
    """The default arc (16 viewers) and wandering viewers (16, over 10 s of frames) stand on the floor inside the
    scene's bounds (the hall's and the room's interiors, the courtyard's ground), and no part of the body from the
    feet to the eyes lies inside any mesh (walls, columns, buildings, the fountain, the dynamic scene's movers)."""
    from volren.data.fog_scenes import _WALK_BOUNDS, fog_scene, fog_scene_camera, fog_scene_walk_area

    spot = fog_scene_camera(name)
    area = fog_scene_walk_area(name)
    base = Camera(position=spot["position"], look_at=spot["look_at"], width=32, height=18)
    lo, hi = _WALK_BOUNDS[name]
    rigs = {0.0: arc_viewers(base, 16, area) + overlap_viewers(base, 4, 0.1)}
    for t in np.arange(0.0, 10.0, 0.5):
        rigs.setdefault(float(t), []).extend(wandering_viewers(base, 16, area, time=float(t), seed=7))
    for t, views in rigs.items():
        eyes = np.array([v.position for v in views])
        assert np.all(eyes[:, [0, 2]] > lo) and np.all(eyes[:, [0, 2]] < hi), t
        assert np.all((eyes[:, 1] > 1.5) & (eyes[:, 1] < 3.0))  # standing, not flying
        body = np.concatenate([eyes * (1, 0, 1) + offset for offset in BODY])
        for mesh in fog_scene(name, t).opaque:
            inside = contains(mesh, body)
            assert not inside.any(), (t, mesh.name, body[inside][:3])


def test_the_arc_leaves_a_camera_outside_the_area_alone():
    """A user's camera outside the walk area (looking at the hall from outside) keeps the plain arc."""
    from volren.camera import orbit_views
    from volren.data.fog_scenes import fog_scene_walk_area

    outside = Camera(position=(0.0, 1.7, -15.0), look_at=(0.0, 2.0, 0.0))
    assert arc_viewers(outside, 5, fog_scene_walk_area("hall")) == orbit_views(outside, 5)
