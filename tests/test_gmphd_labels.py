"""Labels: the label fix (section 2.3), per-label extraction, label hand-over, relabelling."""

from __future__ import annotations

import pytest
import torch

from torchtrack.filters.gmphd.filter import MixtureState, as_rows, labels_in
from torchtrack.filters.gmphd.labels import (
    LostLabels,
    best_per_label,
    confirm_labels,
    label_fix,
    label_handover,
    no_lost_labels,
    no_tentative_labels,
    relabel,
)
from torchtrack.filters.trackers.protocol import make_tracker

F64 = torch.float64


def mixture(weights, positions, labels) -> MixtureState:
    n = len(weights)
    pos = torch.tensor(positions, dtype=F64)
    mean = torch.cat([pos, torch.zeros(n, 2, dtype=F64)], 1)
    return MixtureState(torch.tensor(weights, dtype=F64).log(), mean, torch.eye(4, dtype=F64).expand(n, 4, 4),
                        torch.tensor(labels), torch.ones(n, dtype=torch.bool))


def test_label_fix_keeps_label_for_hypothesis_closest_to_previous_estimate():
    # label 7 has three high-weight hypotheses; its previous estimate was at (10, 0)
    st = mixture([0.9, 0.8, 0.95, 0.7], [[0, 0], [11, 0], [30, 0], [50, 50]], [7, 7, 7, 3])
    est = torch.tensor([True, True, True, True])
    out, nxt = label_fix(st, est, torch.tensor([3, 7]), torch.tensor([[50.0, 50.0], [10.0, 0.0]], dtype=F64), 100)
    assert out.label.tolist()[1] == 7            # the closest to (10, 0) keeps it, although not the heaviest
    assert sorted(out.label.tolist()[i] for i in (0, 2)) == [100, 101]
    assert out.label.tolist()[3] == 3 and nxt == 102
    # a label without a previous estimate: the heaviest keeps it
    out, nxt = label_fix(st, est, torch.tensor([3]), torch.tensor([[50.0, 50.0]], dtype=F64), 100)
    assert out.label.tolist()[2] == 7 and nxt == 102


def test_best_per_label_reports_one_estimate_per_label():
    st = mixture([0.9, 0.8, 0.95, 0.7], [[0, 0], [11, 0], [30, 0], [50, 50]], [7, 7, 7, 3])
    idx = best_per_label(st, torch.ones(4, dtype=torch.bool))
    assert sorted(idx.tolist()) == [2, 3]


def test_relabel_and_handover():
    st = mixture([0.9, 0.1, 0.8], [[0, 0], [1, 0], [20, 0]], [5, 5, 9])
    out = relabel(st, torch.tensor([5, 9]), torch.tensor([5, 2]))
    assert out.label.tolist() == [5, 5, 2]
    # label 4 was reported last frame at (0, 0) moving +3 px/frame; now a new label 12 appears at (3.5, 0)
    lost = no_lost_labels(F64)
    handed = label_handover(torch.tensor([12, 6]), torch.tensor([[3.5, 0.0], [40.0, 0.0]], dtype=F64),
                            torch.tensor([4, 6]), torch.tensor([[0.0, 0.0], [40.0, 0.0]], dtype=F64),
                            torch.tensor([[3.0, 0.0], [0.0, 0.0]], dtype=F64), lost, max_distance=2.0)
    assert handed.tolist() == [4, 6]
    far = label_handover(torch.tensor([12]), torch.tensor([[9.0, 0.0]], dtype=F64), torch.tensor([4]),
                         torch.tensor([[0.0, 0.0]], dtype=F64), torch.tensor([[3.0, 0.0]], dtype=F64), lost, 2.0)
    assert far.tolist() == [12]


def test_handover_never_gives_a_label_that_is_reported_in_the_same_frame():
    # label 7 was lost two frames ago near (0, 0) moving +3 px/frame and is reported again now at (6, 0);
    # a brand-new estimate (label 12) also lies on its path: it must not take 7 (no duplicate identities)
    lost = LostLabels(torch.tensor([7]), torch.tensor([[0.0, 0.0]], dtype=F64), torch.tensor([[3.0, 0.0]], dtype=F64),
                      torch.tensor([1]))
    out = label_handover(torch.tensor([7, 12]), torch.tensor([[6.0, 0.0], [6.5, 0.0]], dtype=F64),
                         torch.tensor([3]), torch.tensor([[50.0, 0.0]], dtype=F64),
                         torch.tensor([[0.0, 0.0]], dtype=F64), lost, max_distance=2.0)
    assert out.tolist() == [7, 12]


def _split_scene(tracker_name: str):
    """Two vehicles drive together (one detection, one component), then split in opposite directions."""
    tracker = make_tracker(tracker_name, {"dtype": "float64", "handover_frames": 0})
    reported = []
    for k in range(1, 25):
        if k <= 8:
            z = torch.tensor([[100.0 + 2.0 * k, 100.0]], dtype=F64)
        else:
            s = k - 8
            z = torch.tensor([[116.0 + 2.0 * s, 100.0 + 2.0 * s], [116.0 + 2.0 * s, 100.0 - 2.0 * s]], dtype=F64)
        v = torch.tensor([[2.0, 0.0]], dtype=F64).expand(z.shape[0], 2)
        ids, pos = tracker.step(k, z, v)
        reported.append((ids.tolist(), pos))
    return reported


