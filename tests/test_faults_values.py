"""Values that mean nothing are refused before any work (issue 25): every bounded option of the typed
configurations (declared with ``torchtrack.config.option``) is enforced at its bound, from YAML (naming the
file and the dotted key) and from Python; command-line numbers are usage errors; the shipped presets load."""

import dataclasses
import math
import typing
from pathlib import Path

import pytest
import yaml

from torchtrack.cli import main
from torchtrack.config import Bounds, Checked, from_mapping, load_sections, preset_path, read_mapping
from torchtrack.detector.config import DetectorConfig, load_config
from torchtrack.errors import TorchtrackError
from torchtrack.filters.trackers.options import GMPHDConfig, GreedyConfig, PMBConfig, SORTConfig, load_tracker_configs
from torchtrack.pipeline.config import PipelineConfig, load_pipeline_config
from torchtrack.sim.maneuver import maneuvering
from torchtrack.sim.video_config import VideoConfig, load_video_config
from torchtrack.tuning.config import TuneSections, read_tune_config

CONFIGS = Path(__file__).resolve().parents[1] / "torchtrack" / "configs"
TOP = [GMPHDConfig, SORTConfig, GreedyConfig, PMBConfig, DetectorConfig, VideoConfig, PipelineConfig, TuneSections]
UNBOUNDED = {"VelocityMapOptions.origin", "PMBConfig.region", "TuneSections.seed"}
"""Numeric fields without a range of their own: a position anywhere, a rectangle checked across its items, any
seed."""


def _numeric(hint) -> bool:
    args = typing.get_args(hint)
    return hint in (int, float) or any(_numeric(a) for a in args if a is not bool and a is not Ellipsis)


