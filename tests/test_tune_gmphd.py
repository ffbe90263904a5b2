"""Tuning the GM-PHD tracker: PHD-likelihood and soft-GOSPA gradients vs finite differences, and a fit of
p_D and the clutter rate from 3x off on simulated detections."""

import math

import numpy as np
import pytest
import torch

from torchtrack.errors import TorchtrackError
from torchtrack.io.mot import from_points, write_motdata
from torchtrack.tuning.parameters import get_raw, set_raw, set_values, tunable_parameters
from torchtrack.tuning.tune import fit, get_tunable, get_values, select_trainable

AREA = 300.0 * 300.0


def truth_file(tmp_path, targets=6, frames=60, seed=0):
    g = np.random.default_rng(seed)
    pos = g.uniform(60, 240, (targets, 2))
    vel = g.normal(0, 1.5, (targets, 2))
    rows = []
    for k in range(frames):
        for i in range(targets):
            p = pos[i] + vel[i] * k
            rows.append((k + 1, i + 1, p[0], p[1]))
    f, i, x, y = map(np.array, zip(*rows))
    path = tmp_path / "gt.txt"
    write_motdata(path, from_points(f, i, x, y))
    return path


def problem(tmp_path, pd=0.8, clutter=8.0, start=None, frames=60, window=20, dtype="float64"):
    start = start or {}
    model = {"tracker": "labelled-gmphd", "dtype": dtype,
             "filter": {"p_detection": start.get("pd", pd), "clutter_density": start.get("clutter", clutter) / AREA,
                        "area": AREA, "sigma": 1.0, "q": 0.1},
             "birth": {"birth_weight": 0.1}}
    tun = get_tunable("gmphd", model)
    data = tun.load_data({"truth": str(truth_file(tmp_path, frames=frames)),
                          "detections": {"pd": pd, "sigma": 1.0, "clutter": clutter, "image_size": [300, 300]},
                          "train_frames": [1, frames - 20], "held_out_frames": [frames - 19, frames],
                          "window": window, "burn_in": 3}, torch.Generator().manual_seed(1))
    return tun, tun.build(), data


def test_gmphd_parameter_names(tmp_path):
    _, tracker, _ = problem(tmp_path)
    names = set(tunable_parameters(tracker))
    assert {"phd.p_detection", "phd.clutter_density", "phd.measurement.sigma", "phd.motion.q",
            "birth.birth_weight"} <= names


@pytest.mark.parametrize("loss", ["phd", "bernoulli", "gospa"])
def test_gmphd_loss_gradients_match_finite_differences(tmp_path, loss):
    tun, tracker, data = problem(tmp_path, frames=30, window=8)
    names = ["phd.p_detection", "phd.clutter_density", "phd.measurement.sigma", "phd.motion.q", "birth.birth_weight"]
    params = select_trainable(tracker, names)
    items = data.train[:1]
    tun.loss(tracker, items, loss).backward()
    base = get_raw(tracker)
    for name in names:
        h = 1e-6
        vals = []
        for sign in (1, -1):
            set_raw(tracker, {**base, name: base[name] + sign * h})
            with torch.no_grad():
                vals.append(tun.loss(tracker, items, loss).item())
        set_raw(tracker, base)
        fd = (vals[0] - vals[1]) / (2 * h)
        assert params[name].raw.grad.item() == pytest.approx(fd, rel=1e-4, abs=1e-7), name


def test_the_bernoulli_likelihood_peaks_at_the_true_pd_where_the_phd_likelihood_does_not(tmp_path):
    tun, tracker, data = problem(tmp_path, pd=0.9, clutter=2.0, frames=100, window=40)
    losses = {}
    for loss in ("phd", "bernoulli"):
        for pd in (0.6, 0.75, 0.9, 0.97):
            set_values(tracker, {"phd.p_detection": pd})
            with torch.no_grad():
                losses[loss, pd] = tun.loss(tracker, data.train, loss).item()
    best = {loss: min((0.6, 0.75, 0.9, 0.97), key=lambda pd: losses[loss, pd]) for loss in ("phd", "bernoulli")}
    assert best == {"phd": 0.75, "bernoulli": 0.9}       # the PHD mass of a persistent target is 1/p_D


