"""Static world of a synthetic satellite-style sequence: textured ground, roads with lanes, car parks,
trees, speckles and buildings (whose roofs move with parallax).

Everything is drawn on a float32 *world canvas* of size ``(height + 2 margin, width + 2 margin)``; the
camera (see :mod:`torchtrack.sim.video`) looks at its centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from torchtrack.geometry import area_factor
from torchtrack.sim.video_config import VideoConfig


@dataclass
class Lane:
    """A directed polyline (world canvas coordinates, ``(n, 2)`` as x, y) that vehicles follow."""

    points: np.ndarray
    arc: np.ndarray            # (n,) cumulative arc length
    intersections: np.ndarray  # (k,) arc lengths where the lane crosses another road

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(m, 2)`` and unit directions ``(m, 2)`` at arc lengths ``s`` ``(m,)``."""
        x = np.interp(s, self.arc, self.points[:, 0])
        y = np.interp(s, self.arc, self.points[:, 1])
        seg = np.clip(np.searchsorted(self.arc, s, side="right") - 1, 0, len(self.arc) - 2)
        d = self.points[seg + 1] - self.points[seg]
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        return np.stack([x, y], axis=1), d


@dataclass
class ParkingSlot:
    """Fixed slots of a car park: centres ``(x, y)`` and heading angles."""

    xy: np.ndarray      # (m, 2)
    angle: np.ndarray   # (m,)


@dataclass
class Building:
    corners: np.ndarray  # (4, 2)
    height: float        # parallax gain
    roof: float          # roof intensity
    shadow: np.ndarray   # (2,) shadow offset
    inner: float         # relative tone of the inner roof


@dataclass
class Scene:
    base: np.ndarray            # float32 world canvas without buildings and vehicles
    lanes: list[Lane]
    slots: ParkingSlot
    buildings: list[Building]


