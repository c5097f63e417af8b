"""The synthetic toy: ellipsoids grouped into rigid parts, and the motion of a dynamic toy's parts.

Parts of a dynamic object rotate about pivots: arms swing periodically, the head wanders along a
quasi-periodic (never repeating) path."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ..capture.board import BoardSpec
from ..core.errors import DbbError

UP = np.array([0.0, 0.0, -1.0])  # board normal on the cameras' side (board face up on a table)


@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid of a rigid part, axis-aligned at rest; centre and radii in metres."""

    part: str
    center: tuple[float, float, float]
    radii: tuple[float, float, float]
    color: tuple[float, float, float]        # albedo, linear 0..1
    stripes: float = 0.0                     # stripe frequency along local z (0: plain)


@dataclass(frozen=True)
class Motion:
    """Rotation of a part about ``pivot`` around ``axis``: angle(t) = sum a_i sin(2 pi t / T_i + p_i)."""

    part: str
    pivot: tuple[float, float, float]
    axis: tuple[float, float, float]
    amplitudes_deg: tuple[float, ...]
    periods_s: tuple[float, ...]
    phases: tuple[float, ...]

    def angle_rad(self, t: float) -> float:
        return math.radians(sum(a * math.sin(2 * math.pi * t / T + p) for a, T, p in
                                zip(self.amplitudes_deg, self.periods_s, self.phases)))


@dataclass(frozen=True)
class ObjectModel:
    """The object: ellipsoids in rigid parts, and the motions of the parts that move."""

    ellipsoids: tuple[Ellipsoid, ...]
    motions: tuple[Motion, ...] = ()

    def posed(self, t: float) -> list[tuple[np.ndarray, np.ndarray, Ellipsoid]]:
        """World pose of every ellipsoid at time t: [(centre (3,), rotation (3, 3), ellipsoid)]."""
        rot = {m.part: (np.asarray(m.pivot), _axis_angle(np.asarray(m.axis), m.angle_rad(t)))
               for m in self.motions}
        out = []
        for e in self.ellipsoids:
            c = np.asarray(e.center, float)
            R = np.eye(3)
            if e.part in rot:
                pivot, R = rot[e.part]
                c = pivot + R @ (c - pivot)
            out.append((c, R, e))
        return out

    def bounding_sphere(self, times: np.ndarray) -> tuple[np.ndarray, float]:
        """A sphere (centre (3,), radius) holding the object at all ``times``."""
        pts = []
        for t in times:
            for c, R, e in self.posed(float(t)):
                # Corners of the ellipsoid's oriented bounding box hold it.
                corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
                pts.append(c + (corners * np.asarray(e.radii)) @ R.T)
        pts = np.concatenate(pts)
        center = 0.5 * (pts.min(0) + pts.max(0))
        return center, float(np.linalg.norm(pts - center, axis=1).max())

    def to_json(self) -> dict:
        return {"ellipsoids": [asdict(e) for e in self.ellipsoids],
                "motions": [asdict(m) for m in self.motions]}

    @classmethod
    def from_json(cls, d: dict) -> "ObjectModel":
        def tup(v):
            return tuple(tup(x) for x in v) if isinstance(v, list) else v

        return cls(tuple(Ellipsoid(**{k: tup(v) for k, v in e.items()}) for e in d["ellipsoids"]),
                   tuple(Motion(**{k: tup(v) for k, v in m.items()}) for m in d["motions"]))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * angle)
    return R


def make_object(kind: str, board: BoardSpec, rng: np.random.Generator) -> ObjectModel:
    """A toy (body, head with ears and nose, arms, feet) standing on the table beside the board.

    Its front faces -y, toward the middle of the camera path. ``dynamic``: the arms swing
    periodically, the head turns and nods along a quasi-periodic path.
    """
    w, h = board.size_m
    s = float(rng.uniform(0.9, 1.1))
    base = np.array([w + 0.07 * s + 0.03, h / 2, 0.0])

    def hsv(hue: float, sat: float, val: float) -> tuple[float, float, float]:
        px = np.uint8([[[int(hue * 179) % 180, int(sat * 255), int(val * 255)]]])
        r, g, b = cv2.cvtColor(px, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
        return (float(r), float(g), float(b))

    hue = float(rng.uniform(0, 1))
    body_c, head_c = hsv(hue, 0.65, 0.85), hsv(hue + 0.08, 0.45, 0.95)
    limb_c, acc_c = hsv(hue + 0.5, 0.7, 0.8), hsv(hue + 0.25, 0.8, 0.6)

    def at(x: float, y: float, z: float) -> tuple[float, float, float]:
        p = base + s * np.array([x, y, z])
        return (float(p[0]), float(p[1]), float(p[2]))

    def rr(*r: float) -> tuple[float, float, float]:
        return tuple(float(s * v) for v in r)  # type: ignore[return-value]

    E = Ellipsoid
    ells = [
        E("body", at(0, 0, -0.062), rr(0.046, 0.039, 0.056), body_c, stripes=7.0),
        E("body", at(-0.022, -0.008, -0.008), rr(0.019, 0.026, 0.008), acc_c),   # feet
        E("body", at(0.022, -0.008, -0.008), rr(0.019, 0.026, 0.008), acc_c),
        E("head", at(0, 0, -0.142), rr(0.036, 0.034, 0.034), head_c, stripes=5.0),
        E("head", at(-0.026, 0.004, -0.172), rr(0.012, 0.006, 0.013), acc_c),    # ears
        E("head", at(0.026, 0.004, -0.172), rr(0.012, 0.006, 0.013), acc_c),
        E("head", at(0, -0.034, -0.138), rr(0.011, 0.010, 0.009), limb_c),        # nose
        E("arm_l", at(-0.058, 0, -0.074), rr(0.012, 0.012, 0.033), limb_c, stripes=4.0),
        E("arm_r", at(0.058, 0, -0.074), rr(0.012, 0.012, 0.033), limb_c, stripes=4.0),
    ]
    motions: list[Motion] = []
    if kind == "dynamic":
        ph = rng.uniform(0, 2 * math.pi, size=6)
        swing_T = float(rng.uniform(1.4, 1.9))
        motions = [
            # Periodic: arms swing in opposition about the shoulders.
            Motion("arm_l", at(-0.054, 0, -0.1), (1.0, 0.0, 0.0), (40.0,), (swing_T,), (ph[0],)),
            Motion("arm_r", at(0.054, 0, -0.1), (1.0, 0.0, 0.0), (40.0,), (swing_T,), (ph[0] + math.pi,)),
            # Non-periodic: the head turns about the up axis with incommensurate periods.
            Motion("head", at(0, 0, -0.11), tuple(UP), (28.0, 14.0, 9.0),
                   (3.1, 3.1 * math.sqrt(2), 3.1 * math.pi), (ph[1], ph[2], ph[3])),
        ]
    elif kind != "static":
        raise DbbError(f"unknown object kind {kind!r} (expected static or dynamic)")
    return ObjectModel(tuple(ells), tuple(motions))