def test_gmphd_fit_recovers_pd_and_clutter_rate_from_3x_off(tmp_path):
    tun, tracker, data = problem(tmp_path, pd=0.8, clutter=8.0, start={"pd": 0.8 / 3, "clutter": 24.0})
    res = fit(tun, tracker, ["phd.p_detection", "phd.clutter_density"], data, "phd",
              {"name": "adam", "lr": 0.2, "steps": 24, "batch_size": 1}, {"patience": 100}, progress=False)
    values = get_values(tracker)
    pd, rate = values["phd.p_detection"].item(), values["phd.clutter_density"].item() * AREA
    assert abs(math.log(pd / 0.8)) < 0.5 * math.log(3)
    assert abs(math.log(rate / 8.0)) < 0.5 * math.log(3)
    assert res.held_out and res.held_out[-1][1] < res.held_out[0][1] + 1e-9
    metrics = tun.evaluate(tracker, data.held_out)
    assert {"MOTA", "OSPA", "IDS"} <= set(metrics)


def test_gmphd_needs_an_area_for_the_phd_likelihood(tmp_path):
    tun = get_tunable("gmphd", {"tracker": "labelled-gmphd", "dtype": "float64"})
    _, _, data = problem(tmp_path, frames=30)
    with pytest.raises(TorchtrackError, match="area"):
        tun.loss(tun.build(), data.train[:1], "phd")


def test_grid_search_scores_every_point_and_keeps_the_best(tmp_path):
    from torchtrack.tuning.grid import grid_search

    tun, tracker, data = problem(tmp_path, frames=40, window=20)
    out = grid_search(tun, tracker, {"metric": "MOTA", "values": {"phd.p_detection": [0.2, 0.8],
                                                                    "phd.clutter_density": [8.0 / AREA]}},
                      data, progress=False)
    assert out["combinations"] == 2 and out["filter_evaluations"] == 2 * len(data.train)
    scores = {}
    for pd in (0.2, 0.8):
        set_values(tracker, {"phd.p_detection": pd})
        scores[pd] = tun.evaluate(tracker, data.train)["MOTA"]
    assert out["best"]["phd.p_detection"] == max(scores, key=scores.get)
    assert out["train"]["MOTA"] == pytest.approx(max(scores.values()))
    with pytest.raises(TorchtrackError, match="valid names"):
        grid_search(tun, tracker, {"values": {"phd.nope": [1.0]}}, data, progress=False)


def test_exported_tracker_options_are_accepted_by_track(tmp_path):
    import yaml

    from torchtrack.filters.trackers.options import read_tracker_sections
    from torchtrack.filters.trackers.protocol import make_tracker

    tun, tracker, _ = problem(tmp_path, frames=30)
    set_values(tracker, {"phd.p_detection": 0.77, "birth.birth_weight": 0.03})
    name, doc = tun.export(tracker)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc))
    cfg = read_tracker_sections(path)
    rebuilt = make_tracker("labelled-gmphd", cfg["labelled-gmphd"])
    values = get_values(rebuilt)
    assert values["phd.p_detection"].item() == pytest.approx(0.77, rel=1e-6)
    assert values["birth.birth_weight"].item() == pytest.approx(0.03, rel=1e-6)


def test_contiguous_windows_are_scored_as_one_stream(tmp_path):
    tun, tracker, data = problem(tmp_path, frames=60, window=10)
    _, _, whole = problem(tmp_path, frames=60, window=40)   # the same detections (same seed), one window
    assert len(data.train) == 4 and len(whole.train) == 1
    assert tun.evaluate(tracker, data.train) == tun.evaluate(tracker, whole.train)
    full, mota = tun.evaluate(tracker, data.train), tun.score(tracker, data.train, "MOTA")   # searches skip the OSPA
    assert "OSPA" in full and "OSPA" not in mota and mota == {k: v for k, v in full.items() if k != "OSPA"}
    assert tun.score(tracker, data.train, "OSPA") == full


def test_training_frames_may_be_several_spans_each_streamed_from_empty(tmp_path):
    tun, tracker, _ = problem(tmp_path)
    base = {"truth": str(truth_file(tmp_path, frames=60)), "window": 10, "burn_in": 3,
            "detections": {"pd": 0.8, "sigma": 1.0, "clutter": 8.0, "image_size": [300, 300]}}

    def train(spans):
        return tun.load_data({**base, "train_frames": spans}, torch.Generator().manual_seed(1)).train

    both, first, second = train([[1, 20], [41, 60]]), train([1, 20]), train([41, 60])
    assert [w.frames for w in both] == [w.frames for w in first + second]
    assert all(all(torch.equal(a, b) for a, b in zip(w.z, v.z)) for w, v in zip(both, first + second))
    # the tracker restarts at the jump: the error counts are those of the two spans tracked separately
    pooled, a, b = (tun.score(tracker, items, "MOTA") for items in (both, first, second))
    assert all(pooled[k] == a[k] + b[k] for k in ("FP", "FN", "IDS"))
    for bad in ([[1, 20], [41]], [[1, 20], 41], ["a", 20]):
        with pytest.raises(TorchtrackError, match="or a list of such spans"):
            train(bad)


