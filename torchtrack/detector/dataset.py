"""Training data: cached synthetic sequences and a dataset of perturbed frame pairs (CenterTrack).

The cache holds ``S`` sequences of ``T`` frames from :func:`torchtrack.sim.video.generate_sequence`
(uint8) with their truth, each from its own camera where ``data.cameras`` gives ranges
(:func:`sequence_camera`), saved once under ``data.cache`` (a file named by a hash of everything that
determines it). :class:`PairDataset` item ``i`` of epoch ``e`` is a pure function of ``(seed, e, i)``:
a random sequence and frame ``k >= 1``, a random crop and one of the 8 flips/rotations, the previous
frame ``k-1`` and the prior heatmap of the previous truth perturbed as in CenterTrack (centre jitter,
dropped peaks, false peaks near objects and anywhere). With ``data.register`` the previous frame is
first warped onto the current one by the true camera motion, as the pipeline does after its
registration, so that static ground cancels between the two and only what moves differs (where the warp
has no previous pixels, along the frame's border, it takes the current ones, as the pipeline does); the prior and
the velocity targets are then in the current frame's coordinates (velocity over the ground). Being a pure
function of the index is what makes ``torchrun`` training with a ``DistributedSampler`` equal to
single-process training.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from torchtrack.detector.config import DetectorConfig
from torchtrack.detector.evaluate import ground_velocity
from torchtrack.detector.network import STRIDE
from torchtrack.detector.region import Region, crop_start
from torchtrack.detector.targets import Targets, gaussian_heatmap, make_targets
from torchtrack.errors import TorchtrackError
from torchtrack.geometry import apply_homography, warp_previous
from torchtrack.io.outputs import atomic_file
from torchtrack.sim.cameras import draw_camera, ranges_from_dict
from torchtrack.sim.video_config import VideoConfig

CACHE_VERSION = 3   # bump when the generator or the cache's content changes


class SequenceCache(NamedTuple):
    """frames (S, T, H, W) uint8; per frame ``f = s*T + t`` the truth rows ``start[f]:start[f+1]`` of
    ids (R,) int64, xy (R, 2) and velocity (R, 2) float32 (NaN where unknown); homography (S, T, 3, 3)
    float64, the true camera map reference -> frame."""

    frames: torch.Tensor
    start: torch.Tensor
    ids: torch.Tensor
    xy: torch.Tensor
    velocity: torch.Tensor
    homography: torch.Tensor

    def truth(self, s: int, t: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f = s * self.frames.shape[1] + t
        a, b = int(self.start[f]), int(self.start[f + 1])
        return self.ids[a:b], self.xy[a:b], self.velocity[a:b]


def split_seed(seed: int, split: str, index: int) -> int:
    """Generator seed of sequence ``index`` of a split: train, val and test never share a seed."""
    return {"train": 0, "val": 1, "test": 2}[split] * 10_000_000 + seed * 10_000 + index


def sequence_camera(cfg: DetectorConfig, video: VideoConfig, seq_seed: int) -> VideoConfig:
    """The camera of the sequence of generator seed ``seq_seed``: ``video``, or with ``data.cameras`` one drawn
    from those ranges by a generator of its own seeded from ``seq_seed``
    (:func:`torchtrack.sim.cameras.draw_camera`)."""
    if cfg.data.cameras is None:
        return video
    return draw_camera(ranges_from_dict(cfg.data.cameras), video, np.random.default_rng([seq_seed, 1]))


def build_cache(cfg: DetectorConfig, split: str, seed: int, count: int | None = None,
                progress: bool = False) -> SequenceCache:
    """Load the cached sequences of ``split`` or generate and save them (see module docstring)."""
    from torchtrack.sim.video import generate_sequence
    from torchtrack.sim.video_config import from_dict

    count = count if count is not None else (cfg.data.train_sequences if split == "train" else cfg.data.val_sequences)
    video = from_dict({**cfg.data.video, "frames": cfg.data.frames}, "data.video")
    key = json.dumps({"v": CACHE_VERSION, "video": repr(video), "split": split, "seed": seed, "n": count,
                      "cameras": cfg.data.cameras}, sort_keys=True)
    path = Path(cfg.data.cache) / f"{split}-{hashlib.sha1(key.encode()).hexdigest()[:12]}.pt"
    if path.is_file():
        try:
            return SequenceCache(**torch.load(path, weights_only=True))
        except Exception as exc:  # a damaged cache is regenerated
            print(f"detector cache {path} unreadable ({exc}); regenerating")
    frames, ids, xy, vel, homs, start = [], [], [], [], [], [0]
    for i in tqdm(range(count), desc=f"generating {split} sequences", unit="seq", disable=not progress):
        seq, seq_h = [], []
        seq_seed = split_seed(seed, split, i)
        for f in generate_sequence(sequence_camera(cfg, video, seq_seed), torch.Generator().manual_seed(seq_seed)):
            seq.append(torch.from_numpy(f.image))
            seq_h.append(torch.from_numpy(f.homography))
            ids.append(torch.from_numpy(f.ids))
            xy.append(torch.from_numpy(f.xy).float())
            vel.append(torch.from_numpy(f.velocity).float())
            start.append(start[-1] + len(f.ids))
        frames.append(torch.stack(seq))
        homs.append(torch.stack(seq_h))
    cache = SequenceCache(torch.stack(frames), torch.tensor(start), torch.cat(ids), torch.cat(xy), torch.cat(vel),
                          torch.stack(homs))
    with atomic_file(path) as tmp:
        torch.save(cache._asdict(), tmp)
    return cache


def _dihedral(img: torch.Tensor, pts: torch.Tensor, vec: torch.Tensor, code: int, size: int):
    """Apply flip/transposition ``code`` in 0..7 to images (..., n, n), points and vectors (N, 2)."""
    pts, vec = pts.clone(), vec.clone()
    if code & 1:                                     # horizontal flip
        img = img.flip(-1)
        pts[:, 0] = size - 1 - pts[:, 0]
        vec[:, 0] = -vec[:, 0]
    if code & 2:                                     # vertical flip
        img = img.flip(-2)
        pts[:, 1] = size - 1 - pts[:, 1]
        vec[:, 1] = -vec[:, 1]
    if code & 4:                                     # transpose
        img = img.transpose(-1, -2)
        pts, vec = pts.flip(-1), vec.flip(-1)
    return img, pts, vec


class PairDataset(Dataset):
    """``len = steps_per_epoch * batch``; item ``i`` -> ``(input (3, c, c), Targets at stride 2)``.

    ``region``: only its pixels are labelled (the crop is placed as much inside it as it fits and the
    cells outside are masked out of the loss, :attr:`Targets.labelled`); ``dont_care`` (S, T, H, W) bool:
    pixels of frame ``(s, t)`` that are neither positive nor negative either (vehicles the truth does not
    list, :mod:`torchtrack.detector.unlabelled`); ``augment``: both frames'
    normalised values scaled by one gain ``U(1 - g, 1 + g)`` and each given Gaussian noise of std ``n``
    (``finetune.gain``, ``finetune.noise``), for small labelled sets."""

    def __init__(self, cache: SequenceCache, cfg: DetectorConfig, seed: int, region: Region | None = None,
                 augment: bool = False, dont_care: torch.Tensor | None = None) -> None:
        s, t, h, w = cache.frames.shape
        c = cfg.data.crop
        if t < 2:
            raise TorchtrackError("detector data: need at least 2 frames per sequence")
        if c > min(h, w):
            raise TorchtrackError(f"detector data: crop {c} is larger than the frames ({h}x{w})")
        self.cache, self.cfg, self.seed, self.epoch = cache, cfg, seed, 0
        self.region, self.augment, self.dont_care = region, augment, dont_care
        fr = cache.frames.float()
        self.mean = fr.mean((2, 3))
        self.std = fr.std((2, 3)) + 1.0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.cfg.train.steps_per_epoch * self.cfg.train.batch

    def __getitem__(self, i: int) -> tuple[torch.Tensor, Targets]:
        d, cache = self.cfg.data, self.cache
        rng = np.random.default_rng([self.seed, self.epoch, i])
        n_seq, n_t, h, w = cache.frames.shape
        s, t = int(rng.integers(n_seq)), int(rng.integers(1, n_t))
        same = rng.random() < d.same_frame
        tp = t if same else t - 1
        c = d.crop
        if self.region is None:
            y0, x0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        else:
            r = self.region
            y0, x0 = crop_start(rng, r.y0, r.y1, c, h), crop_start(rng, r.x0, r.x1, c, w)
        crop = cache.frames[s, t, y0:y0 + c, x0:x0 + c]
        cur = (crop.float() - self.mean[s, t]) / self.std[s, t]
        _, xy, vel = cache.truth(s, t)
        _, pxy, _ = cache.truth(s, tp)
        if d.register and not same:
            m = (cache.homography[s, tp] @ torch.linalg.inv(cache.homography[s, t])).numpy()  # current -> previous
            prev = torch.from_numpy(warp_previous(cache.frames[s, tp].numpy(), m, (c, c), (x0, y0), fill=crop.numpy()))
            pxy = torch.from_numpy(apply_homography(pxy.numpy(), np.linalg.inv(m))).float()
            vel = torch.from_numpy(ground_velocity(xy.numpy(), vel.numpy(), m)).float()
        else:
            prev = cache.frames[s, tp, y0:y0 + c, x0:x0 + c]
        prev = (prev.float() - self.mean[s, tp]) / self.std[s, tp]
        xy = xy - torch.tensor([x0, y0], dtype=torch.float32)
        vel = torch.zeros_like(vel) if same else vel
        if same:
            prior_xy = torch.zeros(0, 2)
        else:
            pxy = pxy - torch.tensor([x0, y0], dtype=torch.float32)
            keep = torch.from_numpy(rng.random(len(pxy)) >= d.prior_drop)
            jitter = torch.from_numpy(rng.normal(0, d.prior_jitter, (len(pxy), 2))).float()
            near = torch.from_numpy(rng.random(len(pxy)) < d.prior_false)
            false_near = pxy[near] + torch.from_numpy(rng.normal(0, 4.0, (int(near.sum()), 2))).float()
            clutter = torch.from_numpy(rng.uniform(0, c, (rng.poisson(d.prior_clutter), 2))).float()
            prior_xy = torch.cat([(pxy + jitter)[keep], false_near, clutter])
        labelled = None if self.region is None else self.region.mask((h, w))[y0:y0 + c, x0:x0 + c]
        if self.dont_care is not None:
            known = ~self.dont_care[s, t, y0:y0 + c, x0:x0 + c]
            labelled = known if labelled is None else labelled & known
        img = torch.stack([cur, prev] + ([] if labelled is None else [labelled.float()]))
        code = int(rng.integers(8))
        img, xy, vel = _dihedral(img, xy, vel, code, c)
        _, prior_xy, _ = _dihedral(img[:0], prior_xy, prior_xy, code, c)
        if labelled is not None:
            img, labelled = img[:2], img[2] > 0.5
        if self.augment:
            f = self.cfg.finetune
            gain = rng.uniform(1 - f.gain, 1 + f.gain)
            img = img * gain + torch.from_numpy(rng.normal(0, f.noise, img.shape)).float()
        prior = gaussian_heatmap(prior_xy, (c, c), d.prior_sigma)
        x = torch.cat([img, prior[None]]).contiguous()
        return x, make_targets(xy, vel, (c, c), STRIDE, d.target_sigma, labelled)


def collate(batch: list[tuple[torch.Tensor, Targets]]) -> tuple[torch.Tensor, Targets]:
    """Stack inputs and targets into ``(B, 3, c, c)`` and a batched :class:`Targets`."""
    xs, ts = zip(*batch)
    return torch.stack(xs), Targets(*(torch.stack(parts) for parts in zip(*ts)))
