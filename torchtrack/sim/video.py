"""Synthetic satellite-style grey video with vehicle truth and the true camera motion.

The generator mimics the WPAFB 2009 wide-area imagery (``data/wpafb-aoi02``): a textured ground
(mean about 60, std about 18), roads, car parks, trees, speckles and buildings whose roofs move with
parallax (false motion), vehicles 3-15 px long, bright or dark, moving along lanes with lognormal
speeds (median ``speed_median``, 90th percentile ``speed_p90`` px/frame), slowing near intersections,
parked in rows 2-5 px apart, born and dying at the borders and in the car parks, with short dropouts.
A small random homography per frame jitters the camera; sensor blur, noise and gain drift finish it, and
:mod:`torchtrack.sim.sensor` adds what real sensors add where asked (motion blur, haze, compression...).

Coordinates: pixels, ``x`` = column and ``y`` = row, origin at the centre of the top-left pixel.
The *reference* coordinates are those of an unjittered camera; ``homography`` ``H_k`` (3x3) maps
reference coordinates to frame ``k``: ``[x_k, y_k, 1]^T ~ H_k [x_ref, y_ref, 1]^T``; the motion from
frame ``k`` to frame ``k-1`` is ``H_{k-1} H_k^{-1}``.

Usage::

    for f in generate_sequence(VideoConfig(frames=10), torch.Generator().manual_seed(0)):
        f.image, f.ids, f.xy, f.velocity, f.homography
    write_sequence(VideoConfig(), torch.Generator().manual_seed(0), "out/seq")
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchtrack.errors import TorchtrackError
from torchtrack.io.frames import Frame, FrameSource
from torchtrack.io.outputs import partial_name, write_json, write_text
from torchtrack.sim.sensor import Sensor
from torchtrack.sim.video_config import VideoConfig, load_video_config
from torchtrack.sim.video_scene import Scene, build_scene, draw_buildings

__all__ = ["VideoConfig", "VideoFrame", "generate_sequence", "write_sequence", "read_camera",
           "load_video_config"]


class VideoFrame(NamedTuple):
    """One frame and its truth.

    image: (H, W) uint8. ids: (N,) int64 vehicle ids of the *visible* vehicles (a vehicle in a dropout
    is absent for those frames and comes back with its id). xy: (N, 2) float64 centres (x = column,
    y = row). velocity: (N, 2) float64 displacement in image coordinates since the previous frame,
    ``xy_k - xy_{k-1}`` (px/frame, camera jitter included; NaN for a vehicle born in this frame).
    moving: (N,) bool, False for parked vehicles. homography: (3, 3) float64 reference -> frame.
    """

    index: int
    image: np.ndarray
    ids: np.ndarray
    xy: np.ndarray
    velocity: np.ndarray
    moving: np.ndarray
    homography: np.ndarray


@dataclass
class _Vehicle:
    id: int
    length: float
    width: float
    tone: float
    bright: bool
    lane: int = -1            # -1: parked
    s: float = 0.0
    desired: float = 0.0
    speed: float = 0.0
    xy: np.ndarray | None = None     # parked position (world canvas)
    angle: float = 0.0               # parked heading
    slot: int = -1
    dropout: int = 0


class _World:
    """Vehicles moving on the scene's lanes and parked in its slots (world canvas coordinates)."""

    def __init__(self, cfg: VideoConfig, scene: Scene, rng: np.random.Generator) -> None:
        self.cfg, self.scene, self.rng = cfg, scene, rng
        self.sigma = np.log(cfg.speed_p90 / cfg.speed_median) / 1.2815515655446004
        self.next_id = 1
        self.vehicles: list[_Vehicle] = []
        self.slot_taken = np.zeros(len(scene.slots.xy), bool)
        for lane_idx, lane in enumerate(scene.lanes):
            n = rng.poisson(cfg.lane_density * lane.length)
            for s in np.sort(rng.uniform(0, lane.length, n)):
                self._add_moving(lane_idx, float(s))
        for k in np.nonzero(rng.random(len(self.slot_taken)) < cfg.park_occupancy)[0]:
            self._park(int(k))
        self._resolve_overlaps()

    def _new(self, **kw) -> _Vehicle:
        cfg, rng = self.cfg, self.rng
        lo, hi = cfg.vehicle_length
        length = float(np.clip(cfg.vehicle_length_median * np.exp(0.3 * rng.standard_normal()), lo, hi))
        bright = bool(rng.random() < cfg.bright_fraction)
        tone = float(rng.uniform(*cfg.bright_tone) if bright else rng.uniform(*cfg.dark_tone))
        v = _Vehicle(self.next_id, length, max(1.8, length * rng.uniform(0.42, 0.55)), tone, bright, **kw)
        self.next_id += 1
        self.vehicles.append(v)
        return v

    def _add_moving(self, lane: int, s: float) -> None:
        desired = self.cfg.speed_median * np.exp(self.sigma * self.rng.standard_normal())
        desired = float(min(self.cfg.speed_max, desired))
        self._new(lane=lane, s=s, desired=desired, speed=desired)

    def _park(self, slot: int) -> None:
        self.slot_taken[slot] = True
        xy = self.scene.slots.xy[slot] + self.rng.normal(0, 0.3, 2)
        self._new(xy=xy, angle=float(self.scene.slots.angle[slot] + self.rng.normal(0, 0.05)), slot=slot)

    def _resolve_overlaps(self) -> None:
        """Drop vehicles closer than their half lengths + 2 px to the next one on the same lane."""
        keep = []
        for lane_idx in range(len(self.scene.lanes)):
            on = sorted((v for v in self.vehicles if v.lane == lane_idx), key=lambda v: -v.s)
            last = None
            for v in on:
                if last is None or last.s - v.s >= (last.length + v.length) / 2 + 2:
                    keep.append(v)
                    last = v
        self.vehicles = keep + [v for v in self.vehicles if v.lane < 0]

    def step(self) -> None:
        """Advance one frame: car following, intersection slow-down, births, deaths, parking, dropouts."""
        cfg, rng, lanes = self.cfg, self.rng, self.scene.lanes
        alive = []
        for lane_idx, lane in enumerate(lanes):
            on = sorted((v for v in self.vehicles if v.lane == lane_idx), key=lambda v: -v.s)
            leader_s, leader_len = np.inf, 0.0
            for v in on:
                factor = 1.0
                if len(lane.intersections):
                    d = float(np.min(np.abs(lane.intersections - v.s)))
                    factor = min(1.0, cfg.intersection_slowdown
                                 + (1 - cfg.intersection_slowdown) * d / cfg.intersection_radius)
                limit = leader_s - (leader_len + v.length) / 2 - 2.0
                target = v.desired * factor
                if cfg.headway > 0:
                    target = min(target, max(0.0, limit - v.s) / cfg.headway)
                v.speed += 0.5 * (target - v.speed)
                new_s = max(v.s, min(v.s + v.speed, limit))
                v.speed, v.s = new_s - v.s, new_s
                leader_s, leader_len = v.s, v.length
                if v.s <= lane.length:
                    alive.append(v)
            if rng.random() < cfg.birth_rate and (not on or min(v.s for v in on) > 2 * cfg.vehicle_length[1]):
                self._add_moving(lane_idx, 0.0)
                alive.append(self.vehicles[-1])
        parked = [v for v in self.vehicles if v.lane < 0]
        for v in parked:
            if rng.random() < cfg.park_toggle_rate:      # departure: a death in the car park
                self.slot_taken[v.slot] = False
            else:
                alive.append(v)
        self.vehicles = alive
        free = np.nonzero(~self.slot_taken)[0]
        for k in free[rng.random(len(free)) < cfg.park_toggle_rate]:   # arrival: a birth in the car park
            self._park(int(k))
        for v in self.vehicles:
            if v.dropout > 0:
                v.dropout -= 1
            elif rng.random() < cfg.dropout_rate:
                v.dropout = int(rng.integers(cfg.dropout_length[0], cfg.dropout_length[1] + 1))

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres ``(N, 2)`` and unit headings ``(N, 2)`` of all vehicles (world canvas)."""
        xy = np.zeros((len(self.vehicles), 2))
        head = np.zeros((len(self.vehicles), 2))
        for lane_idx, lane in enumerate(self.scene.lanes):
            idx = [i for i, v in enumerate(self.vehicles) if v.lane == lane_idx]
            if idx:
                xy[idx], head[idx] = lane.at(np.array([self.vehicles[i].s for i in idx]))
        for i, v in enumerate(self.vehicles):
            if v.lane < 0:
                xy[i] = v.xy
                head[i] = (np.cos(v.angle), np.sin(v.angle))
        return xy, head


def _draw_box(canvas: np.ndarray, c: np.ndarray, u: np.ndarray, length: float, width: float,
              tone: float, opacity: float = 1.0) -> None:
    """Blend an oriented rectangle with area-coverage (anti-aliased) edges into ``canvas`` in place."""
    r = int(np.ceil(max(length, width) / 2 + 2))
    x0, y0 = int(np.floor(c[0])) - r, int(np.floor(c[1])) - r
    x1, y1 = x0 + 2 * r + 2, y0 + 2 * r + 2
    h, w = canvas.shape
    if x1 <= 0 or y1 <= 0 or x0 >= w or y0 >= h:
        return
    ys, xs = np.mgrid[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)]
    dx, dy = xs - c[0], ys - c[1]
    du = np.abs(dx * u[0] + dy * u[1])
    dv = np.abs(-dx * u[1] + dy * u[0])
    a = opacity * np.clip(length / 2 - du + 0.5, 0, 1) * np.clip(width / 2 - dv + 0.5, 0, 1)
    patch = canvas[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)]
    patch += a.astype(np.float32) * (tone - patch)


def _jitter(cfg: VideoConfig, rng: np.random.Generator) -> np.ndarray:
    """Small random homography about the frame centre (reference -> frame)."""
    cx, cy = (cfg.width - 1) / 2, (cfg.height - 1) / 2
    th = rng.normal(0, cfg.jitter_rotation)
    sc = 1 + rng.normal(0, cfg.jitter_scale)
    t = rng.normal(0, cfg.jitter_translation, 2)
    A = np.array([[sc * np.cos(th), -sc * np.sin(th), 0], [sc * np.sin(th), sc * np.cos(th), 0], [0, 0, 1]])
    A[2, :2] = rng.normal(0, cfg.jitter_perspective, 2)
    T = np.array([[1, 0, cx + t[0]], [0, 1, cy + t[1]], [0, 0, 1]])
    Tm = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]])
    H = T @ A @ Tm
    return H / H[2, 2]


def _apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    return p[:, :2] / p[:, 2:3]


def generate_sequence(config: VideoConfig | None, generator: torch.Generator) -> Iterator[VideoFrame]:
    """Yield ``config.frames`` :class:`VideoFrame` s (see the module docstring for the conventions).

    Deterministic for a given ``generator`` state: it draws one 62-bit seed from it and drives a
    NumPy generator from that seed.
    """
    cfg = config or VideoConfig()
    rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,), generator=generator)))
    scene = build_scene(cfg, rng)
    world = _World(cfg, scene, rng)
    m = cfg.margin
    to_ref = np.array([[1.0, 0, -m], [0, 1, -m], [0, 0, 1]])
    sun = np.array([1.0, 1.0])
    phase = rng.uniform(0, 2 * np.pi, 3)
    sensor = Sensor(cfg, rng)
    omega = 0.1
    prev_xy: dict[int, np.ndarray] = {}
    for k in range(cfg.frames):
        if k:
            world.step()
        parallax = cfg.parallax_px / omega * np.array([np.sin(omega * k + phase[0]), np.cos(omega * k + phase[0])])
        canvas = scene.base.copy()
        draw_buildings(canvas, scene.buildings, parallax)
        xy_w, head = world.poses()
        vs = world.vehicles
        for i, v in enumerate(vs):
            if v.dropout > 0:
                continue
            if v.bright:
                _draw_box(canvas, xy_w[i] + sun, head[i], v.length, v.width, 20.0, 0.6)
            _draw_box(canvas, xy_w[i], head[i], v.length, v.width, v.tone)
        H = _jitter(cfg, rng)
        warp = H @ to_ref
        img = cv2.warpPerspective(canvas, warp, (cfg.width, cfg.height), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
        if cfg.psf_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), cfg.psf_sigma)
        img = sensor.optics(img)
        gain = 1 + cfg.gain_drift * np.sin(2 * np.pi * k / 40 + phase[1])
        offset = 3.0 * np.sin(2 * np.pi * k / 55 + phase[2])
        image = sensor.digitise(gain * img + offset + rng.normal(0, cfg.noise_std, img.shape))

        xy_img = _apply(warp, xy_w) if len(vs) else np.zeros((0, 2))
        ids = np.array([v.id for v in vs], np.int64)
        vel = np.array([xy_img[i] - prev_xy[v.id] if v.id in prev_xy else (np.nan, np.nan)
                        for i, v in enumerate(vs)]).reshape(-1, 2)
        prev_xy = {v.id: xy_img[i] for i, v in enumerate(vs)}
        inside = ((xy_img[:, 0] >= 0) & (xy_img[:, 0] <= cfg.width - 1) & (xy_img[:, 1] >= 0)
                  & (xy_img[:, 1] <= cfg.height - 1))
        visible = inside & np.array([v.dropout == 0 for v in vs], bool)
        moving = np.array([v.lane >= 0 for v in vs], bool)
        yield VideoFrame(k, image, ids[visible], xy_img[visible], vel[visible], moving[visible], H)


def write_sequence(config: VideoConfig | None, generator: torch.Generator, out: str | Path,
                   video_format: str = "png", progress: bool = False) -> Path:
    """Write a sequence to the folder ``out`` and return it.

    Layout: ``frames/000001.png ...`` (or ``video.mp4`` / ``video.avi`` when ``video_format`` is
    ``mp4`` / ``avi``), ``gt.txt`` in MOTChallenge form ``frame,id,x,y,w,h,conf,-1,-1,-1`` (frames from
    1, ``x, y`` the top-left corner of a ``gt_box_size`` box centred on the vehicle, conf 1),
    ``velocity.txt`` (``frame,id,vx,vy,moving``; px/frame, empty where unknown) and ``camera.json``
    with the true reference->frame homographies (see the module docstring). Each file appears whole (the
    video under ``video.partial.mp4`` until it is complete); ``torchtrack simulate-video`` writes the folder
    as one set (:class:`torchtrack.io.outputs.OutputFolder`).
    """
    cfg = config or VideoConfig()
    if video_format not in ("png", "mp4", "avi"):
        raise TorchtrackError(f"video format must be png, mp4 or avi, got {video_format!r}")
    out = Path(out)
    (out / "frames" if video_format == "png" else out).mkdir(parents=True, exist_ok=True)
    writer = None
    if video_format != "png":
        fourcc = cv2.VideoWriter_fourcc(*("mp4v" if video_format == "mp4" else "MJPG"))
        video = out / f"video.{video_format}"
        writer = cv2.VideoWriter(str(partial_name(video)), fourcc, 2.0, (cfg.width, cfg.height), False)
    half = cfg.gt_box_size / 2
    gt_lines, vel_lines, homs = [], [], []
    for f in tqdm(generate_sequence(cfg, generator), total=cfg.frames, desc="simulate-video", unit="frame",
                  disable=not progress):
        n = f.index + 1
        if writer is None:
            cv2.imwrite(str(out / "frames" / f"{n:06d}.png"), f.image)
        else:
            writer.write(f.image)
        for vid, (x, y), (vx, vy), moving in zip(f.ids, f.xy, f.velocity, f.moving):
            gt_lines.append(f"{n},{vid},{x - half:.3f},{y - half:.3f},{cfg.gt_box_size:g},"
                            f"{cfg.gt_box_size:g},1,-1,-1,-1")
            vtxt = "," if np.isnan(vx) else f"{vx:.3f},{vy:.3f}"
            vel_lines.append(f"{n},{vid},{vtxt},{int(moving)}")
        homs.append(f.homography.tolist())
    if writer is not None:
        writer.release()
        partial_name(video).replace(video)
    write_text(out / "gt.txt", "\n".join(gt_lines) + "\n")
    write_text(out / "velocity.txt", "\n".join(vel_lines) + "\n")
    camera = {
        "convention": "homographies[k] maps reference pixel coordinates (x = column, y = row) to frame k+1; "
                      "frame k+1 -> frame k is homographies[k-1] @ inv(homographies[k])",
        "width": cfg.width, "height": cfg.height, "gt_box_size": cfg.gt_box_size,
        "homographies": homs,
    }
    write_json(out / "camera.json", camera, indent=1)
    return out


def read_camera(path: str | Path) -> np.ndarray:
    """The true homographies ``(T, 3, 3)`` of a ``camera.json`` written by :func:`write_sequence`."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"a JSON {type(data).__name__}, not an object with a 'homographies' list")
        H = np.asarray(data["homographies"], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TorchtrackError(f"{path}: not a camera.json written by simulate-video ({exc})") from exc
    if H.ndim != 3 or H.shape[1:] != (3, 3):
        raise TorchtrackError(f"{path}: homographies must have shape (T, 3, 3), got {H.shape}")
    return H


class SyntheticSource(FrameSource):
    """Frames of :func:`torchtrack.sim.video.generate_sequence`, generated as they are read.

    ``truth`` holds the last frame's :class:`~torchtrack.sim.video.VideoFrame` (ids, positions,
    camera homography) while iterating. Iterating again regenerates the same sequence only if the
    ``generator`` is re-seeded: pass a fresh one per pass.
    """

    def __init__(self, config: VideoConfig | None = None, generator: torch.Generator | None = None,
                 name: str = "<synthetic>") -> None:
        self.config = config or VideoConfig()
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.path = name
        self.shape = (self.config.height, self.config.width)
        self.truth = None

    def __len__(self) -> int:
        return self.config.frames

    def __iter__(self) -> Iterator[Frame]:
        for vf in generate_sequence(self.config, self.generator):
            self.truth = vf
            yield Frame(vf.index + 1, vf.image, f"{self.path}[{vf.index + 1}]")