def test_label_fix_separates_two_tracks_that_split_from_one_component():
    rep = _split_scene("gmphd")
    ids_before = {i for ids, _ in rep[3:8] for i in ids}
    assert len(ids_before) == 1                               # one track while they drive together
    (old,) = ids_before
    tail = rep[-8:]
    for ids, _ in tail:
        assert len(ids) == 2 and len(set(ids)) == 2           # two tracks with distinct labels
    upper = {ids[int(torch.argmax(pos[:, 1]))] for ids, pos in tail}
    lower = {ids[int(torch.argmin(pos[:, 1]))] for ids, pos in tail}
    assert len(upper) == 1 and len(lower) == 1 and upper != lower   # each label follows one vehicle
    assert old in upper | lower                               # the original label survives on one of them


def test_without_label_fix_the_split_tracks_share_one_label():
    rep = _split_scene("labelled-gmphd")
    tail = rep[-8:]
    assert all(len(ids) == 1 for ids, _ in tail)              # duplicates of one label: only one reported


def _first_report(extracted: list[bool], frames: int, misses: int) -> int | None:
    """Brute force for one new label: the frame it is first reported, given per frame whether it is extracted
    (it stays in the mixture throughout)."""
    count = gap = 0
    for k, e in enumerate(extracted):
        if e:
            count = count + 1 if gap <= misses else 1
            gap = 0
            if count >= frames:
                return k
        else:
            gap += 1
            if gap > misses:
                count = 0
    return None


@pytest.mark.parametrize("frames,misses", [(2, 0), (3, 0), (3, 1), (3, 2), (4, 1)])
def test_confirmation_reports_a_new_label_from_its_nth_extraction(frames, misses):
    patterns = [[bool(b) for b in f"{n:08b}"] for n in range(256)]     # every 8-frame extraction pattern
    for pattern in patterns:
        tentative, reported_at = no_tentative_labels(), None
        for k, extracted in enumerate(pattern):
            label = torch.tensor([9] if extracted else [], dtype=torch.long)
            report, tentative = confirm_labels(label, torch.zeros_like(label, dtype=torch.bool), tentative,
                                               torch.tensor([9]), frames, misses)
            if bool(report.any()):
                reported_at = k
                break
        assert reported_at == _first_report(pattern, frames, misses), pattern


def test_confirmation_reports_known_labels_at_once_and_forgets_labels_gone_from_the_mixture():
    label = torch.tensor([4, 9])
    report, tentative = confirm_labels(label, torch.tensor([True, False]), no_tentative_labels(),
                                       torch.tensor([4, 9]), 3, 2)
    assert report.tolist() == [True, False] and tentative.label.tolist() == [9]
    _, tentative = confirm_labels(torch.tensor([4]), torch.tensor([True]), tentative, torch.tensor([4]), 3, 2)
    assert tentative.label.numel() == 0                      # label 9 was pruned from the mixture


def _first_reported_frame(options: dict, missed: frozenset = frozenset()) -> int | None:
    tracker = make_tracker("gmphd", {"dtype": "float64", **options})
    for k in range(1, 12):
        z = torch.empty(0, 2, dtype=F64) if k in missed else torch.tensor([[100.0 + 2.0 * k, 50.0]], dtype=F64)
        ids, _ = tracker.step(k, z, torch.tensor([[2.0, 0.0]], dtype=F64).expand(z.shape[0], 2))
        if ids.numel():
            return k
    return None


def test_tracker_reports_a_new_vehicle_after_confirm_new_extractions():
    at_once = _first_reported_frame({"confirm_new": False})
    assert at_once is not None
    assert [_first_reported_frame({"confirm_new": n}) for n in (True, 3, 4)] == [at_once + 1, at_once + 2, at_once + 3]
    # a missed detection between the extractions: the count restarts, unless confirm_misses lets it wait
    missed = frozenset({at_once + 1})
    assert _first_reported_frame({"confirm_new": 3}, missed) == at_once + 4
    assert _first_reported_frame({"confirm_new": 3, "confirm_misses": 1}, missed) == at_once + 3


@pytest.mark.parametrize("keys", [0, 1, 7, 300])
def test_labels_in_is_torch_isin(keys):
    gen = torch.Generator().manual_seed(keys)
    query = torch.randint(0, 200, (500,), generator=gen)
    among = torch.randint(0, 200, (keys,), generator=gen)          # repeated labels among the keys too
    assert torch.equal(labels_in(query, among), torch.isin(query, among))
    assert labels_in(query[:0], among).shape == (0,)


def test_as_rows_selects_what_the_mask_selects():
    mask = torch.tensor([True, False, True, True, False])
    values = torch.arange(5) * 10
    assert torch.equal(values[as_rows(mask)], values[mask])
    assert torch.equal(as_rows(torch.tensor([4, 1])), torch.tensor([4, 1]))
