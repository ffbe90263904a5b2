"""Int8 inference of the detector's network (torchtrack.detector.quantized): its float pieces against the
network's own, the int8 maps and detections against the float network's, and which checkpoints run in int8."""

import dataclasses
import json
import os
import subprocess
import sys

import pytest
import torch
from torch.nn import functional as F

from torchtrack.cli import main
from torchtrack.detector.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.detector.config import DetectorConfig, ModelConfig
from torchtrack.detector.inference import DEFAULT_WEIGHTS, Detector, detector_from_checkpoint, load_detector
from torchtrack.detector.network import correlation, correlation_last
from torchtrack.detector.quantized import _coarse_fine, _shuffle, high_pass, quantize, weights_digest
from torchtrack.errors import TorchtrackError
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import from_dict


@pytest.mark.parametrize("w", [20, 32, 48])
def test_correlation_last_is_the_cost_volume(w):
    g = torch.Generator().manual_seed(0)
    a, b = (torch.randn(2, 5, 12, w, generator=g, dtype=torch.float64) for _ in range(2))
    with torch.no_grad():
        ref = correlation(a, b, 3)
        # brute force: the cost of displacement (dy, dx) at p is <a(p), b(p + d)> / C, zero outside the frame
        pad = F.pad(b, (3, 3, 3, 3))
        brute = torch.stack([(a * pad[:, :, dy:dy + 12, dx:dx + w]).sum(1) / 5
                             for dy in range(7) for dx in range(7)], 1)
        torch.testing.assert_close(ref, brute, rtol=0, atol=1e-12)
        torch.testing.assert_close(correlation_last(a, b, 3).permute(0, 3, 1, 2), ref, rtol=0, atol=1e-12)


