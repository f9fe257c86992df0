"""Built-in fog scenes (paper 003 stand-ins for Sponza and Bistro): valid meshes and lights, a camera inside the
bounds, motion only in `dynamic`, and, by ray casting the hall, sun shafts through its windows and shadows beside
them."""

from __future__ import annotations

import numpy as np
import pytest

from volren.data.fog_scenes import FOG_SCENES, HALL_SUN, HALL_WINDOW_X, fog_scene, fog_scene_camera
from volren.errors import VolrenError
from volren.scene import DirectionalLight, Fog, PointLight, Scene, SpotLight, TriangleMesh

NAMES = ("hall", "courtyard", "dynamic")


def first_hit(scene: Scene, origin, direction) -> float:
    """Distance to the nearest triangle of any scene mesh along the ray (Moller-Trumbore, both sides), or inf."""
    tris = np.concatenate([m.vertices[m.faces].astype(np.float64) for m in scene.opaque])
    o, d = np.asarray(origin, dtype=np.float64), np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - tris[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    return float(t[hit].min()) if hit.any() else np.inf


def floor_point_through(window_point) -> np.ndarray:
    """Where the sun ray through a point of the window wall lands on the floor (y = 0)."""
    w = np.asarray(window_point, dtype=np.float64)
    d = np.asarray(HALL_SUN)
    return w + (w[1] / -d[1]) * d + np.array([0.0, 0.01, 0.0])


@pytest.mark.parametrize("name", NAMES)
def test_every_scene_builds_valid_meshes_lights_and_fog(name):
    assert set(FOG_SCENES) == set(NAMES)
    scene = fog_scene(name)
    assert scene.name == name and scene.volumes == () and isinstance(scene.fog, Fog)
    assert 1 <= len(scene.lights) <= 8
    assert all(isinstance(m, TriangleMesh) for m in scene.opaque)
    assert sum(len(m.faces) for m in scene.opaque) < 20_000
    for m in scene.opaque:
        assert np.all(np.isfinite(m.vertices)) and m.faces.min() >= 0 and m.faces.max() < len(m.vertices)
        assert len(np.unique(m.faces)) == len(m.vertices)  # no stray vertices
    assert all(0.0 <= a <= 1.0 for m in scene.opaque for a in m.albedo)


@pytest.mark.parametrize("name", NAMES)
def test_camera_and_lights_lie_inside_the_extent_and_the_camera_sees_its_target(name):
    cam = fog_scene_camera(name)
    lo, hi = (np.asarray(v) for v in cam["extent"])
    pos, look_at = np.asarray(cam["position"]), np.asarray(cam["look_at"])
    assert np.all(lo < pos) and np.all(pos < hi) and np.all(lo < look_at) and np.all(look_at < hi)
    assert first_hit(fog_scene(name), pos, look_at - pos) > np.linalg.norm(look_at - pos)
    for time in (0.0, 1.3, 2.7, 5.0):
        scene = fog_scene(name, time)
        for m in scene.opaque:
            assert np.all(m.vertices >= lo - 1e-5) and np.all(m.vertices <= hi + 1e-5), m.name
        for light in scene.lights:
            if isinstance(light, PointLight | SpotLight):
                assert np.all(lo < light.position) and np.all(np.asarray(light.position) < hi)


def test_courtyard_has_local_lights_only():
    lights = fog_scene("courtyard").lights
    assert 3 <= sum(isinstance(li, PointLight) for li in lights) <= 6
    spots = [li for li in lights if isinstance(li, SpotLight)]
    assert 2 <= len(spots) <= 3 and all(s.direction[1] < -0.5 for s in spots)
    assert not any(isinstance(li, DirectionalLight) for li in lights)


def test_only_the_dynamic_scene_moves_with_time():
    def vertices(name, time):
        return np.concatenate([m.vertices for m in fog_scene(name, time).opaque])

    assert not np.allclose(vertices("dynamic", 0.0), vertices("dynamic", 1.0))
    np.testing.assert_array_equal(vertices("dynamic", 0.0), vertices("dynamic", 8.0 * 3))  # common period 24 s
    for name in ("hall", "courtyard"):
        np.testing.assert_array_equal(vertices(name, 0.0), vertices(name, 1.0))


def test_unknown_name_and_bad_time_raise_one_line_errors():
    with pytest.raises(VolrenError, match="hall, courtyard, dynamic") as err:
        fog_scene("sponza")
    assert "\n" not in str(err.value)
    with pytest.raises(VolrenError, match="hall, courtyard, dynamic"):
        fog_scene_camera("bistro")
    with pytest.raises(VolrenError, match="finite"):
        fog_scene("dynamic", float("nan"))


def test_hall_ceiling_is_closed_and_the_sun_enters_only_through_the_windows():
    scene = fog_scene("hall")
    (sun,) = scene.lights
    assert isinstance(sun, DirectionalLight)
    assert 35.0 <= np.degrees(np.arcsin(-sun.direction[1])) <= 45.0
    up = first_hit(scene, (0.0, 0.01, 0.0), (0.0, 1.0, 0.0))
    assert up == pytest.approx(7.0 - 0.01, abs=1e-4)  # the ceiling's underside, not the sky
    to_sun = -np.asarray(sun.direction)
    # floor points lit through the centre of each window (z = 5.25 is mid-wall): every shaft reaches the sky
    lit = [floor_point_through((x, 3.5, 5.25)) for x in HALL_WINDOW_X]
    assert all(1.0 < p[2] < 2.0 for p in lit)  # the shafts land mid-hall, between the column rows
    assert all(first_hit(scene, p, to_sun) == np.inf for p in lit)
    # the same construction through a pier between two windows lands in its shadow ...
    pier = floor_point_through((-7.5, 3.5, 5.25))
    assert first_hit(scene, pier, to_sun) < 10.0
    # ... and so does a floor point at the foot of the window wall, below the sill
    assert first_hit(scene, (0.0, 0.01, 4.8), to_sun) < 1.0
    # a column stands in a shaft: a floor point just behind it (away from the sun) is in its shadow
    column = np.array([1.5, 1.0, 2.5])  # a point on the axis of the column at x = 1.5 (z = 2.5 row), 1 m up
    shadowed = column + (1.0 / -sun.direction[1]) * np.asarray(sun.direction) + np.array([0.0, 0.01, 0.0])
    assert first_hit(scene, shadowed, to_sun) < 2.0