def test_refine_line_search_uses_training_items_only_and_counts_its_evaluations(tmp_path):
    from torchtrack.tuning.refine import refine
    from torchtrack.tuning.registry import TuneData

    tun, tracker, data = problem(tmp_path, frames=50, window=15, start={"pd": 0.15})
    train_only = TuneData(data.train, [object()])        # scoring a held-out item would fail
    start = tun.evaluate(tracker, data.train)["MOTA"]
    out = refine(tun, tracker, {"metric": "MOTA", "parameters": ["phd.p_detection"], "step": 1.0,
                                "evaluations": 5}, train_only, ["phd.p_detection"], progress=False)
    assert out["start"] == pytest.approx(start)
    assert out["best"] >= out["start"]
    assert out["best"] == pytest.approx(tun.evaluate(tracker, data.train)["MOTA"])   # left at the best point
    assert out["metric_evaluations"] <= 5
    assert out["filter_evaluations"] == out["metric_evaluations"] * len(data.train)
    assert out["frames"] == out["metric_evaluations"] * sum(len(w.frames) for w in data.train)
    if out["best"] > out["start"]:
        assert get_values(tracker)["phd.p_detection"].item() > 0.15
    with pytest.raises(TorchtrackError, match="valid names"):
        refine(tun, tracker, {"parameters": ["phd.nope"]}, data, ["phd.p_detection"], progress=False)


def test_refine_average_returns_the_centroid_of_the_best_points_within_the_budget(tmp_path):
    from torchtrack.tuning.refine import refine

    tun, tracker, data = problem(tmp_path, frames=30, window=15, start={"pd": 0.3})
    names = ["phd.p_detection", "phd.measurement.sigma"]
    calls = []

    def fake_evaluate(module, items, ospa=True):   # a smooth training metric, optimum at p_D 0.6, sigma 1.6
        v = get_values(module, names)
        calls.append(get_raw(module, names))
        pd, sigma = v["phd.p_detection"].item(), v["phd.measurement.sigma"].item()
        return {"MOTA": -(pd - 0.6) ** 2 - (math.log(sigma) - math.log(1.6)) ** 2}

    tun.evaluate = fake_evaluate
    out = refine(tun, tracker, {"parameters": names, "step": 0.5, "sweeps": 3, "evaluations": 9, "average": 3},
                 data, names, progress=False)
    assert len(calls) == out["metric_evaluations"] == 9
    # brute force: the 3 distinct searched points (all but the last call) with the highest metric, averaged in raw
    metric = []
    for raw in calls[:-1]:
        set_raw(tracker, raw)
        v = get_values(tracker, names)
        metric.append(-(v["phd.p_detection"].item() - 0.6) ** 2
                      - (math.log(v["phd.measurement.sigma"].item()) - math.log(1.6)) ** 2)
    distinct = {}
    for _, raw in sorted(zip(metric, calls[:-1]), key=lambda r: -r[0]):
        distinct.setdefault(tuple(round(x.item(), 9) for x in raw.values()), raw)
    top = list(distinct.values())[:3]
    centroid = {n: sum(r[n] for r in top) / 3 for n in names}
    for n in names:
        torch.testing.assert_close(calls[-1][n], centroid[n])
    set_raw(tracker, calls[-1])
    assert out["final"] == pytest.approx(fake_evaluate(tracker, data.train)["MOTA"])
    assert out["best"] == pytest.approx(max(metric))
    assert out["best"] > out["start"]
    with pytest.raises(TorchtrackError, match="average"):
        refine(tun, tracker, {"parameters": names, "evaluations": 1, "average": 2}, data, names, progress=False)


@pytest.mark.parametrize("lookahead", [False, True])
def test_refine_lookahead_crosses_a_flat_step(tmp_path, lookahead):
    from torchtrack.tuning.refine import refine

    tun, tracker, data = problem(tmp_path, frames=30, window=15, start={"pd": 0.3})
    names = ["phd.p_detection"]
    # flat from p_D 0.3 to beyond one step (logit +0.5: 0.41), better from two steps on (+1.0: 0.54)
    tun.evaluate = lambda module, items, ospa=True: {"MOTA": float(get_values(module, names)[names[0]] > 0.5)}
    out = refine(tun, tracker, {"parameters": names, "step": 0.5, "sweeps": 1, "evaluations": 6,
                                "lookahead": lookahead}, data, names, progress=False)
    pd = get_values(tracker, names)[names[0]].item()
    if lookahead:
        assert out["best"] == 1.0 and pd > 0.5
    else:
        assert out["best"] == 0.0 and pd == pytest.approx(0.3)
    with pytest.raises(TorchtrackError, match="lookahead"):
        refine(tun, tracker, {"parameters": names, "lookahead": "yes"}, data, names, progress=False)


