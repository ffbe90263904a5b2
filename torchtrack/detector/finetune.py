"""Fine-tuning trained weights on labelled real frames (``train-detector --finetune``).

Each training pair is, with probability ``finetune.synthetic_share``, a synthetic pair of
:class:`~torchtrack.detector.dataset.PairDataset` (from ``finetune.synthetic_sequences`` cached
sequences, so that the synthetic skill is not forgotten), otherwise a pair of the labelled frames
(:mod:`torchtrack.detector.labelled`) cropped inside the labelled region, with the cells outside it
masked out of the loss, the 8 flips/transpositions, gain and noise (``finetune.gain``, ``noise``). With
``finetune.unlabelled_static: dont_care`` the neighbourhoods of the vehicles the truth does not list (the
starting weights' detections far from every truth point, :mod:`torchtrack.detector.unlabelled`) are masked
out of the loss as well. The
pairs are pure functions of ``(seed, index)``. Adam at ``finetune.lr`` with a linear warm-up (10 % of the
steps) and cosine decay; the losses are those of the synthetic training
(:func:`torchtrack.detector.losses.detection_loss`). Writes ``finetune.out/last.pt`` (the training
checkpoint format) every 100 steps and at the end.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from torchtrack.detector.checkpoint import save_checkpoint
from torchtrack.detector.config import DetectorConfig
from torchtrack.detector.dataset import PairDataset, build_cache, collate
from torchtrack.detector.inference import Detector
from torchtrack.detector.labelled import LabelledFrames
from torchtrack.detector.losses import detection_loss
from torchtrack.detector.region import Region
from torchtrack.detector.targets import Targets
from torchtrack.detector.unlabelled import dont_care_mask, unlabelled_detections

SAVE_EVERY = 100   # steps between checkpoints


class MixedPairs(Dataset):
    """Item ``i``: ``synthetic[i]`` with probability ``share`` (drawn from ``(seed, i)``), else ``real[i]``."""

    def __init__(self, real: Dataset, synthetic: Dataset | None, share: float, seed: int) -> None:
        self.real, self.synthetic, self.share, self.seed = real, synthetic, share, seed

    def __len__(self) -> int:
        return len(self.real)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, Targets]:
        if self.synthetic is not None and np.random.default_rng([self.seed, 29, i]).random() < self.share:
            return self.synthetic[i]
        return self.real[i]


def finetune(cfg: DetectorConfig, weights: dict, data: LabelledFrames, region: Region, seed: int = 0,
             progress: bool = True, log=print) -> dict:
    """Fine-tune the model state dict ``weights`` (whose architecture ``cfg.model`` describes) on ``data``
    inside ``region`` with ``cfg.finetune``; returns ``{"history": [...], "last": path, "seconds": s}``.

    history: per :data:`SAVE_EVERY` steps the mean loss and its parts."""
    started = time.perf_counter()
    f = cfg.finetune
    torch.manual_seed(seed)
    det = Detector(cfg)
    det.net.load_state_dict(weights)
    dont_care = None
    if f.unlabelled_static == "dont_care":
        unlisted = unlabelled_detections(det.eval(), data)
        log(f"unlabelled: {sum(len(p) for p in unlisted)} detections of the starting weights farther than "
            f"{det.config.decode.radius:g} px from every truth point are don't-care within {f.unlabelled_radius:g} px")
        dont_care = dont_care_mask(unlisted, data.frames.shape[1:], f.unlabelled_radius)[None]
    net = det.net.train()
    span = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps_per_epoch=f.steps, batch=f.batch))
    real = PairDataset(data.as_cache(), span, seed, region=region, augment=True, dont_care=dont_care)
    synthetic = None
    if f.synthetic_share > 0:
        synthetic = PairDataset(build_cache(span, "train", seed, count=f.synthetic_sequences, progress=progress),
                                span, seed)
    pairs = MixedPairs(real, synthetic, f.synthetic_share, seed)
    opt = torch.optim.Adam(net.parameters(), lr=f.lr)
    warm = max(1, f.steps // 10)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(s, f.steps) / f.steps)))
    t = cfg.train
    out = Path(f.out)
    history, sums, n = [], {}, 0
    bar = tqdm(total=f.steps, desc="fine-tuning", unit="step", disable=not progress)
    for step in range(f.steps):
        x, tg = collate([pairs[i] for i in range(step * f.batch, (step + 1) * f.batch)])
        loss, parts = detection_loss(net(x.contiguous(memory_format=torch.channels_last),
                                         with_matching=t.match_weight > 0),
                                     tg, t.offset_weight, t.velocity_weight, t.match_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        n += 1
        for k, v in {"loss": loss.item(), **parts}.items():
            sums[k] = sums.get(k, 0.0) + v
        bar.set_postfix(loss=f"{sums['loss'] / n:.3f}")
        bar.update()
        if (step + 1) % SAVE_EVERY == 0 or step + 1 == f.steps:
            history.append({"step": step + 1, **{k: v / n for k, v in sums.items()},
                            "elapsed_s": time.perf_counter() - started})
            sums, n = {}, 0
            save_checkpoint(out / "last.pt", {"config": dataclasses.asdict(cfg), "model": net.state_dict(),
                                              "epoch": 0, "step": step + 1, "optimizer": opt.state_dict(),
                                              "scheduler": sched.state_dict(), "history": history, "seed": seed})
    bar.close()
    seconds = time.perf_counter() - started
    log(f"fine-tuned {f.steps} steps of {f.batch} pairs in {seconds:.0f} s; last loss {history[-1]['loss']:.4f}")
    return {"history": history, "last": str(out / "last.pt"), "seconds": seconds}
