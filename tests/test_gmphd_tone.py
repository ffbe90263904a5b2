"""The grey-level attribute of the labelled GM-PHD (torchtrack.filters.gmphd.tone) and the pipeline's
grey level per detection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.filters.gmphd.filter import GMPHD, MixtureState
from torchtrack.filters.gmphd.labels import label_handover, no_lost_labels
from torchtrack.filters.gmphd.tone import LabelTones, add_births, lookup, no_label_tones, tone_log_ratio, update_tones
from torchtrack.filters.trackers.options import GMPHDFilterOptions
from torchtrack.filters.trackers.protocol import make_tracker
from torchtrack.models import ConstantVelocity, LinearPosition
from torchtrack.pipeline.detection import grey_level
from torchtrack.pipeline.frame_detections import FrameDetections
from torchtrack.pipeline.tracker_stream import run_tracker_step

F64 = torch.float64


def test_tone_log_ratio_is_the_robust_gaussian_over_the_uniform_clutter_density():
    a = torch.tensor([100.0, float("nan")], dtype=F64)
    t = torch.tensor([100.0, 104.0, 30.0], dtype=F64)
    out = tone_log_ratio(a.unsqueeze(1), t, sigma=4.0, outlier=0.1, levels=256.0)
    for k, tk in enumerate(t.tolist()):
        gauss = math.exp(-0.5 * ((tk - 100.0) / 4.0) ** 2) / (4.0 * math.sqrt(2 * math.pi))
        assert float(out[0, k]) == pytest.approx(math.log((0.9 * gauss + 0.1 / 256.0) * 256.0), rel=1e-12)
    assert out[1].tolist() == [0.0, 0.0, 0.0]                # a label without a tone: ratio 1
    assert float(out[0, 2]) == pytest.approx(math.log(0.1), abs=1e-6)   # far off: the outlier's share only


def test_label_tones_are_a_running_then_exponential_mean_and_forget_labels_no_longer_alive():
    tones = add_births(no_label_tones(F64), torch.tensor([5, 6]), torch.tensor([100.0, 50.0], dtype=F64))
    z = torch.tensor([[0.0, 0.0], [40.0, 0.0]], dtype=F64)
    seen = [100.0]
    for t in (110.0, 120.0, 130.0, 140.0):
        tones = update_tones(tones, torch.tensor([5]), torch.tensor([[0.5, 0.0]], dtype=F64), z,
                             torch.tensor([t, 0.0], dtype=F64), rate=0.3, max_distance=3.0,
                             alive=torch.tensor([5, 6]))
        seen.append(t)
    # counts 1, 2, 3: running mean of 100, 110, 120 (steps 1/2, 1/3); then steps of max(1/4, 0.3) = 0.3
    expected = np.mean(seen[:3])
    for t in seen[3:]:
        expected += 0.3 * (t - expected)
    assert float(lookup(tones, torch.tensor([5]))) == pytest.approx(expected)
    assert float(lookup(tones, torch.tensor([6]))) == 50.0          # no detection within 3 px: unchanged
    assert torch.isnan(lookup(tones, torch.tensor([7]))).all()
    tones = update_tones(tones, torch.tensor([6]), torch.tensor([[60.0, 0.0]], dtype=F64), z,
                         torch.tensor([1.0, 2.0], dtype=F64), 0.3, 3.0, alive=torch.tensor([6]))
    assert tones.label.tolist() == [6] and tones.tone.tolist() == [50.0]


def test_update_multiplies_each_pairs_likelihood_by_the_given_ratio():
    phd = GMPHD(ConstantVelocity(2, q=1.0), LinearPosition(2, sigma=1.0),
                GMPHDFilterOptions(p_detection=0.8, clutter_density=1e-3)).to(F64)
    with torch.no_grad():
        mats = phd.matrices()
    mean = torch.tensor([[0.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]], dtype=F64)
    cov = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
    state = MixtureState(torch.tensor([0.9, 0.7], dtype=F64).log(), mean, cov, torch.tensor([1, 2]),
                         torch.ones(2, dtype=torch.bool))
    z = torch.tensor([[1.0, 0.5], [2.5, -0.5]], dtype=F64)
    ratio = torch.tensor([[2.0, 0.1], [0.5, 3.0]], dtype=F64)
    with torch.no_grad():
        post, _ = phd.update(state, z, mats, pair_loglik=lambda jj, kk: ratio.log()[jj, kk])
    # brute force: q_jk = p_D w_j N(z_k; m_j, P_j + R) r_jk, weight q_jk / (κ + Σ_j q_jk)
    pd, kappa = float(mats.p_detection), float(mats.clutter_density)
    S = cov[:, :2, :2] + torch.eye(2, dtype=F64)
    g = torch.stack([torch.distributions.MultivariateNormal(mean[j, :2], S[j]).log_prob(z).exp() for j in range(2)])
    q = pd * torch.tensor([[0.9], [0.7]], dtype=F64) * g * ratio
    expected = q / (kappa + q.sum(0, keepdim=True))
    got = post.log_weight[2:].exp()          # detection components after the two missed-detection ones
    pairs = {(int(lab), round(float(m), 6)) for lab, m in zip(post.label[2:], post.mean[2:, 0])}
    assert len(pairs) == 4
    assert sorted(got.tolist()) == pytest.approx(sorted(expected.flatten().tolist()), rel=1e-8)


def _follow(tone_sigma: float | None) -> np.ndarray:
    """A bright vehicle (tone 200) tracked along x; at frame 9 a dark detection lies closer to its prediction
    than its own. Returns the position reported for its label at frame 9 (the merge of its components: the
    detection it is drawn to dominates)."""
    options = {"dtype": "float64", "confirm_new": False, "filter": {"q": 0.1, "p_detection": 0.9}}
    tracker = make_tracker("gmphd", {**options, "tone_sigma": tone_sigma})
    for k in range(1, 9):
        ids, _ = tracker.step(k, torch.tensor([[2.0 * k, 0.0]], dtype=F64), None, tones=torch.tensor([200.0]))
    label = int(ids[0])
    z = torch.tensor([[18.0, 3.0], [18.0, -3.6]], dtype=F64)          # dark (closer), bright
    ids, pos = tracker.step(9, z, None, tones=torch.tensor([30.0, 200.0], dtype=F64))
    return pos[ids == label][0].numpy()


def test_the_tone_keeps_a_track_on_its_own_vehicle_where_position_alone_takes_the_nearer_one():
    assert _follow(None)[1] > 1.0          # without tones: drawn towards the dark detection (+3)
    assert _follow(4.0)[1] < -1.0          # with them: towards the bright one (−3.6)


def test_handover_refuses_a_lost_label_of_a_different_tone():
    tones = LabelTones(torch.tensor([3, 8]), torch.tensor([200.0, 40.0], dtype=F64), torch.tensor([5, 1]))
    lost = no_lost_labels(F64)
    args = (torch.tensor([8]), torch.tensor([[12.0, 0.0]], dtype=F64), torch.tensor([3]),
            torch.tensor([[10.0, 0.0]], dtype=F64), torch.tensor([[2.0, 0.0]], dtype=F64), lost, 10.0)
    assert label_handover(*args).tolist() == [3]                    # without tones: handed over
    assert label_handover(*args, tone_of=lambda lab: lookup(tones, lab), max_tone_gap=24.0).tolist() == [8]
    assert label_handover(*args, tone_of=lambda lab: lookup(tones, lab), max_tone_gap=200.0).tolist() == [3]


def test_bad_tone_options_are_refused():
    for bad in ({"tone_sigma": 0.0}, {"tone_sigma": 4.0, "tone_outlier": 1.0}, {"tone_rate": 0.0},
                {"tone_handover_gap": -1.0}):
        with pytest.raises(TorchtrackError, match="tone"):
            make_tracker("gmphd", bad)


def test_grey_level_is_the_window_mean_and_selection_keeps_it():
    image = np.zeros((20, 20), np.uint8)
    image[4:7, 9:12] = 90
    image[15, 15] = 255
    assert grey_level(image, np.array([[10.0, 5.0], [10.4, 5.3], [15.0, 15.0], [0.0, 0.0]])).tolist() == [
        90.0, 90.0, pytest.approx(255 / 9, abs=0.5), 0.0]
    pos = np.zeros((3, 2))
    det = FrameDetections(1, np.eye(3), pos, pos, np.ones(3), pos, pos, np.ones(3), np.ones(3, bool),
                          np.array([1.0, 2.0, 3.0]))
    assert det.select(np.array([True, False, True])).tones.tolist() == [1.0, 3.0]
    assert det._replace(tones=None).select(np.array([0])).tones is None


class _Recorder:
    def __init__(self, tone_sigma):
        self.tone_sigma = tone_sigma
        self.calls = []

    def step(self, frame, positions, velocities, **extra):
        self.calls.append(extra)
        return torch.arange(positions.shape[0]), positions


def test_the_pipeline_gives_grey_levels_only_to_a_tracker_that_uses_them():
    pos = np.array([[1.0, 2.0], [3.0, 4.0]])
    det = FrameDetections(2, np.eye(3), pos, pos, np.ones(2), pos, pos, np.ones(2), np.ones(2, bool),
                          np.array([40.0, 200.0]))
    with_tones, without = _Recorder(4.0), _Recorder(None)
    run_tracker_step(with_tones, det, F64)
    run_tracker_step(without, det, F64)
    assert with_tones.calls[0]["tones"].tolist() == [40.0, 200.0]
    assert without.calls == [{}]
    run_tracker_step(with_tones, det._replace(tones=None), F64)
    assert with_tones.calls[1] == {}