def _fields(cls, path=()):
    """``(path of names, owner class, field, type hint)`` of every field below ``cls``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        nested = [t for t in (hints[f.name], *typing.get_args(hints[f.name])) if dataclasses.is_dataclass(t)]
        if nested:                                      # a section, or an optional one (``refine:``)
            yield from _fields(nested[0], path + (f.name,))
        else:
            yield path + (f.name,), cls, f, hints[f.name]


def _cases():
    """One case per bound: ``(top, dotted key, value refused, value accepted, companion values)``."""
    for top in TOP:
        for path, owner, f, hint in _fields(top):
            bounds = f.metadata.get("bounds")
            if bounds is None:
                continue
            default = getattr(owner(), f.name)
            whole = int in typing.get_args(hint) + (hint,)
            eps = 1 if whole else 1e-6
            key = ".".join(path)
            for name, sign, closed in (("ge", -1, True), ("gt", -1, False), ("le", 1, True), ("lt", 1, False)):
                bound = getattr(bounds, name)
                if bound is None:
                    continue
                outside = bound + sign * eps if closed else bound
                inside = bound if closed else bound - sign * eps
                if whole:
                    outside, inside = int(outside), int(inside)
                if isinstance(default, tuple):       # a lower bound on the first item, an upper one on the last
                    at = 0 if sign < 0 else len(default) - 1
                    bad, good = list(default), list(default)
                    bad[at], good[at] = outside, inside
                    yield pytest.param(top, key, bad, good, {}, f"{key}[{at}]", id=f"{key}-{name}")
                else:
                    companion = {"speed_median": inside / 2} if key == "speed_p90" else {}
                    yield pytest.param(top, key, outside, inside, companion, key, id=f"{key}-{name}")
            if bounds.one_of:
                yield pytest.param(top, key, "nonsense", bounds.one_of[-1], {}, key, id=f"{key}-one_of")


def _nested(key: str, value, companion: dict) -> dict:
    *parents, last = key.split(".")
    leaf = {last: value, **companion}
    for parent in reversed(parents):
        leaf = {parent: leaf}
    return leaf


@pytest.mark.parametrize("top, key, bad, good, companion, named", list(_cases()))
def test_every_bound_is_enforced_at_its_edge_naming_file_and_key(top, key, bad, good, companion, named):
    with pytest.raises(TorchtrackError) as caught:
        from_mapping(top, _nested(key, bad, companion), "t.yaml")
    message = str(caught.value)
    assert message.startswith(f"t.yaml: {named} must be ") and "\n" not in message
    built = from_mapping(top, _nested(key, good, companion), "t.yaml")
    value = built
    for part in key.split("."):
        value = getattr(value, part)
    assert list(value) == good if isinstance(good, list) else value == good


def test_every_numeric_option_carries_a_range():
    missing = [f"{owner.__name__}.{f.name}" for top in TOP for _, owner, f, hint in _fields(top)
               if _numeric(hint) and "bounds" not in f.metadata and f"{owner.__name__}.{f.name}" not in UNBOUNDED]
    assert missing == []
    assert all(issubclass(owner, Checked) for top in TOP if top is not TuneSections
               for _, owner, f, _ in _fields(top) if "bounds" in f.metadata)


def test_python_construction_is_checked_too():
    with pytest.raises(TorchtrackError, match=r"^SORTConfig\.max_age must be >= 0; got -1$"):
        SORTConfig(max_age=-1)
    with pytest.raises(TorchtrackError, match=r"^VideoConfig\.dropout_rate must be in \[0, 1\]; got 1\.5$"):
        dataclasses.replace(VideoConfig(), dropout_rate=1.5)
    with pytest.raises(TorchtrackError, match=r"p_detection must be a finite number; got nan"):
        from_mapping(GMPHDConfig, {"filter": {"p_detection": math.nan}})
    with pytest.raises(TorchtrackError, match=r"^VideoConfig\.park_gap must be a range \[low, high\] with low <= "
                                              r"high; got \[5\.0, 2\.0\]$"):
        VideoConfig(park_gap=(5.0, 2.0))


def test_bounds_describe_themselves():
    assert Bounds(ge=0, le=1).describe() == "in [0, 1]" and Bounds(gt=0, lt=1).describe() == "in (0, 1)"
    assert Bounds(gt=0).describe() == "> 0" and Bounds(ge=2).describe() == ">= 2"
    assert Bounds(multiple_of=16).problem("crop", 24) == ("crop", "must be a multiple of 16; got 24")
    assert Bounds(ge=1).problem("x", None) is None and Bounds(ge=1).problem("x", True) is None


def _write(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


def _one_error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    return lines[0]


def test_sort_max_age_below_zero(tmp_path):
    path = _write(tmp_path / "s.yaml", {"sort": {"max_age": -1}})
    with pytest.raises(TorchtrackError, match=rf"^{path}: sort\.max_age must be >= 0; got -1$"):
        load_tracker_configs(path)


def test_tune_steps_below_one_writes_nothing(tmp_path, capsys):
    cfg = {"filter": "kalman", "trainable": ["motion.q"], "data": {"simulate": {"sequences": 4, "steps": 20}},
           "optimizer": {"name": "lbfgs", "steps": -3}}
    path = _write(tmp_path / "tune.yaml", cfg)
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    assert _one_error_line(capsys) == f"torchtrack tune: error: {path}: optimizer.steps must be >= 1; got -3"
    assert not (tmp_path / "out").exists()
    cfg["optimizer"]["steps"] = 2                      # the same out of range through --set
    path = _write(tmp_path / "tune.yaml", cfg)
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out"), "--set", "optimizer.lr=0"]) == 2
    assert _one_error_line(capsys) == f"torchtrack tune: error: {path}: optimizer.lr must be > 0; got 0.0"
    with pytest.raises(TorchtrackError, match=r"early_stopping\.patience must be >= 1; got 0"):
        read_tune_config(path, ["early_stopping.patience=0"])


@pytest.mark.parametrize("config, key, value", [("tune-kalman", "q", "two"), ("tune-kalman", "dt", "fast"),
                                                ("tune-imm-formation", "measurement_sigma", "[1]")])
def test_a_model_option_that_is_not_a_number_names_its_key(config, key, value, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["tune", "--config", config, "--out", str(out), "--set", f"model.{key}={value}"]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"torchtrack tune: error: model.{key} must be a") and "got " in line
    assert not out.exists()


def test_a_camera_file_that_is_not_the_documented_object(tmp_path, capsys):
    import torch

    from torchtrack.sim.video import VideoConfig, write_sequence

    seq = write_sequence(VideoConfig(height=64, width=64, frames=2), torch.Generator().manual_seed(0), tmp_path / "s")
    camera = tmp_path / "camera.json"
    camera.write_text("[[[1, 0, 0], [0, 1, 0], [0, 0, 1]]]")          # the homographies without their object
    assert main(["track", "--frames", str(seq / "frames"), "--camera", str(camera), "--no-video",
                 "--out", str(tmp_path / "out")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"torchtrack track: error: {camera}: not a camera.json") and "a JSON list" in line


def test_maneuver_onset_after_the_last_scan(tmp_path, capsys):
    import torch

    with pytest.raises(TorchtrackError, match=r"^maneuver: onsets\[1\] must be a scan in \[1, 180\] \(scans\); "
                                              r"got 181$"):
        maneuvering(180, 1, 10.0, [60, 181], [90.0, -90.0], 3, 1.0, 0.01, 1.0, torch.Generator())
    doc = yaml.safe_load(preset_path("maneuver").read_text())
    doc["maneuver"]["onsets"] = [60, 200]
    path = _write(tmp_path / "m.yaml", doc)
    assert main(["scenario", "maneuver", "--config", str(path), "--runs", "1"]) == 2
    assert _one_error_line(capsys).endswith("onsets[1] must be a scan in [1, 180] (scans); got 200")


@pytest.mark.parametrize("section, key, value, reason", [
    ("data", "prior_drop", 1.5, "must be in [0, 1]; got 1.5"),
    ("data", "prior_drop", -0.1, "must be in [0, 1]; got -0.1"),
    ("decode", "threshold", 3, "must be in [0, 1); got 3.0"),
    ("train", "epochs", -1, "must be >= 1; got -1"),
    ("data", "crop", 72, "must be a multiple of 16; got 72"),
])
def test_detector_values(section, key, value, reason, tmp_path, capsys):
    path = _write(tmp_path / "d.yaml", {section: {key: value}})
    with pytest.raises(TorchtrackError) as caught:
        load_config(path)
    assert str(caught.value) == f"{path}: {section}.{key} {reason}"
    assert main(["train-detector", "--config", str(path), "--out", str(tmp_path / "run")]) == 2
    assert _one_error_line(capsys) == f"torchtrack train-detector: error: {path}: {section}.{key} {reason}"
    assert not (tmp_path / "run").exists()


def test_detector_video_overrides_are_checked_by_their_dotted_key(tmp_path):
    path = _write(tmp_path / "d.yaml", {"data": {"video": {"dropout_rate": 1.5}}})
    with pytest.raises(TorchtrackError, match=rf"^{path}: data\.video\.dropout_rate must be in \[0, 1\]; got 1\.5$"):
        load_config(path)


@pytest.mark.parametrize("argv, message", [
    (["train-detector", "--epochs", "-1"], "argument --epochs: must be >= 1; got -1"),
    (["train-detector", "--threads", "0"], "argument --threads: must be >= 1; got 0"),
    (["train-detector", "--epochs", "two"], "argument --epochs: must be a whole number; got 'two'"),
    (["tune", "--config", "tune-kalman", "--threads", "0"], "argument --threads: must be >= 1; got 0"),
    (["tune", "--config", "tune-kalman", "--folds", "1"], "argument --folds: must be >= 2; got 1"),
    (["eval", "--gt", "g", "--pred", "p", "--threshold", "-5"], "argument --threshold: must be > 0; got -5.0"),
    (["eval", "--gt", "g", "--pred", "p", "--iou", "1.5"], "argument --iou: must be in (0, 1]; got 1.5"),
    (["track", "--detections", "d", "--threshold", "-5"], "argument --threshold: must be > 0; got -5.0"),
    (["simulate-detections", "--gt", "g", "--pd", "1.5", "--out", "o"], "argument --pd: must be in [0, 1]; got 1.5"),
    (["simulate-detections", "--gt", "g", "--clutter", "nan", "--out", "o"],
     "argument --clutter: must be a finite number; got 'nan'"),
    (["simulate-video", "--frames", "0"], "argument --frames: must be >= 1; got 0"),
])
def test_command_line_numbers_are_usage_errors(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as caught:
        main(argv)
    assert caught.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_video_dropout_rate_above_one(tmp_path, capsys):
    path = _write(tmp_path / "v.yaml", {"video": {"dropout_rate": 1.5}})
    with pytest.raises(TorchtrackError, match=r"v\.yaml: video\.dropout_rate must be in \[0, 1\]; got 1\.5$"):
        load_video_config(path)
    assert main(["simulate-video", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    assert _one_error_line(capsys).endswith("dropout_rate must be in [0, 1]; got 1.5")
    assert not (tmp_path / "out").exists()


def test_pipeline_values_and_registration(tmp_path):
    path = _write(tmp_path / "p.yaml", {"pipeline": {"registration": {"min_inliers": 2}}})
    with pytest.raises(TorchtrackError, match=r"p\.yaml: registration\.min_inliers must be >= 4; got 2$"):
        load_pipeline_config(path)
    path = _write(tmp_path / "p.yaml", {"pipeline": {"trackers": {"sort": {"max_age": -1}}}})
    with pytest.raises(TorchtrackError, match=r"p\.yaml: trackers: sort\.max_age must be >= 0; got -1$"):
        load_pipeline_config(path)


def _load_preset(path: Path):
    name = path.stem
    if name.startswith("gmphd"):
        return load_tracker_configs(path)
    if name.startswith(("pipeline", "select")):
        return load_pipeline_config(path)
    if name.startswith("tune"):
        return read_tune_config(path)
    if name.startswith("wpafb"):
        from torchtrack.pipeline.wpafb_benchmark import BenchmarkConfig

        return BenchmarkConfig.from_mapping(read_mapping(path, "benchmark config"), str(path))
    loaders = {"detector": load_config, "video": load_video_config}
    if name in loaders:
        return loaders[name](path)
    return load_sections(path, name)               # the scenarios' presets


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_presets_all_load(path):
    assert _load_preset(path) is not None
