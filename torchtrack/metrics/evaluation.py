"""What ``torchtrack eval`` computes: the scores of one tracker output against its ground truth, and of a whole
benchmark in the MOTChallenge layout, its sequences combined as TrackEval combines them.

One sequence: CLEAR-MOT, MT/PT/ML, FRAG and IDF1 (:func:`~torchtrack.metrics.clear_mot.clear_mot`), HOTA
(:func:`~torchtrack.metrics.hota.hota`) with the same gate (a centre distance, or an IoU), optionally only the
moving objects (:func:`torchtrack.io.moving.moving_mask`: a synthetic sequence's ``velocity.txt`` flags, else
the paper's rule; the others are don't-care, as in every command that tracks and scores) and the per-frame OSPA / GOSPA
of the box centres. Several sequences (:func:`combine`): CLEAR-MOT's counts summed and its ratios recomputed,
HOTA from summed per-alpha counts with association and localisation weighted by TP (TrackEval's
``combine_sequences``), OSPA / GOSPA averaged over the frames of all sequences.

Layout (:func:`benchmark_sequences`): ground truth ``GT/SEQ/gt/gt.txt`` for every folder ``SEQ`` of ``GT``,
tracker output ``PRED/SEQ.txt`` (TrackEval's MOTChallenge layout, with ``PRED`` the tracker's ``data`` folder).
NumPy only unless OSPA is asked for, so that ``torchtrack eval`` starts without importing torch.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import MOTData, as_mot
from torchtrack.io.moving import flags_beside, moving_mask
from torchtrack.metrics import clear_mot, hota
from torchtrack.metrics.clear_mot import combine as combine_clear_mot
from torchtrack.metrics.hota import KEYS as HOTA_KEYS
from torchtrack.metrics.hota import combine as combine_hota
from torchtrack.metrics.table import gate, protocol, scoring

OSPA_KEYS = ("OSPA", "OSPA_localisation", "OSPA_cardinality", "GOSPA", "GOSPA_localisation", "GOSPA_missed",
             "GOSPA_false")


@dataclass(frozen=True)
class EvalOptions:
    """How tracks are scored.

    Attributes:
        threshold: centre-distance gate of CLEAR-MOT and ``D`` of HOTA's similarity ``max(0, 1 - d / D)``, px.
        iou: an IoU gate instead (HOTA's similarity is then the IoU).
        moving: score only the moving objects (:func:`torchtrack.io.moving.moving_mask`); the others are
            don't-care (predictions matched to them are dropped, neither hits nor false positives).
        count_zero_conf: score ground-truth lines with conf 0 as objects (default: don't-care, as MOTChallenge).
        ospa: the OSPA (p = 1) and GOSPA (p = 2, alpha = 2) cut-off in px; None: not computed.
    """

    threshold: float = 10.0
    iou: float | None = None
    moving: bool = False
    count_zero_conf: bool = False
    ospa: float | None = None

    @property
    def gate(self) -> str:
        return gate(self.threshold, self.iou)

    @property
    def protocol(self) -> str:
        """The line naming the objects scored and the gate (:func:`torchtrack.metrics.table.protocol`)."""
        return protocol(self.moving, self.threshold, self.iou)


@dataclass(frozen=True)
class Evaluation:
    """The scores of one sequence or of several combined.

    Attributes:
        clear_mot: the dict of :func:`~torchtrack.metrics.clear_mot.clear_mot`.
        hota: the dict of :func:`~torchtrack.metrics.hota.hota` (``per_alpha`` included).
        ospa_frames: :data:`OSPA_KEYS` → per-frame values (T,), or None when OSPA was not asked for.
    """

    clear_mot: dict
    hota: dict
    ospa_frames: dict[str, np.ndarray] | None = None

    def scores(self) -> dict:
        """One flat row: the CLEAR-MOT keys, the HOTA keys (means over alpha) and the OSPA means, if any."""
        row = {**self.clear_mot, **{key: self.hota[key] for key in HOTA_KEYS}}
        if self.ospa_frames is not None:
            row.update({key: float(v.mean()) if v.size else float("nan") for key, v in self.ospa_frames.items()})
        return row


def _ospa_frames(gt: MOTData, pred: MOTData, cutoff: float) -> dict[str, np.ndarray]:
    from torchtrack.metrics.ospa import mot_ospa_gospa  # torch: imported only when OSPA is asked for

    _, o, g = mot_ospa_gospa(gt, pred, c=cutoff, p_ospa=1.0, p_gospa=2.0)
    values = (o.total, o.localisation, o.cardinality, g.total, g.localisation, g.missed, g.false)
    return {key: v.numpy() for key, v in zip(OSPA_KEYS, values)}


def evaluate(gt: MOTData, pred: MOTData, options: EvalOptions = EvalOptions(),
             flags: str | Path | None = None) -> Evaluation:
    """The scores of tracker output ``pred`` against ground truth ``gt``; with ``options.moving``, ``flags`` is
    the sequence's ``velocity.txt`` (:func:`torchtrack.io.moving.flags_beside`), None for the paper's rule."""
    common = {"threshold": options.threshold, "iou": options.iou, "count_zero_conf": options.count_zero_conf,
              "ignore": ~moving_mask(gt, flags) if options.moving else None}
    return Evaluation(clear_mot(gt, pred, **common), hota(gt, pred, **common),
                      _ospa_frames(gt, pred, options.ospa) if options.ospa is not None else None)


def evaluate_scores(gt: str | os.PathLike | MOTData | np.ndarray, pred: str | os.PathLike | MOTData | np.ndarray,
                    *, threshold: float = 10.0, iou: float | None = None, moving: bool = False,
                    count_zero_conf: bool = False, ospa: float | None = None,
                    flags: str | os.PathLike | None = None) -> dict:
    """``torchtrack.evaluate``: the scores of ``torchtrack eval --json`` (CLEAR-MOT, MT/PT/ML, FRAG, IDF1, HOTA,
    and OSPA/GOSPA with ``ospa``; ratios as fractions; ``gate`` and ``moving_only`` say how it was scored) of the
    tracks ``pred`` against ``gt``, each a MOTChallenge file's path, a :class:`MOTData` or an array of its rows.
    Options as :class:`EvalOptions`; with ``moving``, the moving objects are those of
    :func:`torchtrack.io.moving.moving_mask` with ``flags`` (default: the ``velocity.txt`` beside ``gt`` where
    ``gt`` is a path and its sequence has one, as in ``torchtrack eval``)."""
    options = EvalOptions(threshold, iou, moving, count_zero_conf, ospa)
    if flags is None and isinstance(gt, str | os.PathLike):
        flags = flags_beside(gt)
    scores = evaluate(as_mot(gt, "gt"), as_mot(pred, "pred"), options, flags).scores()
    return {**scores, **scoring(moving, threshold, iou)}


def combine(evaluations: Sequence[Evaluation]) -> Evaluation:
    """Several sequences' scores together, as TrackEval combines sequences (see the module docstring)."""
    if not evaluations:
        raise TorchtrackError("no sequences to combine")
    frames = None
    if all(e.ospa_frames is not None for e in evaluations):
        frames = {key: np.concatenate([e.ospa_frames[key] for e in evaluations]) for key in OSPA_KEYS}
    return Evaluation(combine_clear_mot([e.clear_mot for e in evaluations]),
                      combine_hota([e.hota for e in evaluations]), frames)


def benchmark_sequences(gt_folder: Path, pred_folder: Path) -> list[tuple[str, Path, Path]]:
    """``(name, GT/SEQ/gt/gt.txt, PRED/SEQ.txt)`` for every sequence folder of ``gt_folder``, sorted by name.

    Raises TorchtrackError naming the folder when it holds no sequence, and naming the first tracker file
    that is missing (TrackEval refuses a benchmark with a sequence unscored, and so does this)."""
    gt_folder, pred_folder = Path(gt_folder), Path(pred_folder)
    for folder, what in ((gt_folder, "--gt-folder"), (pred_folder, "--pred-folder")):
        if not folder.is_dir():
            raise TorchtrackError(f"{what} {folder}: not a folder")
    sequences = sorted(p.parent.parent for p in gt_folder.glob("*/gt/gt.txt"))
    if not sequences:
        raise TorchtrackError(f"--gt-folder {gt_folder}: no sequence (expected {gt_folder}/SEQ/gt/gt.txt)")
    listed = []
    for seq in sequences:
        pred = pred_folder / f"{seq.name}.txt"
        if not pred.is_file():
            raise TorchtrackError(f"{pred}: no tracker output for sequence {seq.name} (expected PRED/SEQ.txt)")
        listed.append((seq.name, seq / "gt" / "gt.txt", pred))
    return listed