def test_high_pass_and_shuffle_are_the_networks_operations():
    g = torch.Generator().manual_seed(1)
    f = torch.randn(2, 6, 9, 13, generator=g, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    ref = f - F.avg_pool2d(f, 3, 1, 1, count_include_pad=False)
    torch.testing.assert_close(high_pass(f, torch.full((6, 1, 3, 3), 1 / 9, dtype=torch.float64)), ref,
                               rtol=0, atol=1e-12)
    maps = torch.randn(2, 12, 5, 7, generator=g)
    assert torch.equal(_shuffle(maps.permute(0, 2, 3, 1)), F.pixel_shuffle(maps, 2))


def test_the_stride2_branch_at_stride4_is_the_networks():
    net = load_detector().net.double()
    fine_in, fine_mix, fine_out = (m.double() for m in _coarse_fine(net))
    g = torch.Generator().manual_seed(2)
    x, u = torch.randn(2, 3, 64, 48, generator=g, dtype=torch.float64), torch.randn(2, 32, 16, 12, generator=g,
                                                                                     dtype=torch.float64)
    with torch.no_grad():
        ref = net.fine_out(F.relu(net.fine_in(x) + F.interpolate(net.fine_mix(u), scale_factor=2, mode="nearest")))
        coarse = fine_out(F.relu(fine_in(x) + fine_mix(u)))                 # (2, 4 * 3, 16, 12)
    torch.testing.assert_close(F.pixel_shuffle(coarse, 2), ref, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def pair():
    """Two frames of a 256² synthetic sequence (the shipped generator) and the first frame's truth as the prior."""
    video = from_dict(dict(load_detector().config.data.video)).replace(width=256, height=256, frames=2)
    f0, f1 = generate_sequence(video, torch.Generator().manual_seed(5))
    return f1.image, f0.image, torch.as_tensor(f0.xy).float()


AGREEMENT = """
import json, sys
import torch
import torchtrack.detector.quantized as q
from torchtrack.detector.evaluate import match
from torchtrack.detector.inference import load_detector
from torchtrack.sim.video import generate_sequence
from torchtrack.sim.video_config import from_dict
q.ENGINE = sys.argv[1]
torch.set_num_threads(1)
ref, fast = load_detector(), load_detector(backend="int8")
video = from_dict(dict(ref.config.data.video)).replace(width=256, height=256, frames=2)
rows = []
for seed in (5, 6, 7):
    f0, f1 = generate_sequence(video, torch.Generator().manual_seed(seed))
    cur, prev, prior = f1.image, f0.image, torch.as_tensor(f0.xy).float()
    with torch.inference_mode():
        a, b = ref.detect(cur, prev, prior), fast.detect(cur, prev, prior)
    i, j = match(a.xy.double().numpy(), b.xy.double().numpy(), 1.0)
    hits = [len(match(d.xy.double().numpy(), f1.xy, 10.0)[0]) for d in (a, b)]
    rows.append({"float": len(a.xy), "int8": len(b.xy), "same": len(i), "truth": len(f1.xy),
                 "float_f1": 2 * hits[0] / (len(a.xy) + len(f1.xy)), "int8_f1": 2 * hits[1] / (len(b.xy) + len(f1.xy)),
                 "velocity_agree": float(((a.velocity[i] - b.velocity[j]).norm(dim=1) < 0.25).float().mean())})
print(json.dumps(rows))
"""
"""Float and int8 detections of three 256² synthetic frame pairs (the shipped generator, the previous frame's truth as
the prior): counts, detections the same within 1 px, velocities within 0.25 px/frame, F1 against the truth."""

INT8_PATHS = {
    "this CPU (x86 engine)": ("x86", {}),
    # what an AVX2-only CPU runs: fbgemm's AVX2 kernels, whose u8·s8 products are added in pairs in 16 bits
    # (vpmaddubsw, saturating) instead of VNNI's 32
    "AVX2 without VNNI": ("fbgemm", {"FBGEMM_ENABLE_INSTRUCTIONS": "AVX2"}),
}


@pytest.mark.parametrize("path", list(INT8_PATHS))
def test_int8_detections_agree_with_the_float_networks_on_each_kernel_path(path):
    """Measured: velocities agree for 0.908 / 0.945 / 0.976 of the same detections with VNNI and 0.804 / 0.931 /
    0.988 on the AVX2 path (the saturating sums move some block-matched velocities on one pair); against the truth
    both int8 paths score as the float network does (F1 within 0.013 on every pair)."""
    engine, env = INT8_PATHS[path]
    if engine not in torch.backends.quantized.supported_engines:
        pytest.skip(f"this torch has no {engine} quantisation engine")
    done = subprocess.run([sys.executable, "-c", AGREEMENT, engine], capture_output=True, text=True,
                          env={**os.environ, **env})
    assert done.returncode == 0, done.stderr[-2000:]
    rows = json.loads(done.stdout.strip().splitlines()[-1])
    for r in rows:
        assert r["float"] > 50 and abs(r["float"] - r["int8"]) <= 0.1 * r["float"]
        assert r["same"] >= 0.85 * r["float"]
        assert abs(r["int8_f1"] - r["float_f1"]) <= 0.02
    assert sum(r["velocity_agree"] for r in rows) / len(rows) >= 0.85


def test_int8_is_deterministic_and_close_to_the_float_maps(pair):
    cur, prev, prior = pair
    ref, fast = load_detector(), load_detector(backend="int8")
    assert (ref.backend, fast.backend) == ("float", "int8")
    with torch.inference_mode():
        maps_ref, maps_fast = (d.maps(*d.inputs(cur, prev, prior)) for d in (ref, fast))
        b = fast.detect(cur, prev, prior)
        again = load_detector(backend="int8").detect(cur, prev, prior)
    assert torch.equal(b.xy, again.xy) and torch.equal(b.velocity, again.velocity)
    assert (maps_ref[0].sigmoid() - maps_fast[0].sigmoid()).abs().max() < 0.25
    # the float network itself is what load_detector gives by default, unchanged by the int8 one beside it
    assert not torch.equal(maps_ref, maps_fast)


def _without_int8():
    data = load_checkpoint(DEFAULT_WEIGHTS)
    data.pop("int8")
    return data


def test_a_checkpoint_without_calibration_runs_in_float_and_int8_is_refused():
    data = _without_int8()
    assert detector_from_checkpoint(data, backend="auto").backend == "float"
    with pytest.raises(TorchtrackError, match="no int8 calibration"):
        detector_from_checkpoint(data, backend="int8")
    with pytest.raises(TorchtrackError, match="backend must be one of"):
        detector_from_checkpoint(data, backend="fp16")


def test_a_calibration_of_other_weights_is_not_used():
    data = load_checkpoint(DEFAULT_WEIGHTS)
    assert data["int8"]["weights"] == weights_digest(data["model"])
    assert detector_from_checkpoint(data, backend="auto").backend == "int8"
    data["model"]["heads.bias"] = data["model"]["heads.bias"] + 1e-3                  # fine-tuned weights
    assert detector_from_checkpoint(data, backend="auto").backend == "float"
    with pytest.raises(TorchtrackError, match="other weights"):
        detector_from_checkpoint(data, backend="int8")


def test_changed_weights_or_training_return_to_the_float_network(pair):
    det = load_detector(backend="int8")
    det.net.train()
    assert det.backend == "float"
    det.net.eval()
    assert det.backend == "int8"
    with torch.no_grad():
        det.net.heads.bias.add_(0.5)                                                   # a training step
    assert det.backend == "float"
    det.net.eval()
    assert det.backend == "float"                                                       # for good


def test_a_table_that_does_not_fit_is_refused():
    net = load_detector().net
    with pytest.raises(TorchtrackError, match="does not fit"):
        quantize(net, {"quant_x": [0.1, 0]})
    table = load_checkpoint(DEFAULT_WEIGHTS)["int8"]["table"]
    for bad in (["x", 0], [0.1], [0.0, 3], [0.1, 300]):
        with pytest.raises(TorchtrackError, match="quant_x"):
            quantize(net, {**table, "quant_x": bad})


def test_quantize_detector_writes_a_calibrated_copy(tmp_path):
    src = tmp_path / "plain.pt"
    data = _without_int8()
    raw = torch.load(DEFAULT_WEIGHTS, weights_only=True)
    raw.pop("int8")
    torch.save(raw, src)
    out = tmp_path / "int8.pt"
    assert main(["quantize-detector", "--weights", str(src), "--out", str(out), "--sequences", "1",
                 "--frames", "2"]) == 0
    written = load_checkpoint(out)
    assert all(torch.equal(written["model"][k], v) for k, v in data["model"].items())
    assert set(written["int8"]["table"]) == set(load_checkpoint(DEFAULT_WEIGHTS)["int8"]["table"])
    assert detector_from_checkpoint(written, backend="int8").backend == "int8"
    assert main(["quantize-detector", "--weights", str(tmp_path / "absent.pt"), "--out", str(out)]) == 2


def test_bench_detector_reports_both_networks(tmp_path):
    out = tmp_path / "bench.json"
    assert main(["bench", "detector", "--sizes", "128", "--repeats", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["reference"] == "reference float" and r["unit"] == "frames" and r["tiles"] == [[128, 128]]
    assert r["networks"] == ["reference float", "reference int8"] and r["fastest"] == "reference int8"
    assert r["ours_per_s"] == r["frames_per_s"]["reference int8"]
    assert r["ratio"] == r["ours_per_s"] / r["reference_per_s"]
    assert 0 < r["max_abs_diff"]["reference int8"]["heatmap_score"] < 0.5


def test_bench_detector_times_other_weights_against_the_reference(tmp_path):
    """Other weights (here a smaller network without a calibration) are timed in float beside the reference's."""
    cfg = DetectorConfig(model=ModelConfig(widths=(8, 16, 16), head=8, motion=4, fine=4))
    small = tmp_path / "small.pt"
    save_checkpoint(small, {"config": dataclasses.asdict(cfg), "model": Detector(cfg).net.state_dict()})
    out = tmp_path / "bench.json"
    assert main(["bench", "detector", "--sizes", "128", "--repeats", "1", "--weights", str(small),
                 "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["networks"] == ["reference float", "reference int8", "new float"]
    assert set(r["max_abs_diff"]) == {"reference int8"} and r["weights"] == str(small)
    assert r["ours_per_s"] == max(r["frames_per_s"][k] for k in ("reference int8", "new float"))