def draws_config(tmp_path, seeds):
    model = {"tracker": "labelled-gmphd", "dtype": "float64",
             "filter": {"p_detection": 0.5, "clutter_density": 8.0 / AREA, "area": AREA, "sigma": 1.0, "q": 0.1},
             "birth": {"birth_weight": 0.1}}
    data = {"truth": str(truth_file(tmp_path, frames=40)),
            "detections": {"pd": 0.8, "sigma": 1.0, "clutter": 8.0, "image_size": [300, 300]},
            "train_frames": [1, 20], "held_out_frames": [21, 40], "window": 20, "burn_in": 3,
            "held_out_draws": seeds}
    return {"filter": "gmphd", "model": model, "trainable": ["phd.p_detection"], "data": data, "loss": "phd",
            "optimizer": {"name": "adam", "lr": 0.1, "steps": 2, "batch_size": 1},
            "grid": {"values": {"phd.p_detection": [0.3, 0.9]}}, "output": {"dir": str(tmp_path / "out")}}


def test_held_out_draws_simulate_the_held_out_frames_anew_per_seed(tmp_path):
    cfg = draws_config(tmp_path, [5, 6])
    tun = get_tunable("gmphd", cfg["model"])
    data = tun.load_data(cfg["data"], torch.Generator().manual_seed(1))
    again = tun.load_data(cfg["data"], torch.Generator().manual_seed(2))
    assert list(data.draws) == [5, 6]
    (held,) = data.held_out
    for seed, (item,) in data.draws.items():
        assert item.frames == held.frames and np.array_equal(item.truth.centers(), held.truth.centers())
        assert not all(torch.equal(a, b) for a, b in zip(item.z, held.z))        # a new draw ...
        assert all(torch.equal(a, b) for a, b in zip(item.z, again.draws[seed][0].z))   # ... fixed by its seed
    assert not all(torch.equal(a, b) for a, b in zip(data.draws[5][0].z, data.draws[6][0].z))


def test_tune_scores_the_tuned_filter_and_the_grid_on_every_draw(tmp_path):
    from torchtrack.tuning.tune import load_filter, tune

    cfg = draws_config(tmp_path, [5, 6])
    report = tune(cfg, progress=False)
    draws = report["held_out_draws"]
    assert draws["seeds"] == [5, 6] and set(draws) == {"seeds", "tuned", "grid"}
    tun = get_tunable("gmphd", cfg["model"])
    data = tun.load_data(cfg["data"], torch.Generator().manual_seed(0))
    fitted, grid = load_filter(report["output"]["params"]), tun.build()
    set_values(grid, report["grid"]["best"])
    for name, module in (("tuned", fitted), ("grid", grid)):
        expected = [tun.evaluate(module, data.draws[s])["MOTA"] for s in (5, 6)]
        assert [d["MOTA"] for d in draws[name]["per_draw"]] == pytest.approx(expected, abs=1e-12)
        assert draws[name]["MOTA"] == pytest.approx(sum(expected) / 2, abs=1e-12)


@pytest.mark.parametrize("seeds, data_change, message", [
    ("1000", {}, "non-empty list of distinct integer seeds"),
    ([], {}, "non-empty list of distinct integer seeds"),
    ([1, 2.5], {}, "non-empty list of distinct integer seeds"),
    ([1, 1], {}, "non-empty list of distinct integer seeds"),
    ([1], {"held_out_frames": None}, "needs simulated 'detections' and 'held_out_frames'"),
])
def test_held_out_draws_bad_values_are_refused(tmp_path, seeds, data_change, message):
    cfg = draws_config(tmp_path, seeds)
    cfg["data"].update(data_change)
    tun = get_tunable("gmphd", cfg["model"])
    with pytest.raises(TorchtrackError, match=message):
        tun.load_data(cfg["data"], torch.Generator().manual_seed(0))


def test_tune_command_prints_the_draws_table(tmp_path, capsys):
    import yaml

    from torchtrack.cli import main

    path = tmp_path / "tune.yaml"
    path.write_text(yaml.safe_dump(draws_config(tmp_path, [5, 6])))
    assert main(["tune", "--config", str(path), "--no-progress", "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "2 further detection draws (seeds 5, 6), mean:" in out
    assert any(line.split()[:1] == ["tuned"] for line in out.splitlines())
    assert any(line.split()[:1] == ["grid"] for line in out.splitlines())
