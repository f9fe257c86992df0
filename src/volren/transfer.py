"""1D transfer functions for direct volume rendering with path tracing (paper 002 §4.2, §6.1).

A transfer function maps a voxel's scalar value to the medium's extinction mu_t [1/m], its albedo (RGB, the share of
mu_t that scatters) and P_brdf, the share of scattering particles that reflect like a surface (Exposure Render's
two-particle split; the rest scatter by the phase function). Control points sit at normalised scalar positions u in
[0, 1], u = value / (the volume's largest value), and properties are linear in between (constant beyond the ends).
Presets: CT-like classifications (bone, muscle and skin, vessels) and a smoke-like ramp. JSON holds the points.
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


@dataclass(frozen=True)
class TransferFunction:
    points: tuple[ControlPoint, ...]
    name: str = "custom"

    def __post_init__(self) -> None:
        pts = tuple(self.points)
        if not pts:
            raise VolrenError("a transfer function needs at least one control point")
        for p in pts:
            if not (np.isfinite(p.position) and 0 <= p.position <= 1):
                raise VolrenError(f"transfer function positions must lie in [0, 1], got {p.position}")
            if not (np.isfinite(p.extinction) and p.extinction >= 0):
                raise VolrenError(f"transfer function extinction must be >= 0, got {p.extinction}")
            if len(p.albedo) != 3 or not all(0 <= a <= 1 for a in p.albedo):
                raise VolrenError(f"transfer function albedo must be 3 values in [0, 1], got {p.albedo}")
            if not 0 <= p.p_brdf <= 1:
                raise VolrenError(f"transfer function P_brdf must lie in [0, 1], got {p.p_brdf}")
        if any(b.position < a.position for a, b in itertools.pairwise(pts)):
            raise VolrenError("transfer function positions must not decrease")
        object.__setattr__(self, "points", pts)

    def table(self, size: int = TABLE_SIZE) -> np.ndarray:
        """(size, 5) float32: extinction, albedo r, g, b, P_brdf at u = i / (size - 1)."""
        u = np.linspace(0.0, 1.0, size)
        pos = np.array([p.position for p in self.points])
        values = np.array([(p.extinction, *p.albedo, p.p_brdf) for p in self.points], dtype=np.float64)
        return np.stack([np.interp(u, pos, values[:, c]) for c in range(5)], axis=1).astype(np.float32)

    def to_json(self) -> str:
        return json.dumps({"name": self.name, "points": [
            {"position": p.position, "extinction": p.extinction, "albedo": list(p.albedo), "p_brdf": p.p_brdf}
            for p in self.points]}, indent=2)

    @staticmethod
    def from_json(text: str, what: str = "transfer function") -> TransferFunction:
        try:
            doc = json.loads(text)
            points = tuple(ControlPoint(float(p["position"]), float(p["extinction"]),
                                        tuple(float(a) for a in p.get("albedo", (0.8, 0.8, 0.8))),
                                        float(p.get("p_brdf", 0.0))) for p in doc["points"])
        except (ValueError, KeyError, TypeError) as exc:
            raise VolrenError(f"{what}: not a transfer function JSON ({type(exc).__name__}: {exc})") from None
        return TransferFunction(points, str(doc.get("name", "custom")))


def linear(max_extinction: float, albedo: Sequence[float], p_brdf: float = 0.0, name: str = "linear"
           ) -> TransferFunction:
    """mu_t proportional to the scalar (mu_t = max_extinction at the largest value): the density-scale model of the
    ray marchers, so that a path tracer with this function renders what they render."""
    a = tuple(float(v) for v in albedo)
    return TransferFunction((ControlPoint(0.0, 0.0, a, p_brdf), ControlPoint(1.0, max_extinction, a, p_brdf)), name)


PRESETS: dict[str, TransferFunction] = {
    "ct-bone": TransferFunction((
        ControlPoint(0.0, 0.0, (0.9, 0.85, 0.8)), ControlPoint(0.45, 0.0, (0.9, 0.85, 0.8), 0.6),
        ControlPoint(0.6, 60.0, (0.95, 0.92, 0.85), 0.8), ControlPoint(1.0, 120.0, (0.97, 0.95, 0.9), 0.9)),
        "ct-bone"),
    "ct-muscle": TransferFunction((
        ControlPoint(0.0, 0.0, (0.9, 0.6, 0.5)), ControlPoint(0.15, 0.0, (0.9, 0.6, 0.5), 0.3),
        ControlPoint(0.25, 4.0, (0.95, 0.75, 0.65), 0.4), ControlPoint(0.4, 12.0, (0.85, 0.35, 0.3), 0.5),
        ControlPoint(0.6, 40.0, (0.95, 0.92, 0.85), 0.8), ControlPoint(1.0, 80.0, (0.97, 0.95, 0.9), 0.9)),
        "ct-muscle"),
    "ct-vessels": TransferFunction((
        ControlPoint(0.0, 0.0, (0.8, 0.1, 0.1)), ControlPoint(0.5, 0.0, (0.8, 0.1, 0.1), 0.5),
        ControlPoint(0.6, 30.0, (0.85, 0.15, 0.12), 0.7), ControlPoint(0.8, 0.0, (0.9, 0.9, 0.9), 0.7),
        ControlPoint(0.9, 80.0, (0.95, 0.95, 0.9), 0.9), ControlPoint(1.0, 100.0, (0.95, 0.95, 0.9), 0.9)),
        "ct-vessels"),
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