def _multiscale_noise(rng: np.random.Generator, shape: tuple[int, int], scales, exponent: float) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for s in scales:
        small = rng.standard_normal((max(2, shape[0] // s + 2), max(2, shape[1] // s + 2))).astype(np.float32)
        big = cv2.resize(small, (shape[1] + 2 * s, shape[0] + 2 * s), interpolation=cv2.INTER_CUBIC)
        out += (s ** exponent) * big[s:s + shape[0], s:s + shape[1]]
    return (out - out.mean()) / (out.std() + 1e-6)


def _border_point(rng: np.random.Generator, side: int, w: int, h: int) -> np.ndarray:
    t = rng.uniform(0.1, 0.9)
    return np.array([[t * w, 0.0], [w - 1.0, t * h], [t * w, h - 1.0], [0.0, t * h]][side])


def _road_centreline(rng: np.random.Generator, w: int, h: int, curved: bool) -> np.ndarray:
    side_a = int(rng.integers(4))
    side_b = (side_a + int(rng.integers(1, 4))) % 4     # another side
    a, b = _border_point(rng, side_a, w, h), _border_point(rng, side_b, w, h)
    mid = 0.5 * (a + b)
    normal = np.array([-(b - a)[1], (b - a)[0]]) / (np.linalg.norm(b - a) + 1e-9)
    ctrl = mid + normal * (rng.uniform(-0.25, 0.25) * min(w, h) if curved else 0.0)
    t = np.linspace(0.0, 1.0, 80)[:, None]
    pts = (1 - t) ** 2 * a + 2 * (1 - t) * t * ctrl + t ** 2 * b
    # extend both ends beyond the canvas so vehicles enter and leave outside the view
    ext_a = pts[0] + (pts[0] - pts[1]) / np.linalg.norm(pts[0] - pts[1]) * 20
    ext_b = pts[-1] + (pts[-1] - pts[-2]) / np.linalg.norm(pts[-1] - pts[-2]) * 20
    return np.vstack([ext_a, pts, ext_b])


def _offset_polyline(pts: np.ndarray, offset: float) -> np.ndarray:
    d = np.gradient(pts, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    return pts + offset * np.stack([-d[:, 1], d[:, 0]], axis=1)


def _arc(pts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])


def _crossings(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection points ``(k, 2)`` of two polylines (all segment pairs at once)."""
    p, r = a[:-1, None, :], (a[1:] - a[:-1])[:, None, :]
    q, s = b[None, :-1, :], (b[1:] - b[:-1])[None, :, :]
    denom = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / denom
        u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / denom
    hit = (np.abs(denom) > 1e-9) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    i, j = np.nonzero(hit)
    return (p[i, 0] + t[i, j, None] * r[i, 0])


def scene_counts(cfg: VideoConfig) -> dict[str, int]:
    """The counts of static objects for ``cfg``'s view: as configured up to a 512 × 512 px view; above it,
    objects that are points (trees, speckles, buildings, car parks) scale with the view's area and roads
    (lines across the view) with its side (:func:`torchtrack.geometry.area_factor`), so that a 4096² frame
    shows the scene of a 512² frame at the same density rather than the same five roads over 64 times the area."""
    area = area_factor(cfg.height, cfg.width)
    return {"highways": round(cfg.highways * area ** 0.5), "local_roads": round(cfg.local_roads * area ** 0.5),
            "car_parks": round(cfg.car_parks * area), "trees": round(cfg.trees * area),
            "speckles": round(cfg.speckles * area), "buildings": round(cfg.buildings * area)}


def build_scene(cfg: VideoConfig, rng: np.random.Generator) -> Scene:
    """Draw the static world (see module docstring) and lay out lanes, car-park slots and buildings."""
    h, w = cfg.height + 2 * cfg.margin, cfg.width + 2 * cfg.margin
    counts = scene_counts(cfg)
    ground = 0.55 * _multiscale_noise(rng, (h, w), (64, 128), 1.0) + 0.45 * _multiscale_noise(
        rng, (h, w), (2, 4, 8, 16), 0.7)
    forest_field = _multiscale_noise(rng, (h, w), (48, 96), 1.0)
    forest = forest_field > np.quantile(forest_field, 1.0 - cfg.forest_fraction)
    crowns = _multiscale_noise(rng, (h, w), (2, 3, 5), 0.5)
    img = 66.0 + 10.0 * ground + 5.0 * crowns
    img = np.where(forest, 38.0 + 12.0 * crowns + 4.0 * ground, img).astype(np.float32)

    # roads
    lanes: list[Lane] = []
    owners: list[int] = []
    centres = []
    for highway in [True] * counts["highways"] + [False] * counts["local_roads"]:
        c = _road_centreline(rng, w, h, curved=highway)
        n_per_dir = int(rng.integers(2, 4)) if highway else 1
        median = 6.0 if highway else 0.0
        half = median / 2 + n_per_dir * cfg.lane_width + 1.5
        tone = float(rng.uniform(72, 92) if highway else rng.uniform(62, 80))
        pts = np.round(c * 16).astype(np.int32)
        cv2.polylines(img, [pts], False, tone, int(2 * half), cv2.LINE_AA, shift=4)
        if highway:
            cv2.polylines(img, [pts], False, tone - 22, int(median), cv2.LINE_AA, shift=4)
        for edge in (-half + 0.8, half - 0.8):
            cv2.polylines(img, [np.round(_offset_polyline(c, edge) * 16).astype(np.int32)], False,
                          tone + 14, 1, cv2.LINE_AA, shift=4)
        for k in range(n_per_dir):
            off = median / 2 + (k + 0.5) * cfg.lane_width
            fwd = _offset_polyline(c, off)
            bwd = _offset_polyline(c, -off)[::-1].copy()
            lanes += [Lane(fwd, _arc(fwd), np.empty(0)), Lane(bwd, _arc(bwd), np.empty(0))]
            owners += [len(centres), len(centres)]
        centres.append(c)
    # intersections: arc length along each lane of every crossing with another road
    pts_x = [np.concatenate([_crossings(centres[i], centres[j]) for j in range(len(centres)) if j != i]
                            or [np.empty((0, 2))]) for i in range(len(centres))]
    for lane, owner in zip(lanes, owners):
        x = pts_x[owner]
        if len(x):
            d = np.linalg.norm(lane.points[None, :, :] - x[:, None, :], axis=2)
            lane.intersections = lane.arc[np.argmin(d, axis=1)]

    # car parks with slots in rows; slot spacing = length + gap (2-5 px)
    slot_xy, slot_angle = [], []
    for _ in range(counts["car_parks"]):
        cw, ch = min(rng.uniform(50, 110), 0.4 * w), min(rng.uniform(40, 90), 0.4 * h)
        cx, cy = rng.uniform(cw / 2, w - cw / 2), rng.uniform(ch / 2, h - ch / 2)
        ang = rng.uniform(0, np.pi)
        box = cv2.boxPoints(((cx, cy), (cw, ch), np.degrees(ang))).astype(np.float32)
        tone = float(rng.uniform(70, 95))
        cv2.fillConvexPoly(img, np.round(box * 16).astype(np.int32), tone, cv2.LINE_AA, shift=4)
        u = np.array([np.cos(ang), np.sin(ang)])
        v = np.array([-u[1], u[0]])
        length = cfg.vehicle_length_median
        pitch = length * 0.55 + rng.uniform(*cfg.park_gap)
        row_gap = length + rng.uniform(4, 8)
        for r in np.arange(-ch / 2 + row_gap / 2 + 2, ch / 2 - row_gap / 2, row_gap):
            for t in np.arange(-cw / 2 + pitch / 2 + 2, cw / 2 - pitch / 2, pitch):
                slot_xy.append(np.array([cx, cy]) + t * u + r * v)
                slot_angle.append(ang + np.pi / 2)
    slots = ParkingSlot(np.array(slot_xy).reshape(-1, 2), np.array(slot_angle))

    # single trees (dark round crowns with a highlight), partly overhanging roads
    centres_t = rng.uniform(0, [w, h], size=(counts["trees"], 2))
    for (x, y), r in zip(centres_t, rng.uniform(2.5, 6.0, counts["trees"])):
        cv2.circle(img, (int(x * 16), int(y * 16)), int(r * 16), float(rng.uniform(22, 42)), -1,
                   cv2.LINE_AA, shift=4)
        cv2.circle(img, (int((x - r / 3) * 16), int((y - r / 3) * 16)), int(r * 5), float(rng.uniform(45, 70)),
                   -1, cv2.LINE_AA, shift=4)
    # static speckles: small dots of vehicle-like contrast
    for x, y in rng.uniform(0, [w, h], size=(counts["speckles"], 2)):
        tone = float(rng.choice([rng.uniform(120, 200), rng.uniform(10, 30)]))
        r = rng.uniform(0.5, 1.1)
        cv2.circle(img, (int(x * 16), int(y * 16)), int(r * 16), tone, -1, cv2.LINE_AA, shift=4)

    buildings = []
    sun = np.array([rng.uniform(2, 5), rng.uniform(2, 5)]) * rng.choice([-1, 1], 2)
    for _ in range(counts["buildings"]):
        bw, bh = rng.uniform(*cfg.building_size, 2)
        c = rng.uniform(0, [w, h])
        box = cv2.boxPoints(((c[0], c[1]), (bw, bh), rng.uniform(0, 180))).astype(np.float64)
        height = rng.uniform(0.3, 1.0)
        buildings.append(Building(box, height, float(rng.uniform(70, 190)), sun * height * 2,
                                  float(rng.uniform(0.7, 1.15))))

    # normalise the ground statistics to the configured mean/std (vehicles and roofs come on top)
    img = (img - img.mean()) / (img.std() + 1e-6) * (cfg.background_std * 0.65) + cfg.background_mean * 0.97
    return Scene(img.astype(np.float32), lanes, slots, buildings)


def draw_buildings(canvas: np.ndarray, buildings: list[Building], parallax: np.ndarray) -> None:
    """Shadows, then roofs shifted by ``height * parallax`` (false motion between frames), in place."""
    for b in buildings:
        shadow = b.corners + b.shadow
        cv2.fillConvexPoly(canvas, np.round(shadow * 16).astype(np.int32), 22.0, shift=4)
    for b in buildings:
        roof = b.corners + b.height * parallax
        cv2.fillConvexPoly(canvas, np.round(roof * 16).astype(np.int32), b.roof, shift=4)
        inner = roof + 0.25 * (roof.mean(axis=0) - roof)
        cv2.fillConvexPoly(canvas, np.round(inner * 16).astype(np.int32), b.roof * b.inner, shift=4)
