"""Training loop, single process or under ``torchrun`` with ``DistributedDataParallel``.

``torchrun --nproc_per_node N -m torchtrack train-detector --config configs/detector.yaml`` runs the
same code: the process group comes from the environment (NCCL on GPUs when every local rank has one of its
own, gloo on CPUs otherwise), each rank takes
``batch / N`` items of every global batch through a ``DistributedSampler`` (same permutation on every
rank), and since items are pure functions of their index and the loss is a mean of per-sample terms,
the averaged gradient equals the single-process gradient of the global batch. Rank 0 writes the
caches, the checkpoints (``last.pt`` every epoch, ``best.pt`` by validation F1) and the progress bar. On a
GPU the kernels are the deterministic ones (cuDNN's autotuned choices are not), so the same seed gives the same
weights there too.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler
from tqdm import tqdm

from torchtrack.detector.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.detector.config import DetectorConfig
from torchtrack.detector.dataset import PairDataset, build_cache, collate
from torchtrack.detector.evaluate import evaluate_cache
from torchtrack.detector.inference import DEFAULT_WEIGHTS, Detector, detector_from_checkpoint
from torchtrack.detector.losses import detection_loss
from torchtrack.detector.targets import Targets
from torchtrack.errors import TorchtrackError


def _init_distributed() -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = torch.device("cpu")
    if world > 1:
        if torch.cuda.device_count() >= int(os.environ.get("LOCAL_WORLD_SIZE", str(world))):
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
        if not dist.is_initialized():
            dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cpu":
            torch.set_num_threads(max(1, min(torch.get_num_threads(), (os.cpu_count() or 1) // world)))
    elif torch.cuda.is_available():
        device = torch.device("cuda")
    return world, rank, device


def _barrier(world: int) -> None:
    if world > 1:
        dist.barrier()


def train(cfg: DetectorConfig, seed: int = 0, resume: bool = False, progress: bool = True,
          log=print, workers: int = 0) -> dict:
    """Train (or resume) the detector of ``cfg``; returns ``{"history": [...], "best": path}``.

    ``workers``: data-loading processes per training process (the samples, pure functions of their
    index, and hence the result do not depend on it).

    Each history entry: epoch, mean loss parts, samples/s and the validation scores (precision,
    recall, f1, velocity_error_px) on the held-out ``val`` sequences.
    """
    started = time.perf_counter()
    world, rank, device = _init_distributed()
    t = cfg.train
    if t.batch % world:
        raise TorchtrackError(f"train.batch {t.batch} is not divisible by the number of processes {world}")
    torch.manual_seed(seed)
    if device.type == "cuda":
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
        torch.use_deterministic_algorithms(True, warn_only=True)
    det = Detector(cfg)
    if t.init and not resume:
        try:
            det.net.load_state_dict(load_checkpoint(initial_weights(t.init))["model"])
        except RuntimeError as exc:
            raise TorchtrackError(f"train.init {t.init}: the weights do not fit model {cfg.model} "
                                  f"({str(exc).splitlines()[0]})") from None
        if rank == 0:
            log(f"train.init: starting from {initial_weights(t.init)}")
    model = det.net.to(device)
    net = DistributedDataParallel(model) if world > 1 else model
    if t.optimizer == "sgd":
        opt = torch.optim.SGD(model.parameters(), lr=t.lr, momentum=0.9, weight_decay=t.weight_decay)
    else:
        opt = torch.optim.Adam(model.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    total = t.epochs * t.steps_per_epoch
    warm = min(50, max(1, total // 10))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(s, total) / total)))
    out = Path(t.out)
    start, history, best_f1 = 0, [], -1.0
    if resume:
        ck = load_checkpoint(out / "last.pt")
        if dataclasses.replace(ck["config"], train=dataclasses.replace(ck["config"].train, epochs=t.epochs)) != cfg:
            raise TorchtrackError(f"--resume: {out / 'last.pt'} was trained with a different config")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        start, history = int(ck["epoch"]) + 1, list(ck["history"])
        best_f1 = max([h["val"]["f1"] for h in history] or [-1.0])
        if rank == 0:
            log(f"resuming from {out / 'last.pt'} after epoch {start}")
    if rank == 0:
        train_cache = build_cache(cfg, "train", seed, progress=progress)
        val_cache = build_cache(cfg, "val", seed, progress=progress)
    _barrier(world)
    if rank != 0:
        train_cache = build_cache(cfg, "train", seed)
    data = PairDataset(train_cache, cfg, seed)
    for epoch in range(start, t.epochs):
        data.set_epoch(epoch)
        sampler = DistributedSampler(data, num_replicas=world, rank=rank, shuffle=True, seed=seed, drop_last=True)
        sampler.set_epoch(epoch)
        loader = DataLoader(data, batch_size=t.batch // world, sampler=sampler, collate_fn=collate,
                            num_workers=workers, drop_last=True)
        model.train()
        bar = tqdm(total=len(loader), desc=f"epoch {epoch + 1}/{t.epochs}", unit="step",
                   disable=not (progress and rank == 0))
        sums = {"loss": 0.0, "heatmap": 0.0, "offset": 0.0, "velocity": 0.0, "matching": 0.0}
        n, t0 = 0, time.perf_counter()
        for x, tg in loader:
            x = x.to(device).contiguous(memory_format=torch.channels_last)
            tg = Targets(*(v.to(device) for v in tg))
            loss, parts = detection_loss(net(x, with_matching=t.match_weight > 0), tg, t.offset_weight,
                                         t.velocity_weight, t.match_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            n += 1
            sums["loss"] += loss.item()
            for k, v in parts.items():
                sums[k] += v
            rate = n * t.batch / (time.perf_counter() - t0)
            bar.set_postfix(loss=f"{sums['loss'] / n:.3f}", samples_per_s=f"{rate:.1f}")
            bar.update()
        bar.close()
        entry = {"epoch": epoch, **{k: v / max(1, n) for k, v in sums.items()},
                 "samples_per_s": n * t.batch / (time.perf_counter() - t0)}
        if rank == 0:
            det.eval()
            entry["val"] = evaluate_cache(det, val_cache, t.val_frames, cfg.decode.radius)
            entry["elapsed_s"] = time.perf_counter() - started     # this run (a resumed run restarts it)
            det.train()
            history.append(entry)
            v = entry["val"]
            log(f"epoch {epoch + 1}: loss {entry['loss']:.4f}  val precision {v['precision']:.3f} recall "
                f"{v['recall']:.3f} F1 {v['f1']:.3f} velocity error {v['velocity_error_px']:.2f} px/frame")
            payload = {"config": dataclasses.asdict(cfg), "model": model.state_dict(), "epoch": epoch,
                       "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "history": history,
                       "seed": seed}
            save_checkpoint(out / "last.pt", payload)
            if v["f1"] > best_f1:
                best_f1 = v["f1"]
                save_checkpoint(out / "best.pt", payload)
        _barrier(world)
    return {"history": history, "best": str(out / "best.pt"), "last": str(out / "last.pt")}


def initial_weights(init: str) -> Path:
    """``train.init``: a path, or the name of a weights file shipped in ``torchtrack/detector/weights``."""
    shipped = DEFAULT_WEIGHTS.parent / f"{init.removesuffix('.pt')}.pt"
    return shipped if "/" not in init and shipped.is_file() else Path(init)


THRESHOLDS = (0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55)


def calibrate_threshold(det: Detector, cache, n_frames: int, radius: float,
                        grid: tuple[float, ...] = THRESHOLDS) -> tuple[float, list[dict]]:
    """The decoding threshold of ``grid`` with the best F1 on the validation ``cache`` (each sequence
    run as a stream, so that the threshold also acts through the prior), and the scores per threshold."""
    rows = []
    for thr in grid:
        det.config = dataclasses.replace(det.config, decode=dataclasses.replace(det.config.decode, threshold=thr))
        rows.append({"threshold": thr, **evaluate_cache(det, cache, n_frames, radius)})
    best = max(rows, key=lambda r: r["f1"])
    return best["threshold"], rows


def export_weights(src: str | Path, dst: str | Path, extra: dict | None = None, calibrate=None) -> Path:
    """Write the model part of a training checkpoint (config, weights, history) for shipping.

    ``calibrate``: the validation :class:`~detector.dataset.SequenceCache`; the exported config then
    carries the decoding threshold of :func:`calibrate_threshold` (and ``calibration`` the scores)."""
    ck = load_checkpoint(src)
    cfg = ck["config"]
    info = {}
    if calibrate is not None:
        det = detector_from_checkpoint(ck)
        thr, rows = calibrate_threshold(det, calibrate, cfg.train.val_frames, cfg.decode.radius)
        cfg = dataclasses.replace(cfg, decode=dataclasses.replace(cfg.decode, threshold=thr))
        info["calibration"] = rows
    payload = {"config": dataclasses.asdict(cfg), "model": {k: v.contiguous() for k, v in ck["model"].items()},
               "epoch": ck.get("epoch"), "history": ck.get("history", []), **info, **(extra or {})}
    save_checkpoint(dst, payload)
    return Path(dst)
