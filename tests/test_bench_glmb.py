"""The NumPy reference of ``bench glmb`` against our δ-GLMB where the two must agree (one group, the sampler
replaced by exhaustive enumeration: the same hypotheses, weights, tables and estimates), its Gibbs sampler
against the exact posterior, and the command on a tiny workload."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch

import torchtrack.filters.glmb.filter as glmb_module
from torchtrack.association.gibbs import FIRST_MEASUREMENT
from torchtrack.bench.glmb_reference import ReferenceGLMB, enumerate_choices, gibbs_chain
from torchtrack.cli import main
from torchtrack.filters.trackers.options import tracker_config
from torchtrack.filters.trackers.protocol import make_tracker

CONFIG = {"q": 0.5, "sigma": 1.0, "velocity_sigma": None, "p_survival": 0.9, "p_detection": 0.9,
          "clutter_density": 0.01, "prune_threshold": 1e-5, "max_hypotheses": 100000, "birth_min": 0.05,
          "birth_rate": 1.0, "confirm_frames": 1}


def _enumerating_sampler(log_eta, cand, rows, widths, n_meas, sweeps, generator=None, active=None):
    """Stands in for :func:`gibbs_sample`: every chain returns every feasible joint choice of its rows (padded
    by repeating the last; the filter keeps distinct samples), so the filter's hypotheses are exact."""
    C, P = rows.shape
    out = torch.zeros(C, sweeps, P, dtype=torch.long)
    for c in range(C):
        options = []
        for p in range(P):
            r = int(rows[c, p])
            if r < 0:
                options.append([0])
                continue
            cols = [k for k in range(widths[p]) if math.isfinite(float(log_eta[r, k]))
                    and (k < FIRST_MEASUREMENT or int(cand[r, k - FIRST_MEASUREMENT]) >= 0)]
            options.append(cols)
        feasible = []
        for combo in itertools.product(*options):
            meas = [int(cand[int(rows[c, p]), k - FIRST_MEASUREMENT]) for p, k in enumerate(combo)
                    if k >= FIRST_MEASUREMENT]
            if len(meas) == len(set(meas)):
                feasible.append(combo)
        assert len(feasible) <= sweeps
        feasible += [feasible[-1]] * (sweeps - len(feasible))
        out[c] = torch.tensor(feasible)
    return out


def _frames():
    """Two vehicles 2 px apart (one gating group every frame), positions with fixed noise, one missed."""
    noise = np.array([[0.3, -0.2], [-0.4, 0.1], [0.2, 0.5], [-0.1, -0.3], [0.4, 0.2], [0.0, -0.5], [-0.3, 0.3]])
    frames = []
    for k in range(4):
        truth = np.array([[1.0 * k, 0.5 * k], [2.0 + 1.0 * k, 0.5 * k]])
        z = truth + noise[k:k + 2]
        frames.append(z[:1] if k == 2 else z)
    return frames


def _hypotheses(ours_state):
    """Our hypotheses as (labels, means (L, 4)) → weight, all in one group."""
    out = []
    for rows, lw in zip(ours_state.hyp.tolist(), ours_state.log_weight.tolist()):
        rows = [r for r in rows if r >= 0]
        labels = tuple(tuple(ours_state.label[r].tolist()) for r in rows)
        order = np.argsort([lab[1] for lab in labels], kind="stable")
        out.append((tuple(labels[i] for i in order), ours_state.mean[[rows[i] for i in order]].numpy(), lw))
    return out


def _reference_hypotheses(ref_state):
    out = []
    for h in ref_state.hypotheses:
        tracks = sorted(h.tracks, key=lambda t: ref_state.table[t].label[1])
        out.append((tuple(ref_state.table[t].label for t in tracks),
                    np.array([ref_state.table[t].mean for t in tracks]).reshape(-1, 4), h.log_weight))
    return out


