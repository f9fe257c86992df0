"""1D transfer functions for direct volume rendering with path tracing (paper 002 §4.2, §6.1).

A transfer function maps a voxel's scalar value to the medium's extinction mu_t [1/m], its albedo (RGB, the share of
mu_t that scatters), P_brdf, the share of scattering particles that reflect like a surface (Exposure Render's
two-particle split; the rest scatter by the phase function), and an optional emission: the radiance emitted per metre
[W/(m^3 sr)] at that scalar (RGB, default 0; the units of `volren.scene.Volume`'s emission * density, not modulated by
the albedo). Emission needs extinction > 0 at the same control point: the path tracer finds emitters only where its
free flights collide. Control points sit at normalised scalar positions u in
[0, 1], u = value / (the volume's largest value), and properties are linear in between (constant beyond the ends).
A function may also hold ``hu_points`` at Hounsfield units: a volume whose ``value_range`` says which HU its
densities stand for (a CT) is classified by those, whatever the series' own min and max; other volumes use the
normalised points. Presets: CT classifications (bone, muscle and skin, vessels; both forms) and a smoke-like ramp.
JSON holds "points" and, optionally, "hu_points"; a point's "emission" is optional (files without it stay valid).
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.errors import VolrenError

TABLE_SIZE = 1024
"""entries of the lookup table the kernels interpolate linearly"""


@dataclass(frozen=True)
class ControlPoint:
    position: float
    """normalised scalar u in [0, 1]"""
    extinction: float
    """mu_t [1/m]"""
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    p_brdf: float = 0.0
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """[W/(m^3 sr)] radiance emitted per metre"""


@dataclass(frozen=True)
class TransferFunction:
    points: tuple[ControlPoint, ...]
    name: str = "custom"
    hu_points: tuple[ControlPoint, ...] = ()
    """the same classification with positions in Hounsfield units, for volumes with a ``value_range``; empty: none"""

    def __post_init__(self) -> None:
        pts = tuple(self.points)
        if not pts:
            raise VolrenError("a transfer function needs at least one control point")
        for p in pts:
            if not (np.isfinite(p.position) and 0 <= p.position <= 1):
                raise VolrenError(f"transfer function positions must lie in [0, 1], got {p.position}")
        hu = tuple(self.hu_points)
        for p in (*pts, *hu):
            if not (np.isfinite(p.extinction) and p.extinction >= 0):
                raise VolrenError(f"transfer function extinction must be >= 0, got {p.extinction}")
            if len(p.albedo) != 3 or not all(0 <= a <= 1 for a in p.albedo):
                raise VolrenError(f"transfer function albedo must be 3 values in [0, 1], got {p.albedo}")
            if not 0 <= p.p_brdf <= 1:
                raise VolrenError(f"transfer function P_brdf must lie in [0, 1], got {p.p_brdf}")
            if len(p.emission) != 3 or not all(np.isfinite(e) and e >= 0 for e in p.emission):
                raise VolrenError(f"transfer function emission must be 3 values >= 0, got {p.emission}")
            if max(p.emission) > 0 and p.extinction == 0:
                raise VolrenError(f"transfer function emission needs extinction > 0 at the same point (position "
                                  f"{p.position}): the path tracer cannot find an emitter it never collides with")
        if not all(np.isfinite(p.position) for p in hu):
            raise VolrenError("transfer function Hounsfield positions must be finite")
        for ps in (pts, hu):
            if any(b.position < a.position for a, b in itertools.pairwise(ps)):
                raise VolrenError("transfer function positions must not decrease")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "hu_points", hu)

    def table(self, size: int = TABLE_SIZE, hu: tuple[float, float] | None = None) -> np.ndarray:
        """(size, 8) float32: extinction, albedo r, g, b, P_brdf, emission r, g, b at u = i / (size - 1); with ``hu`` =
        (HU at u = 0, HU at u = 1) and ``hu_points``, the Hounsfield classification at those HU instead."""
        u = np.linspace(0.0, 1.0, size)
        pos = np.array([p.position for p in self.points])
        points = self.points
        if hu is not None and self.hu_points:
            u = hu[0] + (hu[1] - hu[0]) * u
            pos = np.array([p.position for p in self.hu_points])
            points = self.hu_points
        values = np.array([(p.extinction, *p.albedo, p.p_brdf, *p.emission) for p in points], dtype=np.float64)
        return np.stack([np.interp(u, pos, values[:, c]) for c in range(8)], axis=1).astype(np.float32)

    def to_json(self) -> str:
        doc: dict = {"name": self.name, "points": [_point_json(p) for p in self.points]}
        if self.hu_points:
            doc["hu_points"] = [_point_json(p) for p in self.hu_points]
        return json.dumps(doc, indent=2)

    @staticmethod
    def from_json(text: str, what: str = "transfer function") -> TransferFunction:
        try:
            doc = json.loads(text)
            points, hu_points = (tuple(ControlPoint(float(p["position"]), float(p["extinction"]),
                                                    tuple(float(a) for a in p.get("albedo", (0.8, 0.8, 0.8))),
                                                    float(p.get("p_brdf", 0.0)),
                                                    tuple(float(e) for e in p.get("emission", (0.0, 0.0, 0.0))))
                                       for p in doc.get(key, ()))
                                 for key in ("points", "hu_points"))
            if "points" not in doc:
                raise KeyError("points")
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise VolrenError(f"{what}: not a transfer function JSON ({type(exc).__name__}: {exc})") from None
        return TransferFunction(points, str(doc.get("name", "custom")), hu_points)


def _point_json(p: ControlPoint) -> dict:
    doc = {"position": p.position, "extinction": p.extinction, "albedo": list(p.albedo), "p_brdf": p.p_brdf}
    if max(p.emission) > 0:
        doc["emission"] = list(p.emission)
    return doc


def linear(max_extinction: float, albedo: Sequence[float], p_brdf: float = 0.0, name: str = "linear",
           max_emission: Sequence[float] = (0.0, 0.0, 0.0)) -> TransferFunction:
    """mu_t and emission proportional to the scalar (max_extinction and max_emission at the largest value): the
    density-scale model of the ray marchers, so that a path tracer with this function renders what they render."""
    a = tuple(float(v) for v in albedo)
    e = tuple(float(v) for v in max_emission)
    return TransferFunction((ControlPoint(0.0, 0.0, a, p_brdf), ControlPoint(1.0, max_extinction, a, p_brdf, e)), name)


_BONE, _CORTEX = (0.95, 0.92, 0.85), (0.97, 0.95, 0.9)
_SKIN, _MUSCLE, _BLOOD = (0.95, 0.75, 0.65), (0.85, 0.35, 0.3), (0.85, 0.15, 0.12)

# The CT presets' Hounsfield forms (HU: air -1000, lung -900..-500, fat -100, water 0, soft tissue and muscle 40,
# contrast-filled vessels 150..400, cancellous bone 300..700, cortical bone 1000 and above). ct-bone: nothing up to
# 200 HU (so all soft tissue and fat are clear), rising to bone at 400 and dense cortex at 1000. ct-muscle: clear up to
# -60 HU (air, lung, fat), skin-coloured at water (0), muscle at 40, then white towards bone (300, 1000).
# ct-vessels: clear up to 120 HU, contrast-filled blood 200..300, clear again at 450, bone from 700.
PRESETS: dict[str, TransferFunction] = {
    "ct-bone": TransferFunction((
        ControlPoint(0.0, 0.0, (0.9, 0.85, 0.8)), ControlPoint(0.45, 0.0, (0.9, 0.85, 0.8), 0.6),
        ControlPoint(0.6, 60.0, _BONE, 0.8), ControlPoint(1.0, 120.0, _CORTEX, 0.9)),
        "ct-bone", (
        ControlPoint(-1000.0, 0.0, (0.9, 0.85, 0.8), 0.6), ControlPoint(200.0, 0.0, (0.9, 0.85, 0.8), 0.6),
        ControlPoint(400.0, 60.0, _BONE, 0.8), ControlPoint(1000.0, 120.0, _CORTEX, 0.9))),
    "ct-muscle": TransferFunction((
        ControlPoint(0.0, 0.0, (0.9, 0.6, 0.5)), ControlPoint(0.15, 0.0, (0.9, 0.6, 0.5), 0.3),
        ControlPoint(0.25, 4.0, _SKIN, 0.4), ControlPoint(0.4, 12.0, _MUSCLE, 0.5),
        ControlPoint(0.6, 40.0, _BONE, 0.8), ControlPoint(1.0, 80.0, _CORTEX, 0.9)),
        "ct-muscle", (
        ControlPoint(-1000.0, 0.0, (0.9, 0.6, 0.5), 0.3), ControlPoint(-60.0, 0.0, (0.9, 0.6, 0.5), 0.3),
        ControlPoint(0.0, 4.0, _SKIN, 0.4), ControlPoint(40.0, 12.0, _MUSCLE, 0.5),
        ControlPoint(300.0, 40.0, _BONE, 0.8), ControlPoint(1000.0, 80.0, _CORTEX, 0.9))),
    "ct-vessels": TransferFunction((
        ControlPoint(0.0, 0.0, (0.8, 0.1, 0.1)), ControlPoint(0.5, 0.0, (0.8, 0.1, 0.1), 0.5),
        ControlPoint(0.6, 30.0, _BLOOD, 0.7), ControlPoint(0.8, 0.0, (0.9, 0.9, 0.9), 0.7),
        ControlPoint(0.9, 80.0, (0.95, 0.95, 0.9), 0.9), ControlPoint(1.0, 100.0, (0.95, 0.95, 0.9), 0.9)),
        "ct-vessels", (
        ControlPoint(-1000.0, 0.0, (0.8, 0.1, 0.1), 0.5), ControlPoint(120.0, 0.0, (0.8, 0.1, 0.1), 0.5),
        ControlPoint(200.0, 30.0, _BLOOD, 0.7), ControlPoint(300.0, 30.0, _BLOOD, 0.7),
        ControlPoint(450.0, 0.0, (0.9, 0.9, 0.9), 0.7), ControlPoint(700.0, 80.0, (0.95, 0.95, 0.9), 0.9),
        ControlPoint(1000.0, 100.0, (0.95, 0.95, 0.9), 0.9))),
    "smoke": TransferFunction((ControlPoint(0.0, 0.0, (0.9, 0.9, 0.9)),
                               ControlPoint(1.0, 20.0, (0.9, 0.9, 0.9))), "smoke"),
}


def load_transfer_function(spec: str | Path) -> TransferFunction:
    """A preset by name, or a JSON file."""
    key = str(spec)
    if key in PRESETS:
        return PRESETS[key]
    path = Path(spec)
    if not path.is_file():
        raise VolrenError(f"transfer function '{key}' is neither a preset ({', '.join(PRESETS)}) nor a file")
    return TransferFunction.from_json(path.read_text(), str(path))