def test_reference_equals_our_filter_with_every_assignment_enumerated(monkeypatch):
    monkeypatch.setattr(glmb_module, "gibbs_sample", _enumerating_sampler)
    ours = make_tracker("glmb", dict(CONFIG, chains=1, sweeps=3000))
    reference = ReferenceGLMB(tracker_config("glmb", CONFIG), enumerate_all=True)
    for frame, z in enumerate(_frames(), start=1):
        ids, positions = ours.step(frame, torch.tensor(z))
        ref_labels, ref_means, _ = reference.step(frame, z)
        state = ours.state
        assert int(state.group.max()) == 0                     # one group: the two filters define the same GLMB
        mine, theirs = _hypotheses(state), _reference_hypotheses(reference.state)
        assert len(mine) == len(theirs) > 0
        for labels, means, lw in mine:                         # each of ours matches one of the reference's
            match = [(float(np.abs(m - means).max(initial=0.0)), w) for lab, m, w in theirs if lab == labels]
            assert match, labels
            gap, w = min(match)
            assert gap < 1e-9 and abs(math.exp(w) - math.exp(lw)) < 1e-9
        order = np.argsort([lab[1] for lab in ref_labels])       # the estimate (confirm_frames 1: all reported)
        assert sorted((ids - 1).tolist()) == sorted(lab[1] for lab in ref_labels)
        mine_order = torch.argsort(ids)
        np.testing.assert_allclose(positions[mine_order].numpy(), ref_means[order, :2].reshape(-1, 2), atol=1e-9)
    assert reference.next_index == ours.next_index and ours.births.mean.shape[0] == len(reference.births)
    np.testing.assert_allclose(ours.births.log_r.numpy(), [lr for _, lr in reference.births], atol=1e-9)
    assert len(_reference_hypotheses(reference.state)) > 5     # a non-trivial density by the last frame


def test_reference_with_gibbs_tracks_one_target_as_our_filter():
    """One target, no clutter, p_D 1: a single hypothesis either way (the sampler's draws cannot differ), so the
    reference's Gibbs path gives our filter's estimate, to 1e-9, frame by frame (positions only: two-point
    births (B3) on both sides)."""
    cfg = {"q": 0.5, "sigma": 1.0, "velocity_sigma": None, "p_detection": 1.0, "clutter_density": 1e-12,
           "confirm_frames": 1}
    ours, reference = make_tracker("glmb", cfg), ReferenceGLMB(tracker_config("glmb", cfg), seed=5)
    rng = np.random.default_rng(3)
    zs = np.array([10.0, 20.0]) + np.outer(np.arange(1, 13), [1.5, -0.5]) + rng.normal(0, 1.0, (12, 2))
    for frame, z in enumerate(zs, start=1):
        ids, positions = ours.step(frame, torch.tensor(z[None]))
        labels, means, used = reference.step(frame, z[None])
        assert len(reference.state.hypotheses) == 1 and ids.tolist() == [lab[1] + 1 for lab in labels]
        np.testing.assert_allclose(means[:, :2], positions.numpy(), atol=1e-9)
        assert used.tolist() == ([1.0] if frame > 2 else [0.0])   # two-point births: the first from frames 1, 2
    assert ids.tolist() == [1] and reference.draws > 0


def test_reference_gibbs_chain_samples_the_exact_posterior():
    """One long chain over 3 tracks and 2 measurements: frequencies of the 7 × 7 joint choices against
    π(γ) ∝ Π η_i(γ_i) enumerated; 20 000 sweeps, every probability within 0.015 (about 5 standard errors of a
    correlated chain at these sizes)."""
    rng = np.random.default_rng(1)
    eta = [np.array([0.3, 0.5, 2.0, 0.7]), np.array([0.1, 0.6, 1.5, 1.2]), np.array([0.8, 0.2, 0.0, 0.9])]
    exact = {g: math.prod(e[c] for e, c in zip(eta, g)) for g in enumerate_choices(eta)}
    total = sum(exact.values())
    samples = gibbs_chain(eta, 20000, rng)
    counts = {g: 0 for g in exact}
    for s in samples:
        counts[s] += 1                                          # KeyError: an infeasible sample
    for g, p in exact.items():
        assert abs(counts[g] / len(samples) - p / total) < 0.015, g


@pytest.mark.parametrize("velocities", [False, True])
def test_bench_glmb_cli_tiny(tmp_path, velocities):
    out = tmp_path / "glmb.json"
    argv = ["bench", "glmb", "--targets", "10", "--warmup", "3", "--frames", "3", "--reference-frames", "2",
            "--json", str(out)] + (["--velocities"] if velocities else [])
    assert main(argv) == 0
    payload = json.loads(out.read_text())
    assert {"workload", "ours_per_s", "reference", "reference_per_s", "ratio", "unit"} <= set(payload)
    assert payload["ours_per_s"] > 0 and payload["reference_per_s"] > 0
    assert payload["ratio"] == pytest.approx(payload["ours_per_s"] / payload["reference_per_s"])
